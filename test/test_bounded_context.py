"""Bounded context (neural_estimator.serving.context, the estimators' context option) and
experiments/bounded_context.py."""

import pytest
import torch
from conftest import load_script

import numpy as np

from neural_estimator.methods.interface import EstimatorError
from neural_estimator.methods.registry import make_estimator
from neural_estimator.models import SystemDims, build_model
from neural_estimator.serving.context import bounded_forward, restart_of
from neural_estimator.scenarios import make_scenario


@pytest.fixture(scope="module")
def bc():
    return load_script("experiments/bounded_context.py")


@pytest.mark.parametrize("length,copies", [(10, 1), (10, 3), (10, 10), (7, 2)])
def test_every_step_sees_at_most_length_steps_and_nearly_that_many(length, copies):
    for t in range(60):
        s = restart_of(t, length, copies)
        assert 0 <= s <= t and t - s + 1 <= length
        if t < length:
            assert s == 0
        else:
            assert t - s + 1 >= length - -(-length // copies) + 1  # at least L - ceil(L / K) + 1 steps


@pytest.mark.parametrize("length,copies", [(10, 1), (10, 3), (7, 7), (100, 4)])
def test_the_torch_free_copies_follow_the_schedule_of_the_torch_copies(length, copies):
    """ONNX Runtime's copies (serving.onnx_runtime.BoundedCopies, a table of steps 0 .. 2L - 1 looked
    up at t >= L as L + (t - L) mod L) restart the rows and serve the copy that copy_schedule names
    at every step, and copy_schedule is the rule of s(t): one copy served, restarted at s(t), and
    every copy restarting at o_k + j L."""
    from neural_estimator.serving.context import copy_offsets, copy_schedule
    from neural_estimator.serving.onnx_runtime import BoundedCopies

    state = [np.zeros((2, copies, 3), dtype=np.float32), np.zeros((copies, 5), dtype=np.float32)]
    ours = BoundedCopies(length, copies, [1, 0], state, [0.0, -1.0])
    offsets = copy_offsets(length, copies)
    copy = np.zeros(1, dtype=np.int64)
    for t in range(6 * length + 3):
        restarts, served = copy_schedule(t, length, copies)
        assert list(restarts) == [k for k, o in enumerate(offsets) if t >= o and (t - o) % length == 0]
        assert offsets[served] + (t - offsets[served]) // length * length == restart_of(t, length, copies)
        state[0][...], state[1][...] = 7.0, 7.0
        ours.before_step(t, state, copy)
        assert copy[0] == served
        for k in range(copies):  # a restarted copy's rows hold the starting values, the others are untouched
            assert (state[0][:, k] == (0.0 if k in restarts else 7.0)).all()
            assert (state[1][k] == (-1.0 if k in restarts else 7.0)).all()


def test_the_torch_free_copies_refuse_a_malformed_graph():
    from neural_estimator.serving.onnx_runtime import BoundedCopies

    state = [np.zeros((2, 4, 3), dtype=np.float32)]
    with pytest.raises(EstimatorError, match="no axis 0 of 4 copies"):
        BoundedCopies(10, 4, [0], state, [0.0])
    with pytest.raises(EstimatorError, match="bounded context is malformed: context 3, 4 copies"):
        BoundedCopies(3, 4, [1], state, [0.0])


@pytest.mark.slow
def test_bounded_forward_is_the_model_on_each_steps_window():
    torch.manual_seed(0)
    model = build_model("mamba2", SystemDims(dx=2, dy=3)).double().eval()
    z = torch.randn(2, 37, 3, dtype=torch.float64)
    with torch.no_grad():
        y = bounded_forward(model, z, 10, 3)
        for t in (0, 5, 9, 10, 17, 29, 36):
            s = restart_of(t, 10, 3)
            torch.testing.assert_close(y[:, t], model(z[:, s : t + 1])[:, -1], rtol=0, atol=1e-12)
        torch.testing.assert_close(bounded_forward(model, z, 37, 4), model(z), rtol=0, atol=1e-12)


@pytest.mark.slow
@pytest.mark.parametrize("method", ["gru", "mamba2"])
def test_the_context_option_streams_what_it_runs(method):
    """step() with context=L equals run() with it (float32 round-off), and differs from unbounded."""
    from neural_estimator.data import simulate

    scenario = make_scenario("nlink")
    data = simulate(scenario, 2, 45, seed=5)
    bounded = make_estimator(method, scenario, context=12, context_copies=3)
    whole = bounded.run(data.y, data.u).x
    bounded.reset(2)
    stepped = np.stack([bounded.step(data.y[:, t], data.u[:, t - 1] if t else None) for t in range(45)], axis=1)
    np.testing.assert_allclose(stepped, whole, rtol=0, atol=1e-4 * np.abs(whole).max())
    free = make_estimator(method, scenario).run(data.y, data.u).x
    np.testing.assert_allclose(whole[:, :12], free[:, :12], rtol=0, atol=1e-5)  # before step L: the same copy
    assert np.abs(whole[:, 12:] - free[:, 12:]).max() > 1e-4


@pytest.mark.parametrize("method,key", [("gpt2", "decode_chunk"), ("filterformer", "window")])
def test_the_context_option_of_an_attention_model_is_its_window(method, key):
    """context=L serves the same weights with attention window L: equal to a model built with that
    window, step equal to run, and different from the paper's window of 256 past step L."""
    from neural_estimator.data import simulate
    from neural_estimator.serving.normalization import Normalizer
    from neural_estimator.serving.neural import NeuralEstimator

    scenario = make_scenario("nlink")
    data = simulate(scenario, 2, 40, seed=7)
    norm = Normalizer.from_data(scenario, data)
    torch.manual_seed(0)
    model = build_model(method, scenario)
    narrow = build_model(method, scenario, **{key: 12})
    narrow.load_state_dict(model.state_dict())
    free = NeuralEstimator(scenario, model, norm, method, covariance=False).run(data.y, data.u).x
    bounded_est = NeuralEstimator(scenario, model, norm, method, covariance=False, context=12)
    assert getattr(model.cfg, key) == 12 and not bounded_est.context_by_copies
    bounded = bounded_est.run(data.y, data.u).x
    built = NeuralEstimator(scenario, narrow, norm, method, covariance=False).run(data.y, data.u).x
    np.testing.assert_allclose(bounded, built, rtol=0, atol=1e-6 * np.abs(built).max())
    bounded_est.reset(2)
    stepped = np.stack([bounded_est.step(data.y[:, t], data.u[:, t - 1] if t else None) for t in range(40)], axis=1)
    np.testing.assert_allclose(stepped, bounded, rtol=0, atol=1e-4 * np.abs(bounded).max())
    np.testing.assert_allclose(bounded[:, :12], free[:, :12], rtol=0, atol=1e-5)  # the window has not bound yet
    assert np.abs(bounded[:, 12:] - free[:, 12:]).max() > 1e-4


@pytest.mark.slow
def test_the_context_option_refuses_what_it_cannot_do():
    scenario = make_scenario("nlink")
    with pytest.raises(ValueError, match="attention window must be >= 1"):
        build_model("gpt2", SystemDims(dx=2, dy=3)).set_window(0)
    with pytest.raises(EstimatorError, match="context must be >= 0"):
        make_estimator("mamba2", scenario, context=-1)
    with pytest.raises(EstimatorError, match="context_copies .20. must not exceed context .10."):
        make_estimator("mamba2", scenario, context=10, context_copies=20)
    with pytest.raises(EstimatorError, match="context"):
        make_estimator("mamba2", scenario, context="ten")
    assert make_estimator("mamba2", scenario, context="100").context == 100  # command-line strings


@pytest.mark.slow
def test_runs_on_a_shipped_model(bc, capsys):
    from conftest import ROOT

    model = str(ROOT / "neural_estimator/serving/zoo/nlink-mamba2")
    bc.main(["--model", model, "--trajectories", "2", "--copies", "2"])
    out = capsys.readouterr().out.splitlines()
    assert out[2].split()[0] == "inference" and [r.split()[0] for r in out[3:]] == ["continuous", "bounded"]
    assert all(0 < float(v) < 5 for v in out[4].split()[2:])
    with pytest.raises(SystemExit):
        bc.main(["--model", model, "--trajectories", "2", "--segments", "0,900"])


@pytest.mark.parametrize("scenario_name,method", [("bearings", "gru"), ("nlink", "lstm"), ("nlink", "mamba")])
def test_the_batched_copies_equal_every_copy_stepped_alone(scenario_name, method):
    """The K copies step as one batch of K x B rows, and a covariance head runs on the served copy's
    rows only: means and covariances equal, to float32 round-off, those of stepping every copy
    alone through ``step_with_cov`` from its own fresh state (the arithmetic the batching replaced).
    The bearings GRU is the zoo's bounded-context variant; the others are bounded by the option."""
    from neural_estimator.data import simulate
    from neural_estimator.serving.context import copy_offsets

    scenario = make_scenario(scenario_name)
    options = {} if scenario_name == "bearings" else {"context": 30, "context_copies": 4}
    est = make_estimator(method, scenario, backend="torch", **options)
    assert est.context_by_copies and est.has_covariance
    model, L, K = est.model, est.context, est.context_copies
    T = 2 * L + 10  # every copy restarted at least once
    data = simulate(scenario, 2, T, seed=4)
    est.reset(2)
    states = [None] * K
    for t in range(T):
        u_prev = data.u[:, t - 1] if t and data.u.shape[-1] else None
        x = est.step(data.y[:, t], u_prev)
        z, _ = est._inputs(*est.check_step(data.y[:, t], u_prev))
        z_t = torch.as_tensor(z, dtype=est.dtype)
        outs = {}
        with torch.inference_mode():
            for k, o in enumerate(copy_offsets(L, K)):
                if t < o:
                    continue
                if (t - o) % L == 0:
                    states[k] = model.init_state(2, dtype=est.dtype)
                mean, cov, states[k] = model.step_with_cov(z_t, states[k])
                outs[o + ((t - o) // L) * L] = (mean, cov)
        mean, cov = outs[restart_of(t, L, K)]
        ref_x = est.normalizer.denormalize_states(mean.double().numpy())
        ref_cov = est._denormalize_cov(cov)
        # float32 round-off of two summation orders (a batch of K x B rows against B rows), bounded
        # in the network's own units: 1e-5 of each component's training spread, plus 1e-5 relative.
        # (A bound of 1e-6 of the largest component failed by 1.1x on an N-link rate near -0.34.)
        spread = np.asarray(est.normalizer.out_std, dtype=np.float64)
        worst = np.max(np.abs(x - ref_x) / (1e-5 * (np.abs(ref_x) + spread)))
        assert worst <= 1.0, (t, worst, x, ref_x)
        np.testing.assert_allclose(est.covariance, ref_cov, rtol=1e-4, atol=1e-6 * np.abs(ref_cov).max())
