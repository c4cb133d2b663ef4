"""Covariance heads, consistency metrics and calibration (neural_estimator.serving.uncertainty)."""

from __future__ import annotations

import importlib.util
import json
import math

import numpy as np
import pytest
import torch

from neural_estimator import metrics as M
from neural_estimator.models import SystemDims, build_model
from neural_estimator.metrics import consistency as C
from neural_estimator.serving.uncertainty.heads import CholeskyHead, GaussianModel, HeadError, load_head, save_head

pytestmark = pytest.mark.usefixtures("one_torch_thread")

NAMES = ("gru", "lstm", "gpt2", "filterformer", "mamba", "mamba2")


# ---- consistency metrics against a Gaussian simulation whose coverage is known ----------------------
def _gaussian_nees(n: int, dx: int, claimed_factor: float, seed: int = 0) -> np.ndarray:
    """NEES of errors drawn from N(0, P) with a random SPD P, judged under claimed_factor * P."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(dx, dx))
    P = A @ A.T + 0.5 * np.eye(dx)
    e = rng.normal(size=(n, dx)) @ np.linalg.cholesky(P).T
    return M.nees(e[None], np.broadcast_to(claimed_factor * P, (1, n, dx, dx)))[0]


def test_coverage_of_a_consistent_covariance_is_each_nominal_level():
    eps = _gaussian_nees(40_000, 4, 1.0)
    curve = C.coverage_curve(eps, 4)
    # binomial standard error at n = 40000 is <= 0.0025: 0.01 is four of them
    np.testing.assert_allclose(curve, C.RELIABILITY_LEVELS, atol=0.01)
    assert C.calibration_error(curve) < 0.01
    assert abs(eps.mean() / 4 - 1) < 0.03


def test_coverage_matches_a_slow_reference_count():
    """The chi-square bound against counting, level by level, with scipy's own chi2.ppf."""
    from scipy.stats import chi2

    eps = _gaussian_nees(3_000, 3, 0.7, seed=2)
    curve = C.coverage_curve(eps, 3)
    for q, c in zip(C.RELIABILITY_LEVELS, curve):
        bound = chi2.ppf(q, 3)
        assert c == sum(1 for v in eps if v <= bound) / len(eps)


@pytest.mark.parametrize("factor", [0.25, 4.0])
def test_a_mis_scaled_covariance_is_caught_and_its_scale_recovered(factor):
    eps = _gaussian_nees(40_000, 5, factor)
    curve = C.coverage_curve(eps, 5)
    if factor < 1:  # over-confident: the truth falls outside more often than claimed
        assert curve[C.RELIABILITY_LEVELS.index(0.95)] < 0.7
        assert C.verdict(eps.mean() / 5, curve[-2]) == "over-confident"
    else:
        assert curve[C.RELIABILITY_LEVELS.index(0.95)] > 0.999
        assert C.verdict(eps.mean() / 5, curve[-2]) == "too wide"
    for target in C.SCALE_TARGETS:
        s = C.fit_scale(eps, 5, target)
        assert s == pytest.approx(1.0 / factor, rel=0.04)
        rescaled = C.coverage_curve(eps / s, 5)
        np.testing.assert_allclose(rescaled, C.RELIABILITY_LEVELS, atol=0.015)


def test_degenerate_covariances_count_as_not_covered():
    eps = np.array([1.0, 2.0, np.inf, np.inf])
    assert C.coverage_curve(eps, 2, [0.99])[0] == 0.5
    assert C.fit_scale(eps[:2], 2, "mean") == pytest.approx(0.75)
    with pytest.raises(C.ConsistencyError, match="levels"):
        C.coverage_curve(eps, 2, [1.0])
    with pytest.raises(C.ConsistencyError, match="target"):
        C.fit_scale(eps, 2, "median")


