"""What a team decides on: per-component RMSE, the baselines, the paired ratio and its interval, and
the median over trained instances of a network."""

import json
import math
from pathlib import Path

import numpy as np
import pytest

from neural_estimator import metrics as M
from neural_estimator.cli import main
from neural_estimator.evaluation import evaluate
from neural_estimator.evaluation import comparison as C
from neural_estimator.scenarios import make_scenario

PLUGIN = ["--plugin", "examples/custom_scenario.py"]


@pytest.fixture(autouse=True)
def _repo_cwd(monkeypatch, tmp_path):
    monkeypatch.chdir(Path(__file__).resolve().parents[1])
    monkeypatch.setenv("NEURAL_ESTIMATOR_CACHE", str(tmp_path / "cache"))


def _errors(rng, n=60, t=30, dx=3, scale=(1.0, 10.0, 0.1), outliers=2):
    x = rng.standard_normal((n, t, dx))
    e = rng.standard_normal((n, t, dx)) * np.asarray(scale)
    e[:outliers] *= 1e3  # trajectories the outlier rule drops
    return x, x + e


# ---- components ---------------------------------------------------------------------------------------


def test_aggregate_squared_is_the_mean_of_the_squared_components():
    rng = np.random.default_rng(3)
    x, xh = _errors(rng)
    rep = M.compute_metrics(x, xh, warmup=4)
    assert rep.n_outliers == 2  # the dropped trajectories are out of both sides
    comps = np.asarray(rep.rmse_components)
    assert comps.shape == (3,)
    assert rep.rmse**2 == pytest.approx(np.mean(comps**2), rel=1e-12)
    # in their own units: the component with 10x the error has about 10x the RMSE
    assert 8 < comps[1] / comps[0] < 12 and 8 < comps[0] / comps[2] < 12
    # the per-trajectory errors give the same figures, for the paired bootstrap
    errs = M.trajectory_errors(x, xh, (), rep.outlier_idx, warmup=4)
    assert M.run_rmse(errs) == pytest.approx(rep.rmse, rel=1e-12)
    assert M.run_rmse(errs, full=True) == pytest.approx(rep.full_rmse, rel=1e-12)
    for d in range(3):
        assert M.run_rmse(errs, components=[d]) == pytest.approx(comps[d], rel=1e-12)


def test_components_of_angles_are_wrapped():
    x = np.zeros((4, 5, 2))
    xh = x.copy()
    xh[..., 0] = 2 * np.pi - 0.1  # an angle error of -0.1, not 6.18
    xh[..., 1] = 0.2
    rep = M.compute_metrics(x, xh, angle_states=(0,), spread=1.0)
    assert rep.rmse_components == pytest.approx((0.1, 0.2))


# ---- the paired ratio ---------------------------------------------------------------------------------


def _run(rng, n, scale, kept_all=True):
    mse = (rng.standard_normal((n, 2)) * scale) ** 2 + 0.01
    return M.TrajectoryErrors(mse, np.ones(n, dtype=bool))


def test_paired_interval_contains_its_ratio_and_judges_by_it():
    rng = np.random.default_rng(0)
    n = 300
    ref = [[_run(rng, n, 1.0)] for _ in range(3)]
    same = [[M.TrajectoryErrors(r[0].mse.copy(), r[0].kept.copy())] for r in ref]
    ratio, (lo, hi) = M.paired_ratio(same, ref)
    assert ratio == 1.0 and lo == hi == 1.0  # paired: the same errors give no spread at all
    assert M.verdict((lo, hi)) == "tied"
    worse = [[M.TrajectoryErrors(r[0].mse * 4.0, r[0].kept)] for r in ref]  # twice the RMSE
    ratio, (lo, hi) = M.paired_ratio(worse, ref)
    assert ratio == pytest.approx(2.0) and lo == pytest.approx(2.0) and hi == pytest.approx(2.0)
    # independent noise of the same size: the ratio is near 1 and inside its interval, which holds 1
    other = [[_run(rng, n, 1.0)] for _ in range(3)]
    ratio, (lo, hi) = M.paired_ratio(other, ref)
    assert lo <= ratio <= hi and lo < 1.0 < hi and M.verdict((lo, hi)) == "tied"
    # a method 20 % better with its own noise is "better"
    better = [[M.TrajectoryErrors(o[0].mse * 0.64, o[0].kept)] for o in other]
    ratio, (lo, hi) = M.paired_ratio(better, ref)
    assert lo <= ratio <= hi < 1.0 and M.verdict((lo, hi)) == "better"


