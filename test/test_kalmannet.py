"""The KalmanNet hybrid (neural_estimator/models/kalmannet.py) and its serving: the filter's timing,
its gain, its guards, its checkpoint, its ONNX step, a missing observation (predict only).

Untrained models (seeded, with their gain layer scaled up so the learned update is not negligible)
and a normaliser fitted on simulated data: the tests check the arithmetic and the plumbing, not
accuracy (training is neural_estimator/training's)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from neural_estimator.data import simulate
from neural_estimator.methods import table
from neural_estimator.methods.interface import EstimatorError, previous_controls
from neural_estimator.models import SystemDims, build_model, count_parameters
from neural_estimator.models.kalmannet import CLAMP_STDS, KalmanNetModel
from neural_estimator.scenarios import make_scenario
from neural_estimator.serving.checkpoint import load_checkpoint, save_checkpoint
from neural_estimator.serving.load import load_neural_estimator
from neural_estimator.serving.neural import NeuralEstimator
from neural_estimator.serving.normalization import Normalizer

pytestmark = pytest.mark.usefixtures("one_torch_thread")

SCENARIOS = ("ballistic", "bearings", "lorenz96", "nlink", "quadrotor")
T = 12


def hybrid(name: str, seed: int = 0, gain_scale: float = 10.0, dtype=torch.float32):
    """(scenario, model with normalisation set, normaliser, data) for ``name``: an untrained model
    whose gain layer is scaled up (x10: a gain of the order of PyTorch's default init)."""
    scenario = make_scenario(name)
    data = simulate(scenario, 4, T, seed=seed)
    norm = Normalizer.from_data(scenario, data)
    torch.manual_seed(seed)
    model = build_model("kalmannet", scenario).to(dtype).eval()
    model.set_normalization(norm)
    with torch.no_grad():
        model.gain.weight.mul_(gain_scale)
        model.gain.bias.normal_(0.0, 0.1)
    return scenario, model, norm, data


def zero_gain(model) -> None:
    """K = 0: the fixed model-based part and the network's."""
    with torch.no_grad():
        model.gain.weight.zero_()
        model.gain.bias.zero_()
        model.gain_prior.zero_()


def inputs(norm: Normalizer, data, dtype=torch.float32) -> torch.Tensor:
    z, _ = norm.normalize_inputs(data.y, previous_controls(data.u))
    return torch.as_tensor(z, dtype=dtype)


def test_the_table_entry():
    s = table.spec("kalmannet")
    assert (s.family, s.needs_model, s.trainable, s.takes_init, s.uses_torch, s.paper_row) == (
        "hybrid",
        True,
        True,
        False,
        True,
        None,
    )
    assert "kalmannet" in table.names(trainable=True) and "kalmannet" not in table.names(family="neural")
    assert "kalmannet" not in table.paper_names()


@pytest.mark.parametrize("name", SCENARIOS)
def test_parameters_within_the_budget(name):
    model = build_model("kalmannet", make_scenario(name))
    n = count_parameters(model)
    print(f"kalmannet {name}: {n:,} parameters")
    assert 10_000 < n <= 100_000


@pytest.mark.parametrize("name", ["bearings", "nlink", "quadrotor"])  # an angle observed, angle states, controls
def test_forward_equals_a_loop_of_step(name):
    scenario, model, norm, data = hybrid(name)
    z = inputs(norm, data)
    with torch.no_grad():
        full = model(z)
        state, xs = model.init_state(z.shape[0]), []
        for k in range(T):
            x, state = model.step(z[:, k], state)
            xs.append(x)
        chunks = []  # rollout over two chunks, the state carried (TBPTT's use)
        state = model.init_state(z.shape[0])
        for sl in (slice(0, 5), slice(5, T)):
            x, _, state = model.rollout(z[:, sl], state)
            chunks.append(x)
    assert torch.isfinite(full).all()
    torch.testing.assert_close(torch.stack(xs, 1), full, rtol=0, atol=0)
    torch.testing.assert_close(torch.cat(chunks, 1), full, rtol=0, atol=0)


def test_the_gain_changes_the_estimate():
    """The learned update is not negligible in these tests (else every check below is open loop)."""
    _, model, norm, data = hybrid("lorenz96")
    z = inputs(norm, data)
    with torch.no_grad():
        x = model(z)
        model.gain.weight.zero_()
        model.gain.bias.zero_()
        x0 = model(z)
    assert (x[:, 1:] - x0[:, 1:]).abs().max() > 1e-2


@pytest.mark.parametrize("name", ["lorenz96", "quadrotor", "nlink"])
def test_the_fixed_gain_is_half_the_least_squares_correction(name):
    """K0 = 0.5 pinv(H_n) in normalised units, H_n h's Jacobian at m0 scaled by the statistics: where h
    sees every direction it is asked about, H_n K0 = 0.5 I; N-link's h at the hanging prior sees the
    angles only (d pz / d theta = sin 0 = 0), so there H_n K0 is half a projector of rank 3."""
    scenario, model, norm, _ = hybrid(name, dtype=torch.float64)
    m0 = scenario.prior()[0]
    h_n = scenario.jac_h(m0[None])[0] * norm.out_std[None, :] / norm.in_std[: scenario.dy, None]
    prod = h_n @ model.gain_prior.numpy()
    assert np.linalg.matrix_rank(prod, tol=1e-6) == (3 if name == "nlink" else scenario.dy)
    np.testing.assert_allclose(prod @ prod, 0.5 * prod, atol=1e-9)  # 0.5 times a projector
    if name != "nlink":
        np.testing.assert_allclose(prod, 0.5 * np.eye(scenario.dy), atol=1e-9)


@pytest.mark.parametrize("name", ["ballistic", "bearings"])
def test_the_predicted_observation_is_made_before_y_k_is_read(name):
    scenario, model, norm, data = hybrid(name)
    z = inputs(norm, data)
    k = 5
    z2 = z.clone()
    z2[:, k, : scenario.dy] += 0.5
    with torch.no_grad():
        x1, y1, _ = model.rollout(z, model.init_state(4))
        x2, y2, _ = model.rollout(z2, model.init_state(4))
    torch.testing.assert_close(y1[:, : k + 1], y2[:, : k + 1], rtol=0, atol=0)  # up to and including k
    assert (y1[:, k + 1] - y2[:, k + 1]).abs().max() > 0  # y_k reaches the next prediction
    assert (x1[:, k] - x2[:, k]).abs().max() > 0  # and the update at k
    with torch.no_grad():  # k = 0: h(m0)
        m0 = torch.as_tensor(scenario.prior()[0], dtype=torch.float32)
        h0 = (model.dynamics.h(m0) - model.in_mean[: scenario.dy]) / model.in_std[: scenario.dy]
    torch.testing.assert_close(y1[:, 0], h0.expand(4, -1))


def test_the_observation_residual_wraps_a_bearing():
    scenario, model, norm, _ = hybrid("bearings")
    std, mean = float(norm.in_std[0]), float(norm.in_mean[0])
    y_true, y_pred = np.pi - 0.01, -np.pi + 0.02  # 0.03 rad apart across the wrap point
    z = torch.tensor([[[(y_true - mean) / std]]], dtype=torch.float32)
    yp = torch.tensor([[[(y_pred - mean) / std]]], dtype=torch.float32)
    r = model.obs_residual_norm(yp, z)
    assert r.shape == (1, 1, 1)
    assert float(r) * std == pytest.approx(-0.03, abs=1e-5)


@pytest.mark.parametrize("name", SCENARIOS)
def test_a_zero_gain_is_the_open_loop_baseline(name):
    scenario, model, norm, data = hybrid(name, dtype=torch.float64)
    zero_gain(model)
    with torch.no_grad():
        x_n = model(inputs(norm, data, torch.float64)).numpy()
    x = norm.denormalize_states(x_n)
    ref = table.resolve(table.spec("openloop").factory)(scenario).run(data.y, data.u).x
    np.testing.assert_allclose(x, ref, rtol=1e-9, atol=1e-9)


def test_gradients_flow_through_f():
    """d x_{k|k} / d x_{k-1|k-1} with a zero gain is f's Jacobian (the scenario's analytic one)."""
    scenario, model, norm, _ = hybrid("nlink", dtype=torch.float64)
    zero_gain(model)
    x_prev = np.array([0.3, -0.2, 0.5, 0.1, 0.0, -0.4])
    state = list(model.init_state(1))
    offset = torch.tensor(x_prev[None] - scenario.prior()[0], requires_grad=True)
    state[0], state[4] = offset, torch.ones(1, 1, dtype=torch.float64)  # after step 0
    z = torch.zeros(1, scenario.dy, dtype=torch.float64)
    jac = torch.autograd.functional.jacobian(lambda o: model.step(z, (o, *state[1:]))[0], offset)[0, :, 0, :]
    jac = jac * torch.as_tensor(norm.out_std)[:, None]  # normalised output -> state units
    np.testing.assert_allclose(jac.numpy(), scenario.jac_f(x_prev[None])[0], rtol=1e-7, atol=1e-8)
    # and to the network's weights through f at the next step
    _, model, norm, data = hybrid("lorenz96")
    x, y_pred, _ = model.rollout(inputs(norm, data), model.init_state(4))
    model.obs_residual_norm(y_pred, inputs(norm, data)).square().mean().backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in model.parameters())
    assert model.input_layer.weight.grad.abs().sum() > 0