def test_verdict_bands_and_the_table():
    assert C.verdict(1.0, 0.95) == "consistent"
    assert C.verdict(3.0, 0.80) == "over-confident"
    assert C.verdict(0.1, 1.00) == "too wide"
    assert C.verdict(2.0, 0.99) == "mixed"
    assert C.verdict(None, None) == "—"
    assert C.verdict(1.3, 0.92, 0.32) == "mis-shaped"  # in both bands, but the curve is far off
    assert C.verdict(1.3, 0.92, 0.05) == "consistent"
    rows = {
        "ekf": C.consistency_row({"nees_median": 9.3, "nees": 10.2, "coverage95": 0.95}, 10, C.RELIABILITY_LEVELS),
        "gru": C.consistency_row({"nees_median": None, "nees": None, "coverage95": None}, 10),
    }
    assert rows["ekf"]["nees_mean_per_dim"] == pytest.approx(1.02) and rows["ekf"]["calibration_error"] == 0.0
    table = C.format_consistency_table(rows)
    assert "| ekf | 0.93 | 1.02 | 0.950 | 0.000 | 0.500/0.900/0.990 | consistent |" in table  # a curve: 50/90/99 %
    assert "| gru | — | — | — | — | — | — |" in table


# ---- the head -------------------------------------------------------------------------------------------
def test_cholesky_head_covariance_and_nll_against_torch_distributions():
    torch.manual_seed(0)
    head = CholeskyHead(7, 4).double()
    with torch.no_grad():
        head.linear.weight.normal_(0, 0.3)
        head.linear.bias.normal_(0, 0.3)
        head.unit.copy_(torch.tensor([1.0, 2.0, 0.5, 3.0]))
    h, e = torch.randn(50, 7, dtype=torch.float64), torch.randn(50, 4, dtype=torch.float64)
    cov = head(h)
    assert torch.allclose(cov, cov.transpose(-1, -2)) and torch.linalg.eigvalsh(cov).min() > 0
    mvn = torch.distributions.MultivariateNormal(torch.zeros(4, dtype=torch.float64), covariance_matrix=cov)
    nll_ref = -mvn.log_prob(e).mean() - 2 * math.log(2 * math.pi)  # the head leaves out (dx / 2) log 2 pi
    with torch.no_grad():
        nll = float(head.nll(h, e))
    assert nll == pytest.approx(float(nll_ref.detach()), rel=1e-9)
    head.scale.fill_(3.0)
    assert torch.allclose(head(h), 3.0 * cov)
    head.shrink = 0.1  # correlations shrunk towards zero, variances kept
    shrunk = head(h)
    assert torch.allclose(torch.diagonal(shrunk, dim1=-2, dim2=-1), torch.diagonal(3.0 * cov, dim1=-2, dim2=-1))
    off = ~torch.eye(4, dtype=torch.bool)
    assert torch.allclose(shrunk[:, off], 0.9 * 3.0 * cov[:, off])


@pytest.mark.parametrize("name", NAMES)
def test_gaussian_model_keeps_the_estimate_and_steps_as_it_runs(name):
    """forward_with_cov's mean is the trunk's forward bit for bit; a loop of step_with_cov equals it."""
    torch.manual_seed(0)
    trunk = build_model(name, SystemDims(dx=3, dy=5), **({"decode_chunk": 16} if name == "gpt2" else {})).eval()
    head = CholeskyHead(trunk.features(torch.zeros(1, 1, 5)).shape[-1], 3)
    with torch.no_grad():
        head.linear.weight.normal_(0, 0.2)
    gm = GaussianModel(trunk, head).eval()
    z = torch.randn(2, 40, 5)
    with torch.inference_mode():
        mean, cov = gm.forward_with_cov(z)
        assert torch.equal(mean, trunk(z))
        state, ms, cs = gm.init_state(2), [], []
        for t in range(z.shape[1]):
            m, c, state = gm.step_with_cov(z[:, t], state)
            ms.append(m)
            cs.append(c)
    torch.testing.assert_close(torch.stack(ms, 1), mean, rtol=0, atol=2e-5)
    torch.testing.assert_close(torch.stack(cs, 1), cov, rtol=1e-4, atol=1e-5)
    assert gm.cfg is trunk.cfg  # everything else comes from the trunk