def test_paired_ratio_resamples_instances():
    """Three instances of which one is twice as bad: the interval widens with the instance draw."""
    rng = np.random.default_rng(1)
    n = 400
    ref = [[_run(rng, n, 1.0)] for _ in range(2)]
    one = [[M.TrajectoryErrors(r[0].mse * 1.21, r[0].kept)] for r in ref]
    three = [
        [M.TrajectoryErrors(r[0].mse * f, r[0].kept) for f in (1.0, 1.21, 4.0)] for r in ref
    ]  # instances at RMSE ratio 1, 1.1, 2
    r1, ci1 = M.paired_ratio(one, ref)
    r3, ci3 = M.paired_ratio(three, ref)
    assert r1 == pytest.approx(1.1) and r3 == pytest.approx(1.1)  # the median instance
    assert ci3[0] <= r3 <= ci3[1] and ci3[1] - ci3[0] > 10 * (ci1[1] - ci1[0])


def test_a_perfect_reference_gives_no_ratio():
    exact = [[M.TrajectoryErrors(np.zeros((5, 2)), np.ones(5, dtype=bool))]]
    some = [[M.TrajectoryErrors(np.ones((5, 2)), np.ones(5, dtype=bool))]]
    ratio, ci = M.paired_ratio(some, exact)
    assert math.isnan(ratio) and all(math.isnan(v) for v in ci) and M.verdict(ci) == "unknown"


def test_a_diverged_method_is_worse_on_the_full_rmse():
    rng = np.random.default_rng(8)
    ref = [[_run(rng, 20, 1.0)]]
    mse = ref[0][0].mse.copy()
    mse[3] = np.inf  # one diverged trajectory: dropped from the RMSE, infinite in the Full RMSE
    kept = np.ones(20, dtype=bool)
    kept[3] = False
    diverged = [[M.TrajectoryErrors(mse, kept)]]
    ratio, ci = M.paired_ratio(diverged, ref, full=True)
    assert ratio == math.inf and ci == (math.inf, math.inf) and M.verdict(ci) == "worse"
    ratio, ci = M.paired_ratio(diverged, ref)  # on the kept trajectories it is finite
    assert math.isfinite(ratio) and ci[0] <= ratio <= ci[1]


def test_a_partial_result_with_uneven_instances_is_pending_not_a_crash():
    """While an evaluation runs, one set can hold three instances and the next one: the paired ratio
    refuses it in one line, and the decision table (written after every run) shows it as pending."""
    from neural_estimator.evaluation.protocol import MethodResult

    rng = np.random.default_rng(11)
    ref = [[_run(rng, 30, 1.0)] for _ in range(2)]
    uneven = [[_run(rng, 30, 1.0) for _ in range(3)], [_run(rng, 30, 1.0)]]
    with pytest.raises(M.MetricsError, match=r"same trained instances in every set, got \[3, 1\] per set"):
        M.paired_ratio(uneven, ref)
    x = rng.standard_normal((30, 12, 2))
    results = {"ekf": MethodResult("ekf"), "gru": MethodResult("gru")}
    for m, runs in (("ekf", [(0, 0), (1, 0)]), ("gru", [(0, 0), (0, 1), (0, 2), (1, 0)])):
        for j, k in runs:
            xh = x + rng.standard_normal(x.shape)
            rep = M.compute_metrics(x, xh)
            results[m].add(rep, M.trajectory_errors(x, xh, (), rep.outlier_idx), set_index=j, instance=k)
    pairs = C.paired(results)
    assert pairs["gru"] is None and pairs["ekf"]["verdict"] == "reference"


