"""The data-assimilation options of the ensemble filters: inflation, localisation, regularisation."""

from __future__ import annotations

import numpy as np
import pytest

from neural_estimator.methods.registry import EstimatorError
from neural_estimator.filters import (
    EnsembleKalmanFilter,
    ParticleFilter,
)
from neural_estimator.scenarios import make_scenario
from filter_cases import (
    FILTERS,
    data,
)


# ---- data-assimilation options: inflation, localisation, regularisation ------------------------------
def test_inflation_options_off_by_default_and_validated():
    s = make_scenario("test_filters_linear")
    x, y, u = data(s, 3, 8, seed=2)
    for method in ("ekf", "ukf", "enkf"):
        default = FILTERS[method](s, seed=4).run(y, u)
        off = FILTERS[method](s, seed=4, inflation=1.0, q_inflation=1.0).run(y, u)
        np.testing.assert_array_equal(default.x, off.x)
        np.testing.assert_array_equal(default.cov, off.cov)
        for bad in (0, -1.0, float("inf"), True, '"x"'):
            with pytest.raises(EstimatorError, match="inflation must be a (finite )?number"):
                FILTERS[method](s, inflation=bad)
        assert np.allclose(FILTERS[method](s, q_inflation=4.0).Q, 4.0 * s.process_cov())
    enkf = EnsembleKalmanFilter(s, seed=4, localization_radius=None).run(y, u)
    np.testing.assert_array_equal(enkf.x, EnsembleKalmanFilter(s, seed=4).run(y, u).x)
    pf = ParticleFilter(s, seed=4, regularization=0.0).run(y, u)
    np.testing.assert_array_equal(pf.x, ParticleFilter(s, seed=4).run(y, u).x)


@pytest.mark.parametrize("method", ["ekf", "ukf"])
def test_multiplicative_inflation_scales_the_predicted_spread(method):
    """P^- = inflation^2 (propagated covariance) + Q: with Q removed, the ratio is inflation^2."""
    s = make_scenario("test_filters_pendulum")
    x, y, u = data(s, 4, 2, seed=3)
    preds = []
    for lam in (1.0, 1.3):
        f = FILTERS[method](s, inflation=lam)
        f.reset(4)
        f.step(y[:, 0])
        f._predict(np.ascontiguousarray(u[:, 0]))
        preds.append(f._P - f.Q)
    np.testing.assert_allclose(preds[1], 1.3**2 * preds[0], rtol=1e-9, atol=1e-14)


def test_gaspari_cohn_taper():
    from neural_estimator.filters.localization import gaspari_cohn

    z = np.array([0.0, 1.0 - 1e-12, 1.0 + 1e-12, 2.0, 2.5])
    rho = gaspari_cohn(z)
    assert rho[0] == 1.0 and rho[3] == 0.0 and rho[4] == 0.0
    np.testing.assert_allclose(rho[1:3], 5.0 / 24.0, atol=1e-9)  # continuous at z = 1
    fine = gaspari_cohn(np.linspace(0, 2, 2001))
    assert np.all(np.diff(fine) <= 1e-15)  # decreasing
    # a correlation function: the taper matrix of points on a line is positive semi-definite
    pts = np.linspace(0, 10, 60)
    assert np.linalg.eigvalsh(gaspari_cohn(np.abs(pts[:, None] - pts[None, :]) / 1.5)).min() > -1e-10


def test_localization_cuts_far_observations_on_lorenz96():
    """With radius c, the cross-covariance between a variable and an observation farther than 2c
    (ring distance) is zeroed, so that observation moves the variable only through the (global)
    solve with S: orders of magnitude less than without localisation, where sample correlations
    of 40 members carry it. A huge radius is no localisation (to the taper's 1 - O(1/c^2)).
    On DAPPER's 40-variable ring, where localisation matters (the calibrated default has J = 10)."""
    s = make_scenario(
        "lorenz96", n_vars=40, obs_noise_std=0.25, process_noise_std=0.003, prior_mean=2.34, prior_std=3.64
    )
    x, y, u = data(s, 2, 2, seed=1)
    y2 = y.copy()
    y2[:, 0, 20] += 3.0  # variable 20 is ring distance >= 8 from variables 0..12
    far = {}
    for radius in (4.0, None):
        outs = [
            EnsembleKalmanFilter(s, seed=2, localization_radius=radius).run(yy[:, :1], u[:, :1]).x[:, 0]
            for yy in (y, y2)
        ]
        d = np.abs(outs[0] - outs[1])
        far[radius] = d[:, :13].max()
        assert d[:, 20].min() > 0.1  # the observed variable itself moves
    assert far[4.0] < 1e-3 * far[None], far
    wide = EnsembleKalmanFilter(s, seed=2, localization_radius=1e7).run(y, u).x
    plain = EnsembleKalmanFilter(s, seed=2).run(y, u).x
    np.testing.assert_allclose(wide, plain, atol=1e-6)


def test_localization_needs_declared_distances():
    s = make_scenario("test_filters_linear")
    with pytest.raises(EstimatorError, match="localization needs distances"):
        EnsembleKalmanFilter(s, localization_radius=2.0)
    with pytest.raises(EstimatorError, match="localization_radius must be a finite number > 0"):
        EnsembleKalmanFilter(make_scenario("lorenz96"), localization_radius=0)


def test_regularization_jitters_resampled_particles_by_the_spread():
    """After resampling, duplicates become distinct, with a spread ~ c h_opt times the ensemble's."""
    s = make_scenario("test_filters_linear")
    x, y, u = data(s, 4, 3, seed=5)
    for reg in (0.0, 1.0):
        pf = ParticleFilter(s, seed=1, n_particles=512, ess_fraction=1.0, regularization=reg)  # always resample
        pf.reset(4)
        pf.step(y[:, 0])
        distinct = np.mean([np.unique(pf._X[b], axis=0).shape[0] for b in range(4)])
        if reg == 0.0:
            assert distinct < 0.8 * 512
        else:
            assert distinct == 512
    assert pf.bandwidth == pytest.approx((4 / (512 * (4 + 2))) ** (1 / 8))
    with pytest.raises(EstimatorError, match="regularization must be a finite number >= 0"):
        ParticleFilter(s, regularization=-1)
