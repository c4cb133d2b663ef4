"""Classical filters (EKF, UKF, EnKF, PF) against known answers, filterpy as the independent implementation.

- EKF and UKF equal filterpy's ExtendedKalmanFilter / UnscentedKalmanFilter (Merwe points,
  alpha=1e-3, beta=2, kappa=0) run one trajectory at a time, to 1e-6 relative, on every scenario.
- EnKF and PF agree in distribution with filterpy's EnsembleKalmanFilter and with a particle filter
  built on filterpy.monte_carlo.systematic_resample (RMSE over many trajectories, paired test).
- On a linear-Gaussian scenario EKF and UKF are the Kalman filter; EnKF and PF approach it as the
  ensemble / particle count grows.
- The UKF's closed-form update for linear observations equals the unscented update.
"""

from __future__ import annotations

import numpy as np
import pytest

from neural_estimator.methods.registry import EstimatorError
from neural_estimator.filters import (
    EnsembleKalmanFilter,
    ExtendedKalmanFilter,
    ParticleFilter,
    UnscentedKalmanFilter,
)
from neural_estimator.filters.reference import filterpy_enkf, reference_pf
from neural_estimator.scenarios import BUILTIN_SCENARIOS, make_scenario
from filter_cases import (
    scenario_or_skip,
    data,
    kalman_filter,
    assert_close,
    compare_with_filterpy,
    paired_rmse_check,
)


# ---- the UKF's closed-form update for linear observations ------------------------------------------
LINEAR_OBS_SCENARIOS = ("lorenz96", "quadrotor")


@pytest.mark.parametrize("name", BUILTIN_SCENARIOS)
def test_obs_matrix_declarations_are_true(name):
    """A scenario that declares h(x) = H x must mean it; the UKF's closed form relies on it. Lorenz 96
    and the quadrotor declare it; a built-in that declares none has nothing to hold true."""
    s = scenario_or_skip(name)
    H = s.obs_matrix()
    if H is None:
        assert name not in LINEAR_OBS_SCENARIOS  # the closed-form tests below rely on their declaration
        return
    x = s.sample_initial(np.random.default_rng(0), 9) + np.random.default_rng(1).standard_normal((9, s.dx))
    assert H.shape == (s.dy, s.dx)
    np.testing.assert_allclose(s.h(x), x @ H.T, rtol=1e-14, atol=1e-14)


@pytest.mark.parametrize("name", LINEAR_OBS_SCENARIOS)
def test_ukf_linear_update_equals_unscented_update(name):
    """The closed form (default) and the sigma-point update agree to round-off over a whole run,
    NaN observations included; the closed form is the one used whenever obs_matrix is declared."""
    s = scenario_or_skip(name)
    x, y, u = data(s, 5, 25, seed=4)
    y[1, 7] = np.nan
    closed = UnscentedKalmanFilter(s)
    sigma = UnscentedKalmanFilter(s, linear_update=False)
    assert closed._H is not None and sigma._H is None
    a, b = closed.run(y, u), sigma.run(y, u)
    scale = np.sqrt(np.diag(s.prior()[1]))
    assert np.abs(a.x - b.x).max() <= 1e-7 * scale.max()
    d = np.sqrt(np.diagonal(b.cov, axis1=-2, axis2=-1))
    assert (np.abs(a.cov - b.cov) / (d[..., :, None] * d[..., None, :])).max() <= 1e-6
    assert not a.diverged.any() and not b.diverged.any()


def test_ukf_linear_update_rejects_a_wrong_obs_matrix():
    s = scenario_or_skip("lorenz96")
    s.obs_matrix = lambda: np.eye(3)  # instance attribute: this object only
    with pytest.raises(EstimatorError, match="obs_matrix must be finite"):
        UnscentedKalmanFilter(s)


# ---- EKF / UKF versus filterpy on every scenario -----------------------------------------------------
# Horizons are short where filterpy is slow (Lorenz 96: 81 sigma points x 40 dims per step).
FILTERPY_CASES = {
    "test_filters_linear": 30,
    "test_filters_pendulum": 40,
    "ballistic": 40,
    "bearings": 25,
    "lorenz96": 12,
    "nlink": 25,
    "quadrotor": 40,
}


@pytest.mark.slow
@pytest.mark.parametrize("method", ["ekf", "ukf"])
@pytest.mark.parametrize("name", list(FILTERPY_CASES))
def test_ekf_ukf_match_filterpy(name, method):
    s = scenario_or_skip(name)
    compare_with_filterpy(s, method, n=3, T=FILTERPY_CASES[name], seed=11)


# ---- EnKF / PF versus filterpy in distribution -----------------------------------------------------------


