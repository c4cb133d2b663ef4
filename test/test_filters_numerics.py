"""The filters' numerics (filters/numerics.py: Cholesky with jitter, PSD solves, resampling, log weights) and
the PF's compiled kernels (filters/compiled.py) against the numpy reference path.
"""

from __future__ import annotations

import importlib

import numpy as np
import pytest

from neural_estimator.methods.registry import EstimatorError, make_estimator
from neural_estimator.filters import (
    ParticleFilter,
)
from neural_estimator.filters import numerics as nm
from neural_estimator.scenarios import make_scenario
from filter_cases import (
    FILTERS,
    scenario_or_skip,
    data,
    paired_rmse_check,
)


# ---- numerics -------------------------------------------------------------------------------------------
def test_cholesky_jitter_per_matrix():
    A = np.stack([np.eye(3) * 2.0, np.diag([1.0, 1.0, 0.0]), np.diag([1.0, -1.0, 1.0])])
    L, ok = nm.cholesky(A)
    np.testing.assert_array_equal(ok, [True, True, False])
    np.testing.assert_allclose(L[0] @ L[0].T, A[0])
    np.testing.assert_allclose(L[1] @ L[1].T, A[1], atol=1e-8)  # singular PSD: factored with jitter
    assert np.isnan(L[2]).all()
    L, ok = nm.cholesky(A[:1])
    assert ok is None


def test_psd_solve_never_raises_for_the_batch():
    S = np.stack([np.array([[2.0, 0.5], [0.5, 1.0]]), np.zeros((2, 2))])
    B = np.ones((2, 2, 3))
    X = nm.psd_solve(S, B)
    np.testing.assert_allclose(S[0] @ X[0], B[0])
    assert not np.isfinite(X[1]).all()


@pytest.mark.slow
def test_systematic_resample_equals_filterpy(monkeypatch):
    rng = np.random.default_rng(0)
    w = rng.random((6, 50)) ** 4
    w /= w.sum(axis=1, keepdims=True)
    offsets = rng.random(6)
    idx = nm.systematic_resample(w, offsets)
    import filterpy.monte_carlo.resampling as fpr

    for b in range(6):
        monkeypatch.setattr(fpr, "random", lambda o=offsets[b]: o)
        np.testing.assert_array_equal(idx[b], fpr.systematic_resample(w[b]))


def test_log_weights_normalise_without_overflow():
    logw = np.array([[-1e4, -1e4 + 1.0, -1e4 - 800.0], [0.0, -np.inf, -np.inf]])
    lw, w = nm.normalize_log_weights(logw)
    np.testing.assert_allclose(w.sum(axis=1), 1.0)
    np.testing.assert_allclose(w[0, :2], [1 / (1 + np.e), np.e / (1 + np.e)])
    assert w[0, 2] == 0.0  # far below e^-600: exactly zero, not subnormal
    np.testing.assert_allclose(np.exp(lw[1]), [1.0, 0.0, 0.0])


def test_registry_builds_every_filter():
    s = make_scenario("test_filters_linear")
    for method, cls in FILTERS.items():
        f = make_estimator(method, s, seed=1)
        assert type(f) is cls and f.method == method
        assert importlib.import_module("neural_estimator.filters").__dict__[cls.__name__] is cls


# ---- the PF's compiled kernels (filters/kernels/) against the numpy reference path ------------------
def test_compiled_normals_are_standard_normal():
    """The keyed ziggurat generator: moments, a KS test, the tail beyond the ziggurat's base strip
    (drawn by a separate branch) at its Gaussian rate, and distinct keys give distinct streams."""
    from scipy import stats

    from neural_estimator.filters.kernels import rng as ck

    z = ck.stream_normals(7, 3, 1, 11, 400_000)
    se = 1 / np.sqrt(z.size)
    assert abs(z.mean()) < 4 * se and abs(z.var() - 1) < 4 * np.sqrt(2) * se
    assert stats.kstest(z, "norm").pvalue > 1e-3
    tail = (np.abs(z) > ck._ZIG_R).mean()
    expect = 2 * stats.norm.sf(ck._ZIG_R)
    assert abs(tail - expect) < 4 * np.sqrt(expect / z.size), (tail, expect)
    np.testing.assert_array_equal(z[:100], ck.stream_normals(7, 3, 1, 11, 100))
    for key in [(8, 3, 1, 11), (7, 4, 1, 11), (7, 3, 2, 11), (7, 3, 1, 12)]:
        other = ck.stream_normals(*key, 100)
        assert abs(np.corrcoef(z[:100], other)[0, 1]) < 0.4 and not np.array_equal(z[:100], other)


@pytest.mark.parametrize("substeps", [1, 3])
def test_compiled_lorenz96_transition_is_bit_equal(substeps):
    from neural_estimator.filters.kernels import lorenz96 as ck

    s = make_scenario("lorenz96", substeps=substeps)
    X = np.random.default_rng(0).normal(2.3, 3.6, (2, 64, 40))
    Y = X.copy()
    cfg = s.config
    ck.lorenz96_transition(Y, cfg.forcing, cfg.dt / cfg.substeps, cfg.substeps)
    np.testing.assert_array_equal(Y, s.f(X, None))