def test_the_geometric_ratio_weighs_each_component_alike_on_aligned_replicates():
    """Two components in very different units: the RMSE over both follows the large one, the
    geometric mean of the two ratios does not; its replicates are the components' own, aligned."""
    rng = np.random.default_rng(5)
    n = 300

    def run(scale_a, scale_b):
        mse = np.stack([rng.standard_normal(n) ** 2 * scale_a + 1e-3, rng.standard_normal(n) ** 2 * scale_b], axis=1)
        return M.TrajectoryErrors(mse * np.array([1e6, 1.0]), np.ones(n, dtype=bool))  # metres beside km

    ref = [[run(1.0, 1.0)] for _ in range(2)]
    # the network: 1.21x the squared error on the large component (1.1x RMSE), 16x on the small (4x)
    net = [[M.TrajectoryErrors(r[0].mse * np.array([1.21, 16.0]), r[0].kept)] for r in ref]
    aggregate, _ = M.paired_ratio(net, ref)
    g, (lo, hi) = M.paired_geometric_ratio(net, ref, [0, 1])
    ratios = [M.paired_ratio(net, ref, components=[d])[0] for d in (0, 1)]
    assert ratios == [pytest.approx(1.1), pytest.approx(4.0)]
    assert aggregate == pytest.approx(1.1, rel=1e-3)  # the small component is invisible in the sum
    assert g == pytest.approx(math.sqrt(1.1 * 4.0)) and lo == pytest.approx(g) and hi == pytest.approx(g)
    # one component: exactly the paired ratio and its interval
    other = [[run(1.0, 1.0)] for _ in range(2)]
    assert M.paired_geometric_ratio(other, ref, [1]) == M.paired_ratio(other, ref, components=[1])
    # the same component twice: the replicates align, so the interval is the component's, not narrower
    one = M.paired_ratio(other, ref, components=[1])[1]
    assert M.paired_geometric_ratio(other, ref, [1, 1])[1] == pytest.approx(one)
    g, (lo, hi) = M.paired_geometric_ratio(other, ref, [0, 1])
    assert lo <= g <= hi and lo < 1.0 < hi
    with pytest.raises(M.MetricsError, match="at least one component"):
        M.paired_geometric_ratio(other, ref, [])


def test_the_geometric_ratio_of_a_diverged_component_is_infinite():
    rng = np.random.default_rng(9)
    ref = [[_run(rng, 20, 1.0)]]
    mse = ref[0][0].mse.copy()
    mse[3, 1] = np.inf
    diverged = [[M.TrajectoryErrors(mse, np.ones(20, dtype=bool))]]
    g, ci = M.paired_geometric_ratio(diverged, ref, [0, 1])
    assert g == math.inf and ci == (math.inf, math.inf) and M.verdict(ci) == "worse"
    exact = [[M.TrajectoryErrors(np.zeros((20, 2)), np.ones(20, dtype=bool))]]
    g, ci = M.paired_geometric_ratio(ref[0:1], exact, [0, 1])
    assert math.isnan(g) and M.verdict(ci) == "unknown"


def test_paired_ratio_refuses_unpaired_sets():
    rng = np.random.default_rng(2)
    with pytest.raises(M.MetricsError, match="same sets"):
        M.paired_ratio([[_run(rng, 10, 1.0)]], [[_run(rng, 10, 1.0)], [_run(rng, 10, 1.0)]])
    with pytest.raises(M.MetricsError, match="same trajectories"):
        M.paired_ratio([[_run(rng, 10, 1.0)]], [[_run(rng, 12, 1.0)]])


# ---- the baselines ------------------------------------------------------------------------------------


def test_openloop_equals_a_hand_computation_on_the_quadrotor():
    """Prior mean, then x_{k+1} = f(x_k, u_k) with the recorded controls and no observation."""
    from neural_estimator.data import simulate

    sc = make_scenario("quadrotor")
    data = simulate(sc, n=4, horizon=25, seed=5)
    assert np.abs(data.u).max() > 0  # the controls matter
    res = evaluate(sc, ["openloop"], datasets=[data], cache_dir=False, progress=False, warmup=0)
    x = np.broadcast_to(sc.prior()[0], (4, sc.dx)).copy()
    hand = np.empty_like(data.x)
    for k in range(data.horizon):
        hand[:, k] = x
        x = sc.normalize_state(sc.f(x, data.u[:, k]))
    err = hand - data.x
    err[..., list(sc.angle_states)] = (err[..., list(sc.angle_states)] + np.pi) % (2 * np.pi) - np.pi
    rep = res["openloop"].reports[0]
    assert rep.full_rmse == pytest.approx(float(np.sqrt(np.mean(err**2))), rel=1e-10)
    kept = np.setdiff1d(np.arange(4), rep.outlier_idx)  # the components are over the kept trajectories
    assert rep.rmse_components == pytest.approx(tuple(np.sqrt(np.mean(err[kept] ** 2, axis=(0, 1)))), rel=1e-10)
    assert res["openloop"].baseline and not res["openloop"].reports[0].has_covariance