def test_a_system_without_f_and_h_is_refused_in_one_line(tmp_path):
    with pytest.raises(ValueError, match="differentiable f and h") as err:
        build_model("kalmannet", SystemDims(3, 1, 0))
    assert "\n" not in str(err.value)
    scenario, model, norm, _ = hybrid("ballistic")
    save_checkpoint(tmp_path, model, norm, {"scenario": scenario.describe()})
    card_file = tmp_path / "card.json"
    card = json.loads(card_file.read_text())
    card["scenario"]["scenario"] = "a_plugin_not_loaded"  # rebuilt as dimensions only
    card_file.write_text(json.dumps(card))
    with pytest.raises(EstimatorError, match="kalmannet.*differentiable f and h") as err:
        load_checkpoint(tmp_path)
    assert "\n" not in str(err.value)


def test_a_checkpoint_round_trip_gives_the_same_estimates(tmp_path):
    scenario, model, norm, data = hybrid("quadrotor")
    save_checkpoint(tmp_path, model, norm, {"scenario": scenario.describe()})
    direct = NeuralEstimator(scenario, model, norm, "kalmannet").run(data.y, data.u)
    est = load_neural_estimator("kalmannet", scenario, tmp_path)
    assert isinstance(est.model, KalmanNetModel) and est.covariance is None
    loaded = est.run(data.y, data.u)
    np.testing.assert_array_equal(loaded.x, direct.x)
    assert loaded.cov is None and not loaded.diverged.any()
    est.reset(4)  # the per-message path: a loop of step equals run
    steps = np.stack([est.step(data.y[:, k], previous_controls(data.u)[:, k]) for k in range(T)], 1)
    np.testing.assert_allclose(steps, loaded.x, rtol=1e-6, atol=1e-6)
    loaded_model, _, _ = load_checkpoint(tmp_path)  # the card's scenario rebuilt
    for (k, a), b in zip(model.state_dict().items(), loaded_model.state_dict().values()):
        assert torch.equal(a, b), k


