"""Neural estimators: normalisation, run == a loop of step past the training length, input checks."""

import json

import numpy as np
import pytest
import torch

from neural_estimator.data import simulate
from neural_estimator.methods.registry import EstimatorError
from neural_estimator.serving.neural import resolve_device
from neural_estimator.serving.normalization import Normalizer
from training_cases import (
    ARCHS,
    TOL,
    estimator_for,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tiny tensors: one intra-op thread


# ---- normalisation --------------------------------------------------------------------------------
def test_normalizer_round_trip_and_statistics(spinner):
    data = simulate(spinner, 20, 50, seed=0)
    norm = Normalizer.from_data(spinner, data)
    from neural_estimator.methods.registry import previous_controls

    z, skipped = norm.normalize_inputs(data.y, previous_controls(data.u))
    assert z.shape == (20, 50, 2) and not skipped.any()
    np.testing.assert_allclose(z.reshape(-1, 2).mean(0), 0.0, atol=1e-12)
    np.testing.assert_allclose(z.reshape(-1, 2).std(0), 1.0, atol=1e-12)
    # angles: predicted in radians (mean 0, std 1), wrapped on the way out
    assert norm.out_mean[0] == 0.0 and norm.out_std[0] == 1.0 and norm.out_std[1] != 1.0
    xn = norm.normalize_states(data.x)
    np.testing.assert_allclose(norm.denormalize_states(xn), data.x, atol=1e-12)
    assert norm.denormalize_states(np.array([[3 * np.pi / 2, 0.0]]))[0, 0] == pytest.approx(-np.pi / 2)
    # JSON round trip is exact
    back = Normalizer.from_dict(json.loads(json.dumps(norm.to_dict())))
    for name in ("in_mean", "in_std", "out_mean", "out_std"):
        np.testing.assert_array_equal(getattr(back, name), getattr(norm, name))
    assert back.angle_states == (0,) and (back.dy, back.du) == (1, 1)
    # covariance maps back with diag(std) C diag(std)
    np.testing.assert_allclose(norm.denormalize_covariance(np.eye(2)), np.diag(norm.out_std**2))


def test_normalizer_floor_and_unusable_observations():
    rng = np.random.default_rng(0)
    y, x = rng.normal(5.0, 2.0, (4, 10, 2)), rng.normal(size=(4, 10, 3))
    u = np.zeros((4, 10, 1))  # a control that never varies
    norm = Normalizer.fit(y, u, x)
    assert norm.in_std[2] == pytest.approx(1e-6)
    z, skipped = norm.normalize_inputs(np.array([[np.nan, 1.0], [5.0, 5.0]]), np.zeros((2, 1)))
    assert skipped.tolist() == [True, False]
    assert z[0].tolist() == [0.0, 0.0, 0.0] and np.all(np.isfinite(z))


# ---- the estimator: run equals a loop of step, past the training length -----------------------------
@pytest.mark.parametrize("head", [False, True], ids=["own", "covariance-head"])
@pytest.mark.parametrize("arch", ARCHS)
def test_run_equals_step_loop(arch, spinner, head):
    data = simulate(spinner, 6, 300, seed=1)
    est = estimator_for(spinner, arch, data, head=head)
    Y = data.y[:3].copy()
    Y[1, 40] = np.nan  # an unusable observation: the training mean in its place, in both forms
    out = est.run(Y, data.u[:3])
    assert out.x.shape == (3, 300, 2) and out.x.dtype == np.float64 and not out.diverged.any()
    est.reset(3)
    prev = np.zeros((3, 1))
    xs, covs = [], []
    for k in range(300):
        xs.append(est.step(Y[:, k], prev))
        prev = data.u[:3, k]
        if k == 40:
            assert est.skipped.tolist() == [False, True, False]
        if est.has_covariance:
            covs.append(est.covariance)
    assert np.abs(out.x - np.stack(xs, 1)).max() <= TOL
    assert np.all(np.abs(out.x[..., 0]) <= np.pi)  # the angle comes out wrapped
    assert est.has_covariance == (head or arch == "filterformer")
    if est.has_covariance:
        assert out.cov.shape == (3, 300, 2, 2)
        assert np.abs(out.cov - np.stack(covs, 1)).max() <= TOL * max(1.0, np.abs(out.cov).max())
        assert np.all(np.linalg.eigvalsh(out.cov) > 0)


def test_estimator_checks_inputs(oscillator):
    est = estimator_for(oscillator, "gru", simulate(oscillator, 4, 20, seed=0))
    est.step(np.zeros((3, 1)))  # a step before reset starts y's batch (the Estimator contract)
    assert est.batch == 3
    est.reset(2)
    with pytest.raises(EstimatorError, match=r"observation must be \(B, 1\)"):
        est.step(np.zeros((2, 3)))
    with pytest.raises(EstimatorError, match="batch of 1 observations, but reset for 2"):
        est.step(np.zeros((1, 1)))
    assert est.model.training is False
    if not torch.cuda.is_available():
        with pytest.raises(EstimatorError, match="sees no CUDA GPU"):
            resolve_device("cuda")
    with pytest.raises(EstimatorError, match="unknown device"):
        resolve_device("tpu9")