def test_obsonly_reads_the_observation_where_h_is_invertible_and_is_refused_elsewhere():
    from neural_estimator.filters.baselines import make_baseline
    from neural_estimator.data import simulate
    from neural_estimator.methods.interface import EstimatorError

    sc = make_scenario("lorenz96")
    data = simulate(sc, n=2, horizon=6, seed=1)
    est = make_baseline("obsonly", sc).run(data.y, data.u)
    assert np.array_equal(est.x, data.y)  # H = I: x = y
    nl = make_scenario("nlink")
    d = simulate(nl, n=2, horizon=4, seed=1)
    x = make_baseline("obsonly", nl).run(d.y, d.u).x
    n = nl.dx // 2
    assert np.allclose(nl.h(x)[..., :], nl.h(np.concatenate([x[..., :n], d.x[..., n:]], axis=-1)))
    with pytest.raises(EstimatorError, match="determines no state component"):
        make_baseline("obsonly", make_scenario("bearings"))


def test_evaluate_json_has_components_and_paired_for_every_method(capsys):
    argv = ["evaluate", "--scenario", "ballistic", "--methods", "ekf,ukf,openloop", "--trajectories", "24"]
    assert main(argv + ["--sets", "2", "--horizon", "60", "--quiet", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["components"] == ["altitude", "velocity", "drag_coefficient"]
    assert res["reference"] in ("ekf", "ukf")
    for m, entry in res["methods"].items():
        assert len(entry["rmse_components"]) == 3, m
        p = entry["paired"]
        assert p["reference"] == res["reference"] and p["ci95"][0] <= p["ratio"] <= p["ci95"][1]
    assert res["methods"]["openloop"]["reference_row"] is True
    assert res["methods"]["openloop"]["paired"]["verdict"] == "worse"
    # the table prints them: the components in their units, the ratio column, the reference row
    assert main(argv + ["--sets", "2", "--horizon", "60", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "altitude [km]" in out and "openloop (reference row)" in out and "[95% CI]" in out
    # obsonly where h determines nothing: one line, before any simulation
    assert main(["evaluate", "--scenario", "bearings", "--methods", "obsonly", "--quiet"]) == 2
    assert "determines no state component" in capsys.readouterr().err


def test_not_estimated_flags_a_component_no_method_improves():
    """A method that copies the open loop on one component and halves its error on the other."""
    from neural_estimator.evaluation.protocol import MethodResult

    rng = np.random.default_rng(4)
    x = rng.standard_normal((50, 20, 2))
    base = x + rng.standard_normal(x.shape)
    good = base.copy()
    good[..., 0] = x[..., 0] + 0.5 * (base[..., 0] - x[..., 0])
    results = {}
    for name, xh in (("openloop", base), ("ekf", good)):
        r = MethodResult(name)
        rep = M.compute_metrics(x, xh)
        r.add(rep, M.trajectory_errors(x, xh, (), rep.outlier_idx))
        results[name] = r
    assert C.not_estimated(results) == [False, True]
    assert C.reference_method(results) == "ekf"  # a baseline is never the reference
    del results["openloop"]
    assert C.not_estimated(results) is None


# ---- trained instances --------------------------------------------------------------------------------


def _train(out: Path, init_seed: int) -> Path:
    argv = ["train", *PLUGIN, "--scenario", "oscillator", "--model", "gru", "--out", str(out)]
    argv += ["--trajectories", "24", "--train-length", "120", "--val-trajectories", "8", "--epochs", "1"]
    argv += ["--windows-per-epoch", "16", "--init-seed", str(init_seed), "--quiet", "--no-keep-resume"]
    assert main(argv) == 0
    return out


def test_instances_are_found_run_and_summarised_by_their_median(tmp_path, monkeypatch, capsys):
    from neural_estimator.scenarios import make_scenario as make
    from neural_estimator.serving import instances as I

    zoo = tmp_path / "zoo"
    _train(zoo / "oscillator-gru", 0)
    _train(zoo / "instances" / "i1" / "oscillator-gru", 1)
    _train(zoo / "instances" / "i2" / "oscillator-gru", 2)
    (zoo / "instances" / "i3" / "oscillator-gru").mkdir(parents=True)  # incomplete: not an instance
    found = I.zoo_instances("oscillator", "gru", zoo)
    assert [I.instance_number(p) for p in found] == [0, 1, 2]
    monkeypatch.setattr(I, "ZOO_DIR", zoo)  # evaluate finds the instances of a pair in the zoo
    from neural_estimator.scenarios import load_plugins

    load_plugins(["examples/custom_scenario.py"])
    sc = make("oscillator")
    res = evaluate(sc, ["ukf", "gru"], trajectories=12, horizon=40, sets=2, cache_dir=False, progress=False)
    gru = res["gru"]
    assert gru.n_instances == 3 and len(gru.reports) == 6 and sorted(set(gru.instance)) == [0, 1, 2]
    per_instance = C.instance_spread(gru)
    assert len(per_instance) == 3 and len(set(per_instance)) == 3  # three different networks
    assert gru.summary["rmse"].median == pytest.approx(float(np.median([r.rmse for r in gru.reports])))
    p = C.paired(res)["gru"]
    assert p["instances"] == 3 and p["ci95"][0] <= p["ratio"] <= p["ci95"][1]
    from neural_estimator.evaluation.decision import decision_table

    table = decision_table(sc, res)
    assert "3 (RMSE" in table and "1 instance" not in table
    # the shipped model alone says so
    one = evaluate(sc, ["gru"], checkpoints={"gru": [found[0]]}, trajectories=12, horizon=40, sets=1)
    assert one["gru"].n_instances == 1 and "1 instance" in decision_table(sc, one)
    assert math.isfinite(one["gru"].summary["rmse"].median)


def test_metrics_verb_prints_the_components_of_given_estimates(tmp_path, capsys):
    from neural_estimator.data import load_trajectories, save_estimates

    truth = tmp_path / "truth.npz"
    main(
        [
            "simulate",
            *PLUGIN,
            "--scenario",
            "oscillator",
            "--trajectories",
            "20",
            "--horizon",
            "16",
            "--out",
            str(truth),
        ]
    )
    data, _ = load_trajectories(truth)
    err = np.zeros_like(data.x)
    err[..., 0] = 0.5  # an error on the first component only
    save_estimates(tmp_path / "a.npz", data, data.x + err, "biased")
    save_estimates(tmp_path / "b.npz", data, data.x + 2 * err, "worse")
    capsys.readouterr()
    assert main(["metrics", *PLUGIN, str(truth), str(tmp_path / "a.npz"), str(tmp_path / "b.npz"), "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)["methods"]["biased"]
    assert rep["rmse_components"] == pytest.approx([0.5, 0.0])
    assert main(["metrics", *PLUGIN, str(truth), str(tmp_path / "a.npz"), str(tmp_path / "b.npz")]) == 0
    out = capsys.readouterr().out
    rows = {line.split()[0]: line for line in out.splitlines() if line.startswith(("biased ", "worse "))}
    assert "0.5" in rows["biased"] and "2.000 [2, 2]" in rows["worse"] and "worse" in rows["worse"].split()[-2:]


def test_coverage_over_every_trajectory_counts_the_outliers():
    """Unit covariances, unit errors except two trajectories 1000x off: the outlier rule drops them
    from the kept coverage, not from the coverage over every trajectory."""
    from neural_estimator.metrics import consistency as K

    rng = np.random.default_rng(6)
    x = rng.standard_normal((40, 50, 2))
    e = rng.standard_normal(x.shape)
    e[:2] *= 1e3
    P = np.broadcast_to(np.eye(2), (40, 50, 2, 2))
    rep = M.compute_metrics(x, x + e, P_hat=P)
    assert rep.n_outliers == 2
    i95 = K.RELIABILITY_LEVELS.index(0.95)
    assert rep.coverage_curve[i95] == pytest.approx(rep.coverage95)
    assert rep.coverage_curve_all[i95] == pytest.approx(rep.coverage95 * 38 / 40, abs=1e-3)
    every = np.sum(e**2, axis=-1)  # the NEES under unit covariances, every trajectory
    assert rep.nees_median_all == pytest.approx(float(np.median(every)))
    assert rep.nees_median == pytest.approx(float(np.median(every[2:])))
    row = K.consistency_row(
        dict(rep.scalars(), nees_median_all=rep.nees_median_all), 2, rep.coverage_curve, rep.coverage_curve_all
    )
    assert row["coverage95_all"] < row["coverage95"] and 0.4 < row["coverage50"] < 0.6
    assert row["nees_median_all_per_dim"] == pytest.approx(rep.nees_median_all / 2)
    table = K.format_consistency_table({"ekf": row}, fmt="text")
    assert "50/90/99% cov." in table and "95% cov. (all)" in table and "NEES med./dx (all)" in table


def test_a_bags_report_has_the_per_component_table(tmp_path):
    """The live evaluator's report (evaluate_bag): each stream's component errors and its ratio."""
    from neural_estimator.bags.dataset import arrays_to_bag
    from neural_estimator.evaluation.bag_report import evaluate_bag, write_report
    from neural_estimator.data import simulate

    sc = make_scenario("ballistic")
    data = simulate(sc, 4, 24, seed=3)
    off = np.zeros_like(data.x)
    off[..., 1] = 0.2  # the velocity off by 0.2 km/s, the rest exact
    path = arrays_to_bag(tmp_path / "run.mcap", sc, data.x, data.y, data.u, estimates={"ekf": data.x + off})
    report = evaluate_bag(path)
    assert report.reports["ekf"].rmse_components == pytest.approx((0.0, 0.2, 0.0), abs=1e-12)
    summary = report.summary()
    assert "velocity [km/s]" in summary and "0.2" in summary.split("velocity [km/s]")[1]
    assert "velocity [km/s]" in write_report(report)["markdown"].read_text()


def test_the_reproduce_report_has_each_components_rmse_and_the_instance_count():
    from neural_estimator.paper.reproduce import tables as T

    runs = {
        "ballistic": {
            "ekf": [{"rmse_components": [0.01, 0.04, 0.8]}, {"rmse_components": [0.03, 0.06, 0.9]}],
            "gru": [{"rmse_components": [0.05, 0.1, 0.85]}] * 3,
            "pf": [{"rmse": 1.0}],  # a run cached before the components existed: no row
        }
    }
    lines = T.components_table(runs, "ballistic", ["ekf", "gru", "pf"], ["altitude [km]", "v", "c"], {"gru": 3})
    assert lines[0] == "| Method | altitude [km] | v | c | instances |"
    assert lines[2] == "| EKF | 0.02 | 0.05 | 0.85 | — |"  # medians over the runs
    assert lines[3].startswith("| GRU | 0.05 |") and lines[3].endswith("| 3 instances |") and len(lines) == 4
    one = T.components_table(runs, "ballistic", ["gru"], ["a", "v", "c"], {"gru": 1})
    assert one[2].endswith("| 1 instance |")


def _scaled_results(factors: dict, n=40, rng=None):
    """MethodResults whose per-trajectory errors are one base error times each method's factor (the
    paired ratio is then exactly the factor, with a zero-width interval)."""
    from neural_estimator.evaluation.protocol import MethodResult

    base = (rng or np.random.default_rng(0)).random((n, 2)) + 0.1
    out = {}
    for m, f in factors.items():
        r = MethodResult(m)
        errs = M.TrajectoryErrors(base * f**2, np.ones(n, dtype=bool))
        rep = M.compute_metrics(np.zeros((n, 1, 2)), np.sqrt(base * f**2)[:, None, :], spread=1.0)
        r.add(rep, errs)
        out[m] = r
    return out


def test_the_findings_are_judged_on_their_intervals():
    from neural_estimator.paper.reproduce import intervals as I

    assert I.factor_status((25.0, 40.0), 446) == "reproduced"  # at or above sqrt(446) = 21.1
    assert I.factor_status((3.0, 9.0), 446) == "partly" and I.factor_status((15.0, 30.0), 446) == "undecided"
    assert I.factor_status((0.9, 1.2), 446) == "not"
    assert I.approach_status((1.0, 1.1)) == "reproduced" and I.approach_status((1.1, 1.3)) == "undecided"
    nets = {"gru": 1.2, "lstm": 1.3, "gpt2": 1.4, "filterformer": 3.0, "mamba": 1.1, "mamba2": 1.0}
    by = {
        "lorenz96": _scaled_results({"ekf": 1.0, "ukf": 1.0, "enkf": 1.05, **nets}),
        "quadrotor": _scaled_results({"ekf": 1.0, "pf": 30.0, **nets}),
        "nlink": _scaled_results({**nets, "mamba": 1.5, "mamba2": 1.25}),  # an SSM behind the GRU here
        "bearings": _scaled_results({"ekf": 1.0, "enkf": 1.2, **nets}),
        "ballistic": _scaled_results({"ekf": 1.0, "ukf": 1.0, **nets}),
    }
    rows = I.judge(by)
    assert [j["status"] for j in rows] == ["reproduced", "reproduced", "partly", "not", "partly", "not", "not"]
    assert rows[0]["compared"] == "mamba2 / ekf" and rows[0]["ratio"] == pytest.approx(1.0)
    assert rows[1]["ratio"] == pytest.approx(30.0) and rows[1]["ci95"] == pytest.approx([30.0, 30.0])
    assert "nlink: mamba2 / gru [1.04, 1.04] behind" in rows[2]["compared"]
    assert rows[4]["compared"].startswith("filterformer / mamba2") and rows[4]["ratio"] == pytest.approx(2.4)
    assert "| on the interval |" in I.render(rows)
    # from the JSON the headline writes (NaN as null) the table is the same
    assert I.render(json.loads(json.dumps(M.to_json(rows)))) == I.render(rows)
    assert I.covers(by) and not I.covers({s: r for s, r in by.items() if s != "bearings"})
    assert not I.covers({**by, "quadrotor": {m: r for m, r in by["quadrotor"].items() if m != "pf"}})


def _findings_by_scenario():
    nets = {"gru": 1.2, "lstm": 1.3, "gpt2": 1.4, "filterformer": 3.0, "mamba": 1.1, "mamba2": 1.0}
    return {
        "lorenz96": _scaled_results({"ekf": 1.0, "ukf": 1.0, "enkf": 1.05, **nets}),
        "quadrotor": _scaled_results({"ekf": 1.0, "pf": 30.0, **nets}),
        "nlink": _scaled_results(nets),
        "bearings": _scaled_results({"ekf": 1.0, "enkf": 1.2, **nets}),
        "ballistic": _scaled_results({"ekf": 1.0, "ukf": 1.0, **nets}),
    }


@pytest.mark.parametrize("complete", [True, False])
def test_the_headline_judges_the_findings_on_its_own_measurement(tmp_path, monkeypatch, capsys, complete):
    """The headline command judges the paper's findings on the results it measured (here stood in
    for by results of known ratios), and says in one line when they lack a system or a method."""
    import neural_estimator.evaluation.headline as H

    measured = _findings_by_scenario()
    if not complete:
        del measured["bearings"]

    def measure(family, scenarios, methods, results_out=None, **kw):
        results_out.update(measured)
        return dict(family=family, seed=0, trajectories=40, sets=1, horizon=None, rows=[])

    monkeypatch.setattr(H, "measure_headline", measure)
    out = tmp_path / "headline"
    out.mkdir()
    assert main(["headline", "--family", "development", "--out", str(out), "--quiet"]) == 0
    captured = capsys.readouterr()
    if not complete:
        assert not (out / "findings.md").exists()
        assert "the paper's findings: not judged" in captured.err
        return
    judged = json.loads((out / "findings.json").read_text())
    assert [j["status"] for j in judged][:2] == ["reproduced", "reproduced"]  # mamba2 ~ ekf; pf 30x ekf
    assert (out / "findings.md").read_text() in captured.out
    assert "| the PF fails on the planar quadrotor | pf / ekf | 30.00 [30.00, 30.00] | reproduced |" in captured.out


def test_the_fidelity_page_shows_the_findings_judged_on_the_sealed_measurement():
    """docs/fidelity.md's table of the findings on intervals is generated from the sealed headline's
    committed findings.json: the seven findings, each with a status of the stated rules."""
    root = Path(__file__).resolve().parents[1]
    assert "<!-- generate: headline-findings -->" in (root / "docs/fidelity.md").read_text()
    judged = json.loads((root / "docs/results/headline/findings.json").read_text())
    assert len(judged) == 7
    assert {j["status"] for j in judged} <= {"reproduced", "partly", "not", "undecided", "not measured"}
    development = (root / "experiments/results/findings_intervals.md").read_text()
    assert "python experiments/findings_intervals.py" in development
