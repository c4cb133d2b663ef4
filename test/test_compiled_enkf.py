"""The EnKF's compiled path (filters/compiled_enkf.py) equals its batched numpy path, and the fast
keyed generators (filters/seeding.py) are numpy's, number for number."""

from __future__ import annotations

import numpy as np
import pytest

from neural_estimator.data import simulate
from neural_estimator.filters.kernels.rng import standard_normals
from neural_estimator.filters.enkf import EnsembleKalmanFilter
from neural_estimator.filters.scheduler import BlockScheduler
from neural_estimator.filters.seeding import KeyedSFC64
from neural_estimator.scenarios import make_scenario

# Largest allowed |compiled - batched| relative to the batched array's largest magnitude. The draws
# are the same numbers and the forecast is bit-equal; the matrix products take another BLAS call
# (scipy's through numba, not numpy's stacked matmul) and S is solved by Cholesky, not LU, so the
# last bits differ: measured up to 4e-15 (x) and 2e-14 (cov) over 300 steps, no growth along the run.
RTOL = 1e-12


def _plain(seed, key):
    return np.random.Generator(np.random.SFC64(np.random.SeedSequence(seed, spawn_key=key)))


@pytest.mark.parametrize("seed", [0, 3, 2**32 - 1, 2**32, 2**100 + 7])
def test_keyed_generators_are_numpys(seed):
    keyed = KeyedSFC64(seed)
    for key in [(0, 0, 0), (5, 1, 0), (1, 2, 3), (2**32, 0, 7), (2**40 + 3, 5, 2**33)]:
        ref = _plain(seed, key)
        np.testing.assert_array_equal(keyed.state(key), ref.bit_generator.state["state"]["state"])
        np.testing.assert_array_equal(keyed.generator(key, "slot").standard_normal(300), ref.standard_normal(300))
    sched = BlockScheduler(10, 4, 1, seed)
    np.testing.assert_array_equal(sched.rng(7, 2, 1).random(50), _plain(seed, (7, 2, 1)).random(50))
    with pytest.raises(ValueError, match="key must be"):
        keyed.state((1, -1, 0))


def test_compiled_standard_normals_are_numpys():
    """200,000 draws: the ziggurat's tail (about 1 in 3,600) and wedge (about 1 in 100) branches
    are taken many times."""
    keyed = KeyedSFC64(11)
    for key in [(0, 1, 0), (123, 2, 4)]:
        np.testing.assert_array_equal(
            standard_normals(keyed.pool, keyed.hc, *key, 100_000), _plain(11, key).standard_normal(100_000)
        )


def _pair(scen, **hp):
    fast, ref = EnsembleKalmanFilter(scen, seed=4, **hp), EnsembleKalmanFilter(scen, seed=4, **hp)
    ref.compiled_max_batch = 0
    return fast, ref


def _close(a, b):
    scale = float(np.abs(b).max())
    assert float(np.abs(a - b).max()) <= RTOL * scale


@pytest.mark.parametrize(
    "n_vars, substeps, hp",
    [
        (10, 1, {}),
        (40, 1, {}),
        (12, 1, {"inflation": 1.05, "q_inflation": 2.0, "localization_radius": 2.0}),
        (20, 3, {"n_members": 30}),
    ],
)
def test_compiled_enkf_equals_batched_path(n_vars, substeps, hp):
    scen = make_scenario("lorenz96", n_vars=n_vars, substeps=substeps)
    Y = simulate(scen, 3, 40, 2).y.copy()
    Y[1, 20] = np.nan  # a missing observation: predict only, in both paths
    Y[2, 0, 3] = np.inf
    fast, ref = _pair(scen, **hp)
    a, b = fast.run(Y), ref.run(Y)
    assert fast._compiled is not None and ref._compiled is None
    _close(a.x, b.x)
    _close(a.cov, b.cov)
    np.testing.assert_array_equal(a.diverged, b.diverged)
    # B = 1, the node's call: step in a loop equals run bit for bit, and the skipped flag is set
    fast1, ref1 = _pair(scen, **hp)
    a1 = fast1.run(Y[1:2])
    _close(a1.x, ref1.run(Y[1:2]).x)
    fast1.reset(1)
    held = []
    for k in range(25):
        np.testing.assert_array_equal(fast1.step(Y[1, k : k + 1]), a1.x[:, k])
        assert fast1.skipped[0] == (k == 20)
        held.append((fast1.covariance, fast1.covariance.copy()))
    np.testing.assert_array_equal(fast1.covariance, a1.cov[:, 24])
    for cov, copy in held:  # a handed-out covariance is never written again
        np.testing.assert_array_equal(cov, copy)


def test_compiled_enkf_init_from_observation():
    scen = make_scenario("lorenz96")
    Y = simulate(scen, 2, 10, 5).y
    fast, ref = _pair(scen, init="observation")
    _close(fast.run(Y).x, ref.run(Y).x)


def test_compiled_enkf_runs_every_batch_of_lorenz96_unless_capped():
    enkf = EnsembleKalmanFilter(make_scenario("lorenz96"))
    enkf.reset(5000)
    assert enkf._compiled is not None and len(enkf._blocks) > 1
    enkf.compiled_max_batch = 16  # a cap: larger batches take the batched numpy path
    enkf.reset(17)
    assert enkf._compiled is None
    enkf.reset(1)
    assert enkf._compiled is not None
    other = EnsembleKalmanFilter(make_scenario("bearings"))
    other.reset(1)
    assert other._compiled is None


@pytest.mark.parametrize("threads", [1, 2])
def test_compiled_enkf_over_several_blocks_equals_the_batched_path(threads):
    """Blocks of 3 streams (7 streams: 3 blocks, the last short) on one and two threads: each block
    draws the batched path's numbers of that block."""
    scen = make_scenario("lorenz96", n_vars=12)
    Y = simulate(scen, 7, 30, 4).y.copy()
    Y[5, 10] = np.nan
    fast, ref = _pair(scen, threads=threads)
    for f in (fast, ref):
        f.block_elements = 3 * f._stream_elements()
    a, b = fast.run(Y), ref.run(Y)
    assert len(fast._blocks) == 3 and fast._compiled is not None and ref._compiled is None
    _close(a.x, b.x)
    _close(a.cov, b.cov)
    np.testing.assert_array_equal(a.diverged, b.diverged)


def test_compiled_enkf_flags_a_diverged_stream():
    scen = make_scenario("lorenz96")
    fast, ref = _pair(scen)
    y = np.full((1, scen.dy), 1e200)
    for est in (fast, ref):
        est.reset(1)
        for _ in range(6):
            x = est.step(y)
    assert fast.diverged[0] == ref.diverged[0]
    assert np.isnan(x).all() == ref.diverged[0]


@pytest.mark.parametrize("n_vars", [10, 40])
def test_compiled_enkf_predict_is_bit_equal(n_vars):
    """The forecast (RK4 and process noise) is the batched path's bit for bit, on both loop orders."""
    scen = make_scenario("lorenz96", n_vars=n_vars)
    fast, ref = _pair(scen)
    for est in (fast, ref):
        est.reset(2)
        est._k = 3
    ref._X = fast._X.copy()
    fast._predict(np.zeros((2, 0)))
    ref._predict(np.zeros((2, 0)))
    np.testing.assert_array_equal(fast._X, ref._X)