def _estimator_with_head(tmp_path, method="gru", **kwargs):
    """A tiny untrained model of ``method`` for nlink saved as a checkpoint with a covariance head."""
    from neural_estimator.data import simulate
    from neural_estimator.serving.card import CARD_FILE, read_card, write_json
    from neural_estimator.serving.checkpoint import save_checkpoint
    from neural_estimator.serving.normalization import Normalizer
    from neural_estimator.serving.load import load_neural_estimator
    from neural_estimator.scenarios import make_scenario

    scenario = make_scenario("nlink")
    data = simulate(scenario, 3, 30, seed=3)
    norm = Normalizer.from_data(scenario, data)
    torch.manual_seed(0)
    model = build_model(method, scenario)
    save_checkpoint(tmp_path, model, norm, {"scenario": scenario.describe()})
    head = CholeskyHead(model.features(torch.zeros(1, 1, norm.d_in)).shape[-1], scenario.dx)
    with torch.no_grad():
        head.linear.weight.normal_(0, 0.2)
    _, card = read_card(tmp_path)
    plain = load_neural_estimator(method, scenario, tmp_path, **kwargs)
    card["covariance_head"] = save_head(tmp_path, head, {"calibration": {"scale": 1.0}})
    write_json(tmp_path / CARD_FILE, card)
    return scenario, data, plain, load_neural_estimator(method, scenario, tmp_path, **kwargs)


@pytest.mark.parametrize(
    "method,kwargs", [("gru", {}), ("gru", {"context": 8, "context_copies": 2}), ("filterformer", {})]
)
def test_estimator_with_a_head_reports_covariance_in_step_and_run(tmp_path, method, kwargs):
    """A card with a head serves its covariance (bounded context included); run equals a loop of
    step for the covariance too; the estimate is the model's without the head, bit for bit."""
    scenario, data, plain, est = _estimator_with_head(tmp_path, method, **kwargs)
    assert est.has_covariance
    whole = est.run(data.y, data.u)
    assert np.array_equal(whole.x, plain.run(data.y, data.u).x)
    assert whole.cov.shape == data.x.shape + (scenario.dx,)
    assert np.linalg.eigvalsh(whole.cov).min() > 0
    est.reset(3)
    xs, covs = [], []
    for t in range(data.y.shape[1]):
        xs.append(est.step(data.y[:, t], data.u[:, t - 1] if t else None))
        covs.append(est.covariance)
    np.testing.assert_allclose(np.stack(xs, 1), whole.x, rtol=0, atol=1e-4 * np.abs(whole.x).max())
    np.testing.assert_allclose(np.stack(covs, 1), whole.cov, rtol=1e-3, atol=1e-6 * np.abs(whole.cov).max())


def test_a_card_without_a_head_serves_as_before_and_a_bad_head_is_refused(tmp_path):
    from neural_estimator.methods.interface import EstimatorError
    from neural_estimator.serving.card import CARD_FILE
    from neural_estimator.serving.load import load_neural_estimator

    scenario, data, plain, est = _estimator_with_head(tmp_path)
    assert not plain.has_covariance and plain.run(data.y, data.u).cov is None
    assert not load_neural_estimator("gru", scenario, tmp_path, covariance=False).has_covariance
    (tmp_path / "covariance_head.safetensors").write_bytes(b"not a head")
    with pytest.raises(EstimatorError, match="sha256"):
        load_neural_estimator("gru", scenario, tmp_path)
    card = json.loads((tmp_path / CARD_FILE).read_text())
    with pytest.raises(HeadError, match="inside the checkpoint"):
        load_head(tmp_path, {**card["covariance_head"], "file": "../x"}, scenario.dx)
    with pytest.raises(HeadError, match="shrink must be in"):
        load_head(tmp_path, {**card["covariance_head"], "sha256": None, "shrink": 1.5}, scenario.dx)