@pytest.mark.parametrize("name", ["lorenz96", "nlink", "ballistic", "bearings", "quadrotor", "test_filters_pendulum"])
def test_compiled_pf_predict_equals_numpy_given_the_same_draws(name):
    """One compiled predict step == the scenario's numpy f plus the stream's keyed draws times sqrt(Q)
    (the built-ins: the fused kernels of filters/kernels; the others: numpy
    f + the compiled noise; angles normalised)."""
    from neural_estimator.filters.kernels import rng as ck
    from neural_estimator.filters.base import PHASE_PREDICT

    s = scenario_or_skip(name)
    x, y, u = data(s, 5, 3, seed=2)
    pf = ParticleFilter(s, seed=9, n_particles=16, threads=2)
    pf.block_elements = 2 * pf._stream_elements()  # blocks of 2 streams: keys must follow the stream
    pf.reset(5)
    pf._k = 4
    X0 = pf._X.copy()
    pf._predict(np.ascontiguousarray(u[:, 0]))
    fx = s.f(X0, np.broadcast_to(u[:, 0][:, None, :], (5, 16, s.du)))
    L = pf._sqrt_Q if pf._sd_Q is None else np.diag(pf._sd_Q)
    for b in range(5):
        z = ck.stream_normals(9, 4, PHASE_PREDICT, b, 16 * s.dx).reshape(16, s.dx)
        expect = s.normalize_state(fx[b] + z @ L.T)
        np.testing.assert_allclose(s.state_residual(pf._X[b], expect), 0.0, atol=1e-12)


