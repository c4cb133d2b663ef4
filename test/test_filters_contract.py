"""The classical filters' estimator contract: run == loop of step (bit for bit), blocking, threads and batch
size change nothing, NaN rows skip the update, divergence is flagged per stream, bad input raises, and the
paper's hyperparameter defaults.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest

from neural_estimator.data.simulate import simulate
from neural_estimator.methods.registry import EstimatorError, make_estimator, previous_controls
from neural_estimator.filters import (
    EKFHyperParams,
    EnKFHyperParams,
    ParticleFilter,
    PFHyperParams,
    UKFHyperParams,
)
from neural_estimator.scenarios import make_scenario
from filter_cases import (
    FILTERS,
    scenario_or_skip,
    data,
)


# ---- contract: run == loop of step, NaN skipping, divergence, bad input ---------------------------------
CONTRACT_SCENARIOS = ("test_filters_linear", "test_filters_pendulum", "bearings")


@pytest.mark.parametrize("name", CONTRACT_SCENARIOS)
@pytest.mark.parametrize("method", list(FILTERS))
def test_run_equals_loop_of_step(method, name):
    s = scenario_or_skip(name)
    x, y, u = data(s, 5, 20, seed=8)
    y[1, 4] = np.nan  # a skipped update inside the sequence
    y[3, 0, 0] = np.inf
    opts = {"n_particles": 256} if method == "pf" else {}
    est = make_estimator(method, s, seed=3, **opts).run(y, u)
    f = make_estimator(method, s, seed=3, **opts)
    f.reset(5)
    up = previous_controls(u)
    for k in range(20):
        xk = f.step(y[:, k], up[:, k])
        np.testing.assert_array_equal(xk, est.x[:, k])
        np.testing.assert_array_equal(f.covariance, est.cov[:, k])
    np.testing.assert_array_equal(f.diverged, est.diverged)


@pytest.mark.parametrize("name", CONTRACT_SCENARIOS)
@pytest.mark.parametrize("method", ["ekf", "ukf"])
def test_blocking_does_not_change_results(method, name):
    """Streams are processed in cache-sized blocks; one stream per block agrees to round-off.

    (Not bit for bit: numpy's stacked matmul and einsum may take another kernel for another stack
    size. run and step share the blocks, so they stay bit-equal.) The EnKF and PF draw per block,
    so for them the block size is part of the random stream: see the two tests below.
    """
    s = scenario_or_skip(name)
    x, y, u = data(s, 6, 12, seed=13)
    y[2, 3] = np.nan
    whole = FILTERS[method](s, seed=3)
    single = FILTERS[method](s, seed=3)
    single.block_elements = 1
    a, b = whole.run(y, u), single.run(y, u)
    assert len(single._blocks) == 6 and len(whole._blocks) == 1
    np.testing.assert_allclose(a.x, b.x, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(a.cov, b.cov, rtol=1e-12, atol=1e-12)


def _blocked(method, s, block_streams, threads):
    """A filter whose blocks hold ``block_streams`` streams, on ``threads`` threads."""
    opts = {"n_particles": 64} if method == "pf" else {}
    f = FILTERS[method](s, seed=3, threads=threads, **opts)
    f.block_elements = block_streams * f._stream_elements()
    assert f.block_size == block_streams
    return f


@pytest.mark.parametrize("name", CONTRACT_SCENARIOS)
@pytest.mark.parametrize("method", list(FILTERS))
def test_threads_do_not_change_results(method, name):
    """Blocks run concurrently on threads, draws keyed by block: bit-equal to one thread."""
    s = scenario_or_skip(name)
    x, y, u = data(s, 7, 10, seed=13)
    y[2, 3] = np.nan
    one = _blocked(method, s, 2, threads=1).run(y, u)
    three = _blocked(method, s, 2, threads=3).run(y, u)
    np.testing.assert_array_equal(one.x, three.x)
    np.testing.assert_array_equal(one.cov, three.cov)
    np.testing.assert_array_equal(one.diverged, three.diverged)


@pytest.mark.parametrize("name", CONTRACT_SCENARIOS)
@pytest.mark.parametrize("method", ["enkf", "pf"])
def test_stream_draws_do_not_depend_on_batch_size(method, name):
    """A stream's random numbers depend on the seed and its index only: the first B streams of a
    larger batch equal a batch of B (here B = 5 ends in a partial block of 1, the larger run has 2
    there), to round-off (stacks of 1 and 2 may take different matmul kernels)."""
    s = scenario_or_skip(name)
    x, y, u = data(s, 6, 10, seed=13)
    big = _blocked(method, s, 2, threads=2).run(y, u)
    small = _blocked(method, s, 2, threads=2).run(y[:5], u[:5])
    np.testing.assert_allclose(small.x, big.x[:5], rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(small.cov, big.cov[:5], rtol=1e-10, atol=1e-10)


def test_threads_option_is_checked():
    s = scenario_or_skip("test_filters_linear")
    assert FILTERS["ukf"](s, threads="2").threads == 2
    for bad in (0, -1, "two", 1.5):
        with pytest.raises(EstimatorError, match="threads must be an integer"):
            FILTERS["ukf"](s, threads=bad)


def test_threads_default_comes_from_the_environment(monkeypatch):
    s = scenario_or_skip("test_filters_linear")
    monkeypatch.setenv("NEURAL_ESTIMATOR_THREADS", "3")
    assert FILTERS["pf"](s).threads == 3
    monkeypatch.setenv("NEURAL_ESTIMATOR_THREADS", "0")
    with pytest.raises(EstimatorError, match=r"\$NEURAL_ESTIMATOR_THREADS: threads must be an integer"):
        FILTERS["pf"](s)


@pytest.mark.parametrize("method", list(FILTERS))
def test_nan_observation_predicts_only(method):
    s = make_scenario("test_filters_pendulum")
    x, y, u = data(s, 3, 6, seed=9)
    up = previous_controls(u)
    opts = {"n_particles": 128} if method == "pf" else {}
    f = FILTERS[method](s, seed=4, **opts)
    g = FILTERS[method](s, seed=4, **opts)
    f.reset(3)
    g.reset(3)
    for k in range(4):
        f.step(y[:, k], up[:, k])
        g.step(y[:, k], up[:, k])
    predicted = copy.deepcopy(f)
    predicted._predict(up[:, 4])
    m_pred, P_pred = predicted._estimate()
    bad = y[:, 4].copy()
    bad[1, 0] = np.nan
    xk = f.step(bad, up[:, 4])
    xg = g.step(y[:, 4], up[:, 4])
    np.testing.assert_array_equal(f.skipped, [False, True, False])
    np.testing.assert_array_equal(g.skipped, [False, False, False])
    np.testing.assert_allclose(xk[1], m_pred[1], rtol=1e-12, atol=1e-12)  # stream 1: prediction only
    np.testing.assert_allclose(f.covariance[1], P_pred[1], rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(xk[[0, 2]], xg[[0, 2]])  # the other streams are not affected
    assert not f.diverged.any()
    # A skipped first observation leaves the prior (EKF/UKF: exactly m0, P0).
    if method in ("ekf", "ukf"):
        h = FILTERS[method](s)
        x0 = h.step(np.full((2, s.dy), np.nan))
        np.testing.assert_array_equal(x0, np.broadcast_to(s.prior()[0], (2, s.dx)))
        np.testing.assert_array_equal(h.covariance, np.broadcast_to(s.prior()[1], (2, s.dx, s.dx)))


@pytest.mark.parametrize("method", list(FILTERS))
def test_divergence_flagged_per_stream(method):
    s = make_scenario("test_filters_explosive")
    x, y, u = data(s, 3, 8, seed=10)
    y_bad = y.copy()
    y_bad[1, 2] = 1e200  # stream 1 is told it is at 1e200; squaring overflows on the next steps
    opts = {"n_particles": 128} if method == "pf" else {}
    bad = FILTERS[method](s, seed=5, **opts).run(y_bad, u)
    good = FILTERS[method](s, seed=5, **opts).run(y, u)
    np.testing.assert_array_equal(bad.diverged, [False, True, False])
    first = np.flatnonzero(np.isnan(bad.x[1]).any(axis=1))[0]
    assert 2 <= first <= 4
    assert np.isnan(bad.x[1, first:]).all() and np.isnan(bad.cov[1, first:]).all()
    assert np.isfinite(bad.x[1, :first]).all()
    np.testing.assert_array_equal(bad.x[[0, 2]], good.x[[0, 2]])  # the others go on, untouched
    np.testing.assert_array_equal(bad.cov[[0, 2]], good.cov[[0, 2]])
    assert not good.diverged.any()


@pytest.mark.parametrize("method", list(FILTERS))
def test_bad_input_raises(method):
    s = make_scenario("test_filters_linear")
    f = make_estimator(method, s)
    with pytest.raises(EstimatorError, match="observation must be"):
        f.step(np.zeros((2, s.dy + 1)))
    with pytest.raises(EstimatorError, match="observations must be"):
        f.run(np.zeros((2, 5, 3)))
    with pytest.raises(EstimatorError, match="unknown option"):
        make_estimator(method, s, not_an_option=1)
    f.reset(2)
    with pytest.raises(EstimatorError, match="batch of 3"):
        f.step(np.zeros((3, s.dy)))


@pytest.mark.parametrize("method", list(FILTERS))
def test_non_psd_prior_raises(method):
    s = make_scenario("test_filters_linear")
    m0, P0 = s.prior()
    P_bad = P0.copy()
    P_bad[0, 1] = P_bad[1, 0] = 2.0  # symmetric, eigenvalue -1
    s.prior = lambda: (m0, P_bad)
    with pytest.raises(EstimatorError, match="prior covariance P0 is not positive semi-definite"):
        make_estimator(method, s)
    s.prior = lambda: (m0, P0 + np.triu(np.ones((4, 4)), 1))
    with pytest.raises(EstimatorError, match="not symmetric"):
        make_estimator(method, s)


def test_hyperparameter_defaults_are_the_papers():
    assert (UKFHyperParams().alpha, UKFHyperParams().beta, UKFHyperParams().kappa) == (1e-3, 2.0, 0.0)
    assert EnKFHyperParams().n_members == 50
    hp = PFHyperParams()
    assert (hp.n_particles, hp.init_std, hp.ess_fraction, hp.rejuvenation_std) == (1024, 1.0, 0.5, 0.0)
    assert EKFHyperParams().joseph_form
    s = make_scenario("test_filters_linear")
    f = make_estimator("pf", s, n_particles="64", rejuvenation_std=0.1)  # strings as from a command line
    assert f.hp.n_particles == 64 and f.hp.rejuvenation_std == 0.1
    with pytest.raises(EstimatorError, match="ess_fraction"):
        make_estimator("pf", s, ess_fraction=1.5)
    for cls in FILTERS.values():
        assert cls.has_covariance


def test_pf_initial_spread_is_isotropic_std_one():
    s = make_scenario("test_filters_pendulum")  # P0 = diag(0.3^2, 0.5^2): the spread must ignore it
    f = ParticleFilter(s, n_particles=20000)
    f.reset(1)
    X = f._X[0]
    np.testing.assert_allclose(s.state_mean(X), s.prior()[0], atol=0.03)
    np.testing.assert_allclose(X[:, 1].std(), 1.0, rtol=0.03)
    g = ParticleFilter(s, n_particles=20000, init_std=None)
    g.reset(1)
    np.testing.assert_allclose(g._X[0, :, 1].std(), 0.5, rtol=0.03)


def test_rejuvenation_jitters_resampled_particles():
    s = make_scenario("test_filters_linear")
    x, y, u = data(s, 2, 6, seed=12)
    plain = ParticleFilter(s, n_particles=256, seed=1)
    jit = ParticleFilter(s, n_particles=256, seed=1, rejuvenation_std=0.05)
    for f in (plain, jit):
        f.reset(2)
        f.step(y[:, 0])
    # after the first update the ESS is far below N / 2 and both resampled: duplicates only without jitter
    assert len(np.unique(plain._X[0, :, 0])) < 256
    assert len(np.unique(jit._X[0, :, 0])) == 256


def test_step_before_reset_starts_the_observations_batch_in_both_families():
    """The Estimator contract: a step before any reset starts as many streams as y has rows."""
    s = make_scenario("lorenz96")
    d = simulate(s, 3, 2, seed=1)
    for method in ("ukf", "gru"):
        fresh, reset = make_estimator(method, s), make_estimator(method, s)
        reset.reset(3)
        np.testing.assert_array_equal(fresh.step(d.y[:, 0]), reset.step(d.y[:, 0]))
        assert fresh.batch == 3
