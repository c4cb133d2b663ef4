"""The hybrid's state form (``gain_form="state"``, neural_estimator/models/kalmannet.py): the update
G_n delta_n with delta_n the least-squares state correction through h linearised at the prediction,
and G0, the alpha-beta gains carried through the model's kinematics.

Every reference here is computed independently of the model: numpy's least squares on the scenario's
analytic Jacobians (``jac_h``, ``jac_f``), not torch's autograd."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from neural_estimator.data import simulate
from neural_estimator.methods import table
from neural_estimator.methods.interface import previous_controls
from neural_estimator.models import build_model
from neural_estimator.models.kalmannet import LEAST_SQUARES_EPS, HybridSystemError
from neural_estimator.scenarios import make_scenario
from neural_estimator.serving.checkpoint import load_checkpoint, save_checkpoint
from neural_estimator.serving.normalization import Normalizer

pytestmark = pytest.mark.usefixtures("one_torch_thread")

T = 12


def state_hybrid(name: str, alpha: float = 0.25, seed: int = 0, dtype=torch.float64):
    scenario = make_scenario(name)
    data = simulate(scenario, 4, T, seed=seed)
    norm = Normalizer.from_data(scenario, data)
    torch.manual_seed(seed)
    model = build_model("kalmannet", scenario, gain_form="state", prior_gain=alpha).to(dtype).eval()
    model.set_normalization(norm)
    return scenario, model, norm, data


def inputs(norm, data, dtype=torch.float64) -> torch.Tensor:
    return torch.as_tensor(norm.normalize_inputs(data.y, previous_controls(data.u))[0], dtype=dtype)


@pytest.mark.parametrize("name", ["nlink", "bearings", "lorenz96"])
def test_delta_is_the_least_squares_correction_at_the_prediction(name):
    """delta_n = argmin |J_n d - e_n|^2 (+ eps |d|^2) with J_n h's analytic Jacobian at x_{k|k-1}
    (not at m0): numpy's regularised normal equations on the scenario's jac_h."""
    scenario, model, norm, data = state_hybrid(name)
    rng = np.random.default_rng(1)
    x = data.x[:, 5]  # states away from the prior (N-link's angles swung)
    e_n = rng.normal(size=(x.shape[0], scenario.dy))
    got = model._least_squares_correction(torch.as_tensor(x), torch.as_tensor(e_n)).numpy()
    for b in range(x.shape[0]):
        j_n = scenario.jac_h(x[b : b + 1])[0] * norm.out_std[None, :] / norm.in_std[: scenario.dy, None]
        ref = np.linalg.solve(j_n.T @ j_n + LEAST_SQUARES_EPS * np.eye(scenario.dx), j_n.T @ e_n[b])
        np.testing.assert_allclose(got[b], ref, rtol=1e-7, atol=1e-9)
    if name == "nlink":  # h does not see the rates: they get no correction of their own
        np.testing.assert_array_equal(got[:, 3:], 0.0)


def test_g0_is_alpha_beta_through_the_models_kinematics():
    """N-link: G0[S, S] = alpha I on the angles h sees, G0[U, S] = (beta / dt) pinv(A_n[S, U]) with
    A = (df/dx(m0) - I) / dt from the analytic jac_f and beta = alpha^2 / (2 - alpha); the rest 0."""
    alpha = 0.3
    scenario, model, norm, _ = state_hybrid("nlink", alpha=alpha)
    dt, s, u = scenario.dt, slice(0, 3), slice(3, 6)
    a = (scenario.jac_f(scenario.prior()[0][None])[0] - np.eye(6)) / dt
    a_n = a * norm.out_std[None, :] / norm.out_std[:, None]
    beta = alpha**2 / (2 - alpha)
    g0 = model.gain_prior.numpy()
    np.testing.assert_allclose(g0[s, s], alpha * np.eye(3), atol=1e-12)
    np.testing.assert_allclose(g0[u, s], beta / dt * np.linalg.pinv(a_n[s, u]), rtol=1e-6, atol=1e-9)
    np.testing.assert_array_equal(g0[:, u], 0.0)
    # the rate rows are the rates that make the angle correction beta's share over one period
    np.testing.assert_allclose(np.diag(g0[u, s]) * norm.out_std[u] * dt, beta, rtol=2e-2)


def test_g0_is_alpha_i_where_h_sees_every_state():
    scenario, model, _, _ = state_hybrid("lorenz96", alpha=0.4)
    np.testing.assert_allclose(model.gain_prior.numpy(), 0.4 * np.eye(scenario.dx), atol=1e-12)


@pytest.mark.parametrize("name", ["nlink", "quadrotor"])
def test_a_zero_gain_is_the_open_loop_in_the_state_form_too(name):
    scenario, model, norm, data = state_hybrid(name)
    with torch.no_grad():
        model.gain.weight.zero_()
        model.gain.bias.zero_()
        model.gain_prior.zero_()
        x = norm.denormalize_states(model(inputs(norm, data)).numpy())
    ref = table.resolve(table.spec("openloop").factory)(scenario).run(data.y, data.u).x
    np.testing.assert_allclose(x, ref, rtol=1e-9, atol=1e-9)


def test_the_state_form_changes_the_estimate_and_a_loop_of_step_equals_forward():
    scenario, model, norm, data = state_hybrid("nlink")
    z = inputs(norm, data)
    with torch.no_grad():
        full = model(z)
        state, steps = model.init_state(z.shape[0], dtype=z.dtype), []
        for k in range(T):
            x_k, state = model.step(z[:, k], state)
            steps.append(x_k)
        model.gain_prior.zero_()
        model.gain.weight.zero_()
        model.gain.bias.zero_()
        open_loop = model(z)
    torch.testing.assert_close(torch.stack(steps, 1), full, rtol=0, atol=0)
    assert (full[:, 2:] - open_loop[:, 2:]).abs().max() > 1e-2


def test_gradients_are_finite_through_the_jacobian():
    """Training differentiates through vmap(jacrev(h)) and the solve: every weight gets a finite
    gradient, and the input layer a non-zero one."""
    _, model, norm, data = state_hybrid("nlink", dtype=torch.float32)
    model.train()
    x = model(inputs(norm, data, torch.float32))
    target = torch.as_tensor(norm.normalize_states(data.x), dtype=torch.float32)
    (x - target).square().mean().backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in model.parameters())
    assert model.input_layer.weight.grad.abs().sum() > 0


def test_the_form_survives_a_checkpoint(tmp_path):
    scenario, model, norm, data = state_hybrid("nlink", dtype=torch.float32)
    save_checkpoint(tmp_path, model, norm, {"scenario": scenario.describe()})
    loaded, _, _ = load_checkpoint(tmp_path)
    assert loaded.cfg.gain_form == "state" and loaded.cfg.prior_gain == 0.25
    z = inputs(norm, data, torch.float32)
    with torch.no_grad():
        torch.testing.assert_close(loaded.eval()(z), model(z), rtol=0, atol=0)


def test_an_unknown_form_is_refused_in_one_line():
    with pytest.raises(HybridSystemError, match="gain_form 'kalman' is not one of innovation, state") as err:
        build_model("kalmannet", make_scenario("lorenz96"), gain_form="kalman")
    assert "\n" not in str(err.value)


def test_the_state_form_has_no_onnx_step_and_says_why(tmp_path):
    from neural_estimator.serving.export import export_beside

    scenario, model, norm, _ = state_hybrid("bearings", dtype=torch.float32)
    assert "Jacobian" in model.onnx_blocker
    save_checkpoint(tmp_path, model, norm, {"scenario": scenario.describe()})
    assert export_beside(tmp_path, scenario) is None and not (tmp_path / "step.onnx").exists()