@pytest.mark.parametrize("name", ["ballistic", "bearings", "lorenz96", "quadrotor"])
def test_the_onnx_step_equals_the_torch_step(tmp_path, name):
    pytest.importorskip("onnxruntime")
    from neural_estimator.serving.export import export_beside
    from neural_estimator.serving.onnx_runtime import OnnxEstimator

    scenario, model, norm, data = hybrid(name)
    assert model.onnx_blocker is None
    save_checkpoint(tmp_path, model, norm, {"scenario": scenario.describe()})
    assert export_beside(tmp_path, scenario) is not None
    ort = load_neural_estimator("kalmannet", scenario, tmp_path, backend="auto")
    assert isinstance(ort, OnnxEstimator)
    ref = load_neural_estimator("kalmannet", scenario, tmp_path, backend="torch")
    y, u = data.y[:1].copy(), previous_controls(data.u)[:1]
    y[0, 6] = np.nan  # a dropped reading on the way
    ort.reset(1)
    ref.reset(1)
    for k in range(T):
        a, b = ort.step(y[:, k], u[:, k]), ref.step(y[:, k], u[:, k])
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-5 * float(np.max(norm.out_std)))
        assert ort.skipped[0] == ref.skipped[0] == (k == 6)


def test_nlink_has_no_onnx_step_and_says_why(tmp_path):
    from neural_estimator.serving.export import export_beside

    scenario, model, norm, _ = hybrid("nlink")
    assert "linalg_solve" in model.onnx_blocker
    save_checkpoint(tmp_path, model, norm, {"scenario": scenario.describe()})
    (tmp_path / "step.onnx").write_bytes(b"stale")
    assert export_beside(tmp_path, scenario) is None and not (tmp_path / "step.onnx").exists()
    est = load_neural_estimator("kalmannet", scenario, tmp_path, backend="auto")
    assert est.backend == "torch"
    with pytest.raises(EstimatorError, match="linalg_solve") as err:
        load_neural_estimator("kalmannet", scenario, tmp_path, backend="onnxruntime")
    assert "\n" not in str(err.value)