# ---- calibration of any method: cov_scale ------------------------------------------------------------
def test_cov_scale_multiplies_the_reported_covariance_of_a_filter_in_step_and_run():
    from neural_estimator.data import simulate
    from neural_estimator.methods.registry import EstimatorError, make_estimator
    from neural_estimator.scenarios import make_scenario

    scenario = make_scenario("ballistic")
    data = simulate(scenario, 2, 12, seed=1)
    plain, scaled = make_estimator("ekf", scenario), make_estimator("ekf", scenario, cov_scale="2.5")
    a, b = plain.run(data.y, data.u), scaled.run(data.y, data.u)
    assert np.array_equal(a.x, b.x)
    np.testing.assert_allclose(b.cov, 2.5 * a.cov, rtol=1e-15)
    scaled.reset(2)
    for t in range(12):
        scaled.step(data.y[:, t], data.u[:, t - 1] if t else None)
    np.testing.assert_allclose(scaled.covariance, b.cov[:, -1], rtol=1e-15)
    with pytest.raises(EstimatorError, match="cov_scale must be a finite number > 0"):
        make_estimator("pf", scenario, cov_scale=0)


def test_evaluate_reports_a_consistency_table_and_the_reliability_curve():
    from neural_estimator.evaluation import consistency_table, evaluate
    from neural_estimator.scenarios import make_scenario

    scenario = make_scenario("ballistic")
    results = evaluate(
        scenario,
        ["ekf"],
        trajectories=6,
        horizon=30,
        seed=777,
        sets=1,
        cache_dir=False,
        progress=False,
        options={"ekf": {"cov_scale": 100.0}},
    )
    rep = results["ekf"].reports[0]
    assert len(rep.coverage_curve) == len(C.RELIABILITY_LEVELS)
    assert rep.coverage_curve[C.RELIABILITY_LEVELS.index(0.95)] == pytest.approx(rep.coverage95)
    table = consistency_table(results, scenario.dx)
    assert "| ekf |" in table and "too wide" in table  # a covariance 100 times too large


def test_the_live_path_publishes_the_heads_covariance(tmp_path):
    """The node's per-message path (OnlineEstimator) of a neural model with a head carries its
    covariance in every result and builds the covariance message (no 'not estimated' diagonal)."""
    from neural_estimator.stream import messages as MSG
    from neural_estimator.stream.online import OnlineEstimator

    scenario, data, plain, est = _estimator_with_head(tmp_path)
    online = OnlineEstimator(est, "gru")
    assert online.publish_covariance and not OnlineEstimator(plain, "gru").publish_covariance
    codec = MSG.VectorCodec(scenario.name, MSG.observation_labels(scenario))
    est_ref = est.run(data.y[:1, :5], data.u[:1, :5])
    for k in range(5):
        u_prev = data.u[0, k - 1] if k else np.zeros(scenario.du)
        (res,) = online.feed(codec.encode(1000 + k, 0, k, np.concatenate([data.y[0, k], u_prev])))
        assert res.status == "estimated" and res.covariance is not None
        np.testing.assert_allclose(res.P, est_ref.cov[0, k], rtol=1e-3, atol=1e-7)


def test_the_reproduce_report_has_the_consistency_table():
    from neural_estimator.paper.reproduce import tables as R

    summ = {
        "lorenz96": {
            "ekf": M.summarize([{"nees_median": 9.3, "nees": 10.1, "coverage95": 0.95}]),
            "gru": M.summarize([{"nees_median": None, "nees": None, "coverage95": None}]),
            "pf": M.summarize([{"nees_median": 900.0, "nees": 1e6, "coverage95": 0.01}]),
        }
    }
    lines = R.consistency_table(summ, ["lorenz96"], ["ekf", "gru", "pf"], {"lorenz96": 10})
    assert lines[0].startswith("| Method | lorenz96 NEES mean/dx | lorenz96 verdict |")
    assert "| EKF | 1.01 | consistent |" in lines and "| PF | 100,000.0 | over-confident |" in lines
    assert not any(line.startswith("| GRU") for line in lines)  # no covariance: no row


def test_the_band_scale_trades_the_tail_for_the_bulk_on_heavy_tailed_errors():
    """Student-t errors: no Gaussian scale is right everywhere. The band scale keeps the 95 %
    coverage inside its fitting band and has a smaller calibration error than the exact-95 % one."""
    rng = np.random.default_rng(0)
    eps = (rng.standard_t(3, size=(100_000, 4)) ** 2).sum(axis=1)
    exact, band = (C.fit_scale(eps, 4, t) for t in ("coverage", "band"))
    c_exact, c_band = C.coverage_curve(eps / exact, 4), C.coverage_curve(eps / band, 4)
    assert c_exact[C.RELIABILITY_LEVELS.index(0.95)] == pytest.approx(0.95, abs=1e-3)
    assert C.FIT_BAND[0] - 1e-3 <= c_band[C.RELIABILITY_LEVELS.index(0.95)] <= C.FIT_BAND[1] + 1e-3
    assert C.calibration_error(c_band) < C.calibration_error(c_exact) - 0.03