@pytest.mark.parametrize("name", ["lorenz96", "quadrotor"])
def test_compiled_linear_likelihood_equals_numpy(name):
    s = scenario_or_skip(name)
    x, y, u = data(s, 3, 2, seed=2)
    pf = ParticleFilter(s, seed=9, n_particles=32)
    assert pf._ck_H is not None
    pf.reset(3)
    logw = np.random.default_rng(1).normal(-np.log(32), 0.1, (3, 32))
    got, want = pf._update_block_compiled(pf._X, logw, y[:, 0]), pf._update_block(pf._X, logw, y[:, 0])
    for g, w in zip(got[:2], want[:2]):  # log-weights and weights (the third is the ok flag, None)
        np.testing.assert_allclose(g, w, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("name", ["nlink", "ballistic", "bearings"])
def test_compiled_model_likelihood_equals_numpy(name):
    """The scenarios' compiled h likelihoods (masses' positions, range, wrapped bearing) == numpy's."""
    s = scenario_or_skip(name)
    x, y, u = data(s, 3, 2, seed=2)
    pf = ParticleFilter(s, seed=9, n_particles=64, init_std=2.0)
    assert pf._ck_loglik is not None and pf._ck_H is None
    pf.reset(3)
    pf._X = pf._X + np.random.default_rng(4).normal(0.0, 0.5, pf._X.shape)  # spread: large innovations too
    if name == "bearings":  # bearings around +-pi, where the innovation must wrap
        y = np.where(np.arange(3)[:, None, None] == 0, np.pi - 1e-3, y)
    logw = np.random.default_rng(1).normal(-np.log(64), 0.1, (3, 64))
    got, want = pf._update_block_compiled(pf._X, logw, y[:, 0]), pf._update_block(pf._X, logw, y[:, 0])
    for g, w in zip(got[:2], want[:2]):
        np.testing.assert_allclose(g, w, rtol=1e-10, atol=1e-9)


def test_compiled_model_transitions_match_the_scenarios():
    """N-link (own sine and cosine: a few ulp) and ballistic (also below ground) kernels. The ballistic
    kernel calls libm's exp; numpy's f is bit-equal to it where numpy's exp is libm's, and within a few
    ulp on CPUs where numpy takes its own AVX-512 exp (last place differs on about 5 % of arguments)."""
    from neural_estimator.filters.kernels import ballistic, nlink

    rng = np.random.default_rng(0)
    s = make_scenario("nlink", n_links=4)
    x = s.sample_initial(rng, 3000) + rng.normal(0.0, 2.0, (3000, 8))  # 3000: not a multiple of the pass
    X = x.copy()
    _, W, G = s._constants()
    nlink.nlink_transition(X, s.config.dt / s.config.substeps, s.config.substeps, np.ascontiguousarray(W), -G)
    np.testing.assert_allclose(s.state_residual(X, s.f(x)), 0.0, atol=1e-12)
    b = make_scenario("ballistic", substeps=3)
    x = b.sample_initial(rng, 500)
    x[:250, 0] = rng.normal(0.0, 3.0, 250)  # around and below the ground, where E(a) = 1
    X = x.copy()
    cfg = b.config
    ballistic.ballistic_transition(X, cfg.g, cfg.k, cfg.dt / cfg.substeps, cfg.substeps)
    np.testing.assert_allclose(X, b.f(x), rtol=1e-14, atol=1e-13)


@pytest.mark.slow
def test_compiled_sincos_is_within_two_ulp():
    import numba as nb

    from neural_estimator.filters.kernels import trig as cm

    @nb.njit
    def both(x, s, c):
        for i in range(x.size):
            s[i], c[i] = cm._sincos(x[i])

    x = np.concatenate([np.random.default_rng(1).uniform(-50.0, 50.0, 200_000), np.arange(-8, 9) * np.pi / 4])
    s, c = np.empty_like(x), np.empty_like(x)
    both(x, s, c)
    for got, want in ((s, np.sin(x)), (c, np.cos(x))):
        err = np.abs(got - want) / np.spacing(np.maximum(np.abs(want), 1e-300))
        # near a zero of sin or cos the reference's own rounding of x dominates: absolute 1e-16 there
        assert np.all((err <= 2.0) | (np.abs(got - want) < 2e-16)), err.max()


@pytest.mark.parametrize("name", ["nlink", "lorenz96"])
def test_compiled_weighted_moments_equal_numpy(name):
    """The PF's compiled estimate: circular mean for angles (straddling the +-pi cut), plain mean
    otherwise, and the weighted covariance of the wrapped residuals, against the numpy path."""
    from neural_estimator.filters.kernels import pf as cm
    from neural_estimator.filters.numerics import weighted_covariance

    s = make_scenario(name)
    rng = np.random.default_rng(3)
    X = s.normalize_state(rng.normal(np.pi - 0.2, 0.3, (4, 50, s.dx)))
    w = rng.dirichlet(np.ones(50), 4)
    mean, cov = np.empty((4, s.dx)), np.empty((4, s.dx, s.dx))
    cm.weighted_moments(X, w, np.isin(np.arange(s.dx), s.angle_states), mean, cov)
    want = s.state_mean(X, w)
    np.testing.assert_allclose(s.state_residual(mean, want), 0.0, atol=1e-12)
    np.testing.assert_allclose(cov, weighted_covariance(s.state_residual(X, want[:, None, :]), w), atol=1e-12)
    np.testing.assert_array_equal(cov, np.swapaxes(cov, 1, 2))


def test_compiled_weight_normalisation_equals_numpy():
    """log-sum-exp normalisation per row == numerics.normalize_log_weights, including the floor of
    negligible weights (exactly 0) and the rows that must come back NaN (all -inf, or a NaN)."""
    from neural_estimator.filters.kernels import pf as ck
    from neural_estimator.filters.numerics import LOG_W_FLOOR, normalize_log_weights

    logw = np.random.default_rng(2).normal(-5.0, 300.0, (5, 64))
    logw[1, :] = -np.inf
    logw[2, 7] = np.nan
    logw[3, 3] = 1e6  # every other weight below the floor: exactly one particle left
    with np.errstate(divide="ignore", invalid="ignore"):
        want_l, want_w = normalize_log_weights(logw)
    got_l, got_w = logw.copy(), np.empty_like(logw)
    ck.normalize_log_weights_rows(got_l, got_w, LOG_W_FLOOR)
    np.testing.assert_allclose(got_l, want_l, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(got_w, want_w, rtol=1e-12, atol=1e-300)
    assert np.isnan(got_w[1]).all() and np.isnan(got_w[2]).all() and np.count_nonzero(got_w[3]) == 1


@pytest.mark.parametrize(
    "name", ["test_filters_linear", "test_filters_pendulum", "nlink", "ballistic", "bearings", "quadrotor"]
)
def test_compiled_pf_equals_numpy_pf_in_distribution(name):
    """Same algorithm, different random numbers: per-trajectory RMSE equal (paired test)."""
    s = scenario_or_skip(name)
    x, y, u = data(s, 40, 15, seed=8)
    fast = ParticleFilter(s, seed=2, n_particles=256).run(y, u).x
    ref = ParticleFilter(s, seed=3, n_particles=256, compiled=False).run(y, u).x
    paired_rmse_check(s, fast, ref, x, f"{name} compiled PF vs numpy PF")


def test_compiled_option_is_checked():
    s = scenario_or_skip("test_filters_linear")
    assert ParticleFilter(s, compiled="false")._compiled is False
    assert ParticleFilter(s, compiled="yes")._compiled is True  # the package's one grammar
    for bad in (2, "sometimes"):
        with pytest.raises(EstimatorError, match="compiled must be true or false"):
            ParticleFilter(s, compiled=bad)


def test_compiled_systematic_resampling_equals_numpy_per_row():
    from neural_estimator.filters.kernels import pf as ck

    rng = np.random.default_rng(4)
    for N in (1, 7, 256):
        w = rng.dirichlet(np.full(N, 0.3), size=5)
        w[1] = 0.0
        w[1, N // 2] = 1.0  # a collapsed row
        u = rng.random(5)
        X = rng.normal(size=(5, N, 3))
        need = np.array([True, True, False, True, True])
        got = X.copy()
        ck.systematic_resample_rows(got, w, u, need)
        for r in range(5):
            if need[r]:
                idx = nm.systematic_resample(w[r : r + 1], u[r : r + 1])[0]
                np.testing.assert_array_equal(got[r], X[r, idx])
            else:
                np.testing.assert_array_equal(got[r], X[r])