def test_a_told_model_is_served_by_torch_not_by_the_trained_models_onnx_step(tmp_path):
    """step.onnx has the f and h of the model trained with in its graph: told another model
    (model_set), the per-message default serves torch's hybrid around the told f and h; asking
    for the graph explicitly is refused in one line."""
    pytest.importorskip("onnxruntime")
    from neural_estimator.scenarios.model import model_scenario
    from neural_estimator.serving.export import export_beside
    from neural_estimator.serving.onnx_runtime import OnnxEstimator

    scenario, model, norm, data = hybrid("lorenz96")
    save_checkpoint(tmp_path, model, norm, {"scenario": scenario.describe()})
    assert export_beside(tmp_path, scenario) is not None
    told = model_scenario(scenario, {"forcing": "10"})
    exact = load_neural_estimator("kalmannet", scenario, tmp_path, backend="auto")
    assert isinstance(exact, OnnxEstimator)
    served = load_neural_estimator("kalmannet", told, tmp_path, backend="auto")
    assert not isinstance(served, OnnxEstimator) and served.backend == "torch"
    y, u = data.y[:1], data.u[:1]  # one stream: the exported step's batch
    ref = load_neural_estimator("kalmannet", told, tmp_path, backend="torch").run(y, u).x
    np.testing.assert_array_equal(served.run(y, u).x, ref)
    assert np.abs(ref - exact.run(y, u).x).max() > 1e-2  # the told model's estimates differ
    trained = "step.onnx beside its card holds the f and h of the model it was trained with, not the model told"
    with pytest.raises(EstimatorError, match=trained) as err:
        load_neural_estimator("kalmannet", told, tmp_path, backend="onnxruntime")
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("name", ["lorenz96", "nlink"])
def test_a_non_finite_observation_only_predicts(name):
    scenario, model, norm, data = hybrid(name)
    est = NeuralEstimator(scenario, model, norm, "kalmannet")
    y = data.y.copy()
    k = 4
    y[1, k, 0] = np.nan  # stream 1 loses its reading at step k; the others keep theirs
    u = previous_controls(data.u)
    out = est.run(y, data.u).x
    est.reset(4)
    xs = []
    for t in range(T):
        xs.append(est.step(y[:, t], u[:, t]))
        assert est.skipped.tolist() == [False, t == k, False, False]
    np.testing.assert_allclose(np.stack(xs, 1), out, rtol=1e-5, atol=1e-5)
    assert np.isfinite(out).all()
    predicted = scenario.normalize_state(scenario.f(out[1:2, k - 1], u[1:2, k]))
    np.testing.assert_allclose(out[1, k], predicted[0], rtol=1e-4, atol=1e-4 * float(np.max(norm.out_std)))
    clean = est.run(data.y, data.u).x
    np.testing.assert_array_equal(out[[0, 2, 3]], clean[[0, 2, 3]])  # the other streams untouched
    assert np.abs(clean[1, k] - predicted[0]).max() > 1e-3  # with its reading, stream 1 updates


def test_a_runaway_state_stays_finite():
    """The guard: a huge gain drives the estimate far away, which is clamped, never NaN."""
    scenario, model, norm, data = hybrid("ballistic", gain_scale=1e6)
    with torch.no_grad():
        x = model(inputs(norm, data))
    assert torch.isfinite(x).all()
    assert x.abs().max() > 100  # it did run away (normalised units) ...
    assert (x.abs() <= CLAMP_STDS * (1 + 1e-6)).all()  # ... to the clamp, mu_x +- 1e3 sigma_x