def test_the_calibrated_settings_are_options_every_filter_takes():
    from neural_estimator.methods.registry import make_estimator
    from neural_estimator.scenarios import make_scenario
    from neural_estimator.serving.uncertainty.calibrated import calibrated_options

    scenario = make_scenario("nlink")
    for method in ("ekf", "ukf", "enkf", "pf"):
        opts = calibrated_options("nlink", method)
        assert opts.get("cov_scale", 1.0) > 0
        est = make_estimator(method, scenario, **opts)
        assert est.cov_scale == opts.get("cov_scale", 1.0)
    assert calibrated_options("nlink", "gru") == {}


def test_every_calibrated_filter_setting_was_chosen_on_its_scenarios_default_constants():
    """A setting chosen on other constants (before a recalibration moved the defaults) would be
    served at the defaults without a word: the file records the preset, and it must be today's."""
    import json
    from pathlib import Path

    from neural_estimator.paper import PAPER_SCENARIOS
    from neural_estimator.scenarios import default_preset
    from neural_estimator.serving.uncertainty.calibrated import CALIBRATED_FILE

    spec = importlib.util.spec_from_file_location(
        "calibrate_covariances", Path(__file__).resolve().parents[1] / "scripts" / "calibrate_covariances.py"
    )
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    MAX_SCALE = script.MAX_SCALE
    table = json.loads(CALIBRATED_FILE.read_text())
    assert set(table) == set(PAPER_SCENARIOS)
    for scenario, methods in table.items():
        assert set(methods) == {"ekf", "ukf", "enkf", "pf"}, scenario
        for method, entry in methods.items():
            assert entry["validation"]["preset"] == default_preset(scenario), (scenario, method)
            # no scale that only dresses a degenerate covariance (scripts/calibrate_covariances.py)
            assert 0 < entry["options"].get("cov_scale", 1.0) <= MAX_SCALE, (scenario, method)


def test_new_weights_in_a_checkpoint_drop_the_old_covariance_head(tmp_path):
    """A head fitted on other weights is removed when a checkpoint is written over (retraining):
    the new card has no head and the directory holds no stale head file."""
    from neural_estimator.serving.checkpoint import save_checkpoint
    from neural_estimator.serving.normalization import Normalizer

    scenario, data, plain, est = _estimator_with_head(tmp_path)
    assert (tmp_path / "covariance_head.safetensors").is_file()
    old_card = json.loads((tmp_path / "card.json").read_text())  # passed on whole, as a fine-tuning would
    save_checkpoint(tmp_path, plain.model, Normalizer.from_data(scenario, data), old_card)
    assert not (tmp_path / "covariance_head.safetensors").exists()
    assert "covariance_head" not in json.loads((tmp_path / "card.json").read_text())


def test_the_onnx_backend_serves_the_heads_covariance_too():
    """A shipped model with a covariance head on ONNX Runtime (the head exported with the step): the
    estimate and the covariance of torch's step, to float32 round-off."""
    pytest.importorskip("onnxruntime")
    from neural_estimator.methods.registry import make_estimator
    from neural_estimator.scenarios import make_scenario

    scenario = make_scenario("lorenz96")
    torch_est, ort_est = make_estimator("gru", scenario), make_estimator("gru", scenario, backend="onnxruntime")
    assert ort_est.has_covariance
    Y = np.random.default_rng(0).normal(size=(6, 1, 10))
    torch_est.reset(1)
    ort_est.reset(1)
    for y in Y:
        np.testing.assert_allclose(ort_est.step(y), torch_est.step(y), rtol=0, atol=1e-5)
        np.testing.assert_allclose(ort_est.covariance, torch_est.covariance, rtol=1e-4, atol=1e-9)