# scenario: (trajectories, horizon). filterpy's EnKF calls f and h once per member (50 per step),
# which is slow for the RK4 scenarios; the reference PF is vectorised over particles.
ENKF_CASES = {
    "test_filters_linear": (30, 20),
    "test_filters_pendulum": (30, 20),
    "ballistic": (12, 10),
    "bearings": (24, 20),
    "nlink": (10, 8),
    "quadrotor": (20, 15),
}
PF_CASES = {
    "test_filters_linear": (30, 20),
    "test_filters_pendulum": (30, 20),
    "ballistic": (20, 20),
    "bearings": (30, 20),
    "lorenz96": (6, 8),
    "nlink": (12, 10),
    "quadrotor": (30, 20),
}


@pytest.mark.slow
@pytest.mark.parametrize("name", list(ENKF_CASES))
def test_enkf_matches_filterpy_in_distribution(name):
    s = scenario_or_skip(name)
    n, T = ENKF_CASES[name]
    x, y, u = data(s, n, T, seed=5)
    ours = EnsembleKalmanFilter(s, seed=1).run(y, u).x
    ref = np.array([filterpy_enkf(s, y[b], u[b], N=50, seed=100 + b) for b in range(n)])
    paired_rmse_check(s, ours, ref, x, f"{name} EnKF")


@pytest.mark.slow
@pytest.mark.parametrize("name", list(PF_CASES))
def test_pf_matches_reference_in_distribution(name):
    s = scenario_or_skip(name)
    n, T = PF_CASES[name]
    x, y, u = data(s, n, T, seed=6)
    ours = ParticleFilter(s, seed=2).run(y, u).x
    ref = np.array([reference_pf(s, y[b], u[b], N=1024, init_std=1.0, seed=200 + b) for b in range(n)])
    paired_rmse_check(s, ours, ref, x, f"{name} PF")


# ---- the linear-Gaussian known answer ------------------------------------------------------------------
def test_ekf_ukf_equal_kalman_filter():
    s = make_scenario("test_filters_linear")
    x, y, u = data(s, 4, 40, seed=3)
    for cls in (ExtendedKalmanFilter, UnscentedKalmanFilter):
        est = cls(s).run(y, u)
        for b in range(4):
            xk, Pk = kalman_filter(s, y[b], u[b])
            assert_close(est.x[b], xk, np.ones(4), f"{cls.method} mean")
            d = np.sqrt(np.diagonal(Pk, axis1=1, axis2=2))
            assert_close(est.cov[b], Pk, d[:, :, None] * d[:, None, :], f"{cls.method} covariance")


def _error_vs_kf(cls, size_option, sizes, n=12, T=25, **options):
    """Mean |x - x_KF| / KF std for each ensemble / particle count (B trajectories, all steps)."""
    s = make_scenario("test_filters_linear")
    x, y, u = data(s, n, T, seed=4)
    kf = [kalman_filter(s, y[b], u[b]) for b in range(n)]
    xk = np.array([m for m, _ in kf])
    sd = np.sqrt(np.array([np.diagonal(P, axis1=1, axis2=2) for _, P in kf]))
    errs = []
    for N in sizes:
        est = cls(s, seed=7, **{size_option: N}, **options).run(y, u)
        errs.append(float(np.mean(np.abs(est.x - xk) / sd)))
    return errs


def test_enkf_approaches_kalman_filter():
    errs = _error_vs_kf(EnsembleKalmanFilter, "n_members", [10, 100, 1000, 4000])
    assert all(a > b for a, b in zip(errs, errs[1:])), errs
    # Monte Carlo error of an ensemble mean ~ 0.8 / sqrt(N) KF std (mean absolute value of a normal):
    # 0.013 at N = 4000, measured 0.025 (the gain is random too); 0.05 leaves margin.
    assert errs[-1] < 0.05, errs


@pytest.mark.slow
def test_pf_approaches_kalman_filter():
    # P0 = I in this scenario, so the paper's x_0 std = 1 spread is exactly the prior.
    errs = _error_vs_kf(ParticleFilter, "n_particles", [64, 256, 1024, 4096, 16384])
    # Monte Carlo error ~ 1 / sqrt(ESS): each 4x more particles should halve it; demand at least 25 %.
    assert all(b < 0.75 * a for a, b in zip(errs, errs[1:])), errs
    # The first update has ESS ~ N / 20 (prior std 1 against observation std 0.2 and 0.3), so the
    # error is ~ 0.8 sqrt(20 / N) ~ 0.03 KF std at N = 16384 on those steps; measured 0.06, bound 0.1.
    assert errs[-1] < 0.1, errs
    errs_prior = _error_vs_kf(ParticleFilter, "n_particles", [16384], init_std=None)
    assert errs_prior[0] < 0.1, errs_prior
