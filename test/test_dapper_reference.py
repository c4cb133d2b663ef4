"""DAPPER (nansencenter/DAPPER 1.7) as a second independent reference, on identical Lorenz 96 data.

DAPPER is given the scenario's own f, H, Q, R and prior (``filters.reference.dapper_filter``), and
both filter the same truth and observations:

- EKF vs DAPPER's ExtKF: deterministic algorithms, equal up to DAPPER's extra Q on the prior
  (1e-6 of P0, see dapper_filter) and its P = (I - K H) P^- update (ours: Joseph form, equal in
  exact arithmetic): the means agree to 1e-6 of the state's scale (measured 3e-8).
- EnKF vs DAPPER's EnKF('PertObs'): same algorithm, different random draws (and DAPPER centres its
  observation perturbations): per-trajectory RMSE equal within 4 standard errors of the paired
  difference plus 5 % (the paired test of filter_cases.paired_rmse_check).
- The sakov2008 setting (observation variance 1): with inflation and localisation, ours in
  DAPPER's published RMSE band (0.18-0.24 after burn-in); DAPPER's EnKF is run beside it on the
  same data and printed.

The PF is not compared: DAPPER's PartFilt regularises by default (reg, nuj) with Scott's bandwidth
and jitters only duplicated particles, where ours jitters every resampled particle with Musso's.
"""

from __future__ import annotations

import numpy as np
import pytest

from neural_estimator.data.simulate import simulate
from neural_estimator.filters import EnsembleKalmanFilter, ExtendedKalmanFilter
from neural_estimator.filters.reference import dapper_filter
from neural_estimator.scenarios import make_scenario

pytestmark = pytest.mark.slow  # DAPPER's EnKF on long Lorenz 96 runs

pytest.importorskip("dapper")


def _rmse(est: np.ndarray, x: np.ndarray, burn_in: int) -> np.ndarray:
    return np.sqrt(((est - x)[:, burn_in:] ** 2).mean(axis=(1, 2)))


def test_ekf_equals_dapper_extkf():
    s = make_scenario("lorenz96")
    d = simulate(s, 2, horizon=60, seed=3)
    ours = ExtendedKalmanFilter(s).run(d.y, d.u).x
    theirs = np.array([dapper_filter(s, d.x[b], d.y[b], "ExtKF", seed=1, infl=1.0) for b in range(2)])
    # measured: 3e-8 at the first analysis (DAPPER's prior + Q), decaying to 1e-11 by step 150
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-6 * 3.64)


def test_enkf_equals_dapper_enkf_pertobs_in_distribution():
    s = make_scenario("lorenz96")
    n, T, burn = 6, 120, 30
    d = simulate(s, n, horizon=T, seed=4)
    ours = EnsembleKalmanFilter(s, seed=1).run(d.y, d.u).x
    theirs = np.array(
        [dapper_filter(s, d.x[b], d.y[b], "EnKF", seed=10 + b, upd_a="PertObs", N=50, infl=1.0) for b in range(n)]
    )
    r_ours, r_ref = _rmse(ours, d.x, burn), _rmse(theirs, d.x, burn)
    diff = r_ours - r_ref
    tol = 4 * diff.std(ddof=1) / np.sqrt(n) + 0.05 * r_ref.mean()
    assert abs(diff.mean()) <= tol, (r_ours, r_ref, tol)


def test_enkf_reaches_dapper_band_at_sakov2008():
    """Observation variance 1, 40 members: with inflation 1.02 and Gaspari-Cohn localisation
    (radius 6 on the ring) ours lands in DAPPER's published band, as DAPPER's EnKF('PertObs',
    N=40, infl=1.06) does on the same data."""
    # sakov2008's ring: J = 40 (the package's calibrated default is J = 10, see Lorenz96's docstring)
    s = make_scenario(
        "lorenz96", n_vars=40, obs_noise_std=1.0, process_noise_std=0.003, prior_mean=2.34, prior_std=3.64
    )
    n, T, burn = 3, 250, 100
    d = simulate(s, n, horizon=T, seed=11)
    ours = EnsembleKalmanFilter(s, seed=1, n_members=40, inflation=1.02, localization_radius=6.0).run(d.y, d.u).x
    theirs = np.array(
        [dapper_filter(s, d.x[b], d.y[b], "EnKF", seed=20 + b, upd_a="PertObs", N=40, infl=1.06) for b in range(n)]
    )
    r_ours, r_ref = _rmse(ours, d.x, burn), _rmse(theirs, d.x, burn)
    print(f"sakov2008: ours {np.round(r_ours, 3)}, DAPPER {np.round(r_ref, 3)}")
    # DAPPER's band is for runs started at the truth; from the climatological prior its
    # non-localised EnKF loses some of these 3 trajectories (printed), ours does not.
    assert 0.15 < np.median(r_ours) < 0.24 and r_ours.max() < 0.26
