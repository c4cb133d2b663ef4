"""The EKF's compiled single-stream path (filters/compiled_ekf.py) equals its batched numpy path."""

from __future__ import annotations

import numpy as np
import pytest

from neural_estimator.data import simulate
from neural_estimator.filters.ekf import ExtendedKalmanFilter
from neural_estimator.scenarios import make_scenario


def _pair(scen, **hp):
    fast, ref = ExtendedKalmanFilter(scen, **hp), ExtendedKalmanFilter(scen, **hp)
    ref.compiled_max_batch = 0
    return fast, ref


@pytest.mark.parametrize(
    "n_vars, substeps, hp",
    [(10, 1, {}), (40, 1, {}), (12, 3, {"inflation": 1.05, "q_inflation": 2.0, "joseph_form": False})],
)
def test_compiled_ekf_equals_batched_path(n_vars, substeps, hp):
    scen = make_scenario("lorenz96", n_vars=n_vars, substeps=substeps)
    data = simulate(scen, 3, 60, 2)
    Y = data.y.copy()
    Y[1, 20] = np.nan  # a missing observation: predict only, in both paths
    fast, ref = _pair(scen, **hp)
    a, b = fast.run(Y), ref.run(Y)
    assert fast._compiled is not None and ref._compiled is None
    np.testing.assert_allclose(a.x, b.x, rtol=1e-11, atol=1e-11)
    np.testing.assert_allclose(a.cov, b.cov, rtol=1e-10, atol=1e-12)
    np.testing.assert_array_equal(a.diverged, b.diverged)
    # step at B = 1 (the node's call) gives the same as run, and the handed-out covariance stays put
    fast.reset(1)
    held = []
    for k in range(10):
        fast.step(Y[0, k : k + 1])
        held.append((fast.covariance, fast.covariance.copy()))
    np.testing.assert_allclose(fast.covariance[0], b.cov[0, 9], rtol=1e-10, atol=1e-12)
    for cov, copy in held:
        np.testing.assert_array_equal(cov, copy)


def test_compiled_ekf_runs_every_batch_of_lorenz96_unless_capped():
    scen = make_scenario("lorenz96")
    ekf = ExtendedKalmanFilter(scen)
    ekf.reset(5000)
    assert ekf._compiled is not None
    ekf.compiled_max_batch = 16  # a cap: larger batches take the batched numpy path
    ekf.reset(17)
    assert ekf._compiled is None
    other = ExtendedKalmanFilter(make_scenario("bearings"))
    other.reset(1)
    assert other._compiled is None


@pytest.mark.parametrize("threads", [1, 2])
def test_compiled_ekf_over_several_blocks_equals_the_batched_path(threads):
    """Blocks of 3 streams (7 streams: 3 blocks, the last short) on one and two threads."""
    scen = make_scenario("lorenz96", n_vars=12)
    Y = simulate(scen, 7, 30, 4).y.copy()
    Y[5, 10] = np.nan
    fast, ref = _pair(scen, threads=threads)
    for f in (fast, ref):
        f.block_elements = 3 * f._stream_elements()
    a, b = fast.run(Y), ref.run(Y)
    assert len(fast._blocks) == 3 and fast._compiled is not None and ref._compiled is None
    np.testing.assert_allclose(a.x, b.x, rtol=1e-11, atol=1e-11)
    np.testing.assert_allclose(a.cov, b.cov, rtol=1e-10, atol=1e-12)


def test_compiled_ekf_flags_a_diverged_stream():
    scen = make_scenario("lorenz96")
    fast, ref = _pair(scen)
    y = np.full((2, 1, scen.dy), 1e200)  # overflows within a few steps
    for est in (fast, ref):
        est.reset(1)
        for k in range(5):
            est.step(y[0])
    assert fast.diverged[0] == ref.diverged[0]
