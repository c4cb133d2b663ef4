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


def test_the_bounded_step_with_a_covariance_equals_every_copy_stepped_with_its_head():
    """Only the copy whose estimate is served runs the covariance head; the others advance their
    state by the model's plain step. The shipped bearings GRU (a bounded-context variant with a
    covariance head): means, covariances and every copy's state equal, to the bit, those of stepping
    every copy through ``step_with_cov`` (the arithmetic before)."""
    from neural_estimator.data import simulate
    from neural_estimator.serving.context import copy_offsets

    scenario = make_scenario("bearings")
    est = make_estimator("gru", scenario, backend="torch")
    assert est.context_by_copies and est.has_covariance
    data = simulate(scenario, 2, 130, seed=4)
    est.reset(2)
    model, L, K = est.model, est.context, est.context_copies
    states = [None] * K
    for t in range(130):
        x = est.step(data.y[:, t])
        z, _ = est._inputs(*est.check_step(data.y[:, t], None))
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
        np.testing.assert_array_equal(x, est.normalizer.denormalize_states(mean.double().numpy()))
        np.testing.assert_array_equal(est.covariance, est._denormalize_cov(cov))
        for mine, theirs in zip(est._state, states):
            assert (mine is None) == (theirs is None)
            if mine is not None:
                torch.testing.assert_close(mine, theirs, rtol=0, atol=0)
