"""A recorded run is read into arrays through compact per-stream buffers (bags/cells.py): the
arrays are what the cells' messages say (the last of a repeated cell kept, cells outside the
announced run dropped and counted, missing cells NaN), and reading holds a small multiple of the
arrays, not a Python object per message."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from neural_estimator.stream import messages as MSG
from neural_estimator.bags.dataset import arrays_to_bag, bag_to_arrays
from neural_estimator.bags.errors import BagError
from neural_estimator.bags.writer import BagWriter
from neural_estimator.data import simulate
from neural_estimator.scenarios import make_scenario


def _write(path, scen, items, announce=True, scenario_last=False):
    with BagWriter(path) as bag:
        for topic in ("/scenario", "/observation", "/ground_truth", "/estimates/ekf"):
            bag.add_topic(topic, MSG.STRING if topic == "/scenario" else MSG.JOINT_STATE)
        desc = MSG.encode_scenario(scen.describe(), **({"trajectories": 2, "horizon": 6} if announce else {}))
        t = 1
        if not scenario_last:
            bag.write("/scenario", 0, desc)
        for topic, raw in items:
            bag.write(topic, t, raw)
            t += 1
        if scenario_last:  # a late announcement still defines the run of every message before it
            bag.write("/scenario", t, desc)


def test_repeats_outside_cells_missing_cells_and_a_late_announcement(tmp_path):
    scen = make_scenario("bearings")
    data = simulate(scen, 2, 6, seed=3)
    obs, truth = MSG.observation_labels(scen), MSG.state_labels(scen)
    items = []
    for n in range(2):
        for k in range(6):
            if (n, k) == (1, 4):
                continue  # lost: NaN and counted missing
            items.append(("/observation", MSG.encode_vector(10 * k + n, "b", n, k, obs, data.y[n, k])))
            items.append(("/ground_truth", MSG.encode_vector(0, "b", n, k, truth, data.x[n, k])))
            items.append(("/estimates/ekf", MSG.encode_vector(0, "ekf", n, k, truth, data.x[n, k] + 1)))
    items.append(("/estimates/ekf", MSG.encode_vector(0, "ekf", 0, 2, truth, data.x[0, 2] + 7)))  # a repeat: kept
    items.append(("/observation", MSG.encode_vector(999, "b", 0, 3, obs, data.y[0, 3] * 2)))  # a repeat
    items.append(("/observation", MSG.encode_vector(0, "b", 0, 6, obs, data.y[0, 0])))  # step 6: outside
    items.append(("/observation", MSG.encode_vector(0, "b", 5, 0, obs, data.y[0, 0])))  # trajectory 5: outside
    items.append(("/ground_truth", MSG.encode_vector(0, "b", 0, 1, ["x"], [1.0])))  # wrong names: rejected
    for late in (False, True):
        path = tmp_path / f"run-{late}.mcap"
        _write(path, scen, items, scenario_last=late)
        run = bag_to_arrays(path)
        x_want, y_want = data.x.copy(), data.y.copy()
        x_want[1, 4] = y_want[1, 4] = np.nan
        y_want[0, 3] = data.y[0, 3] * 2
        ekf_want = x_want + 1
        ekf_want[0, 2] = data.x[0, 2] + 7
        np.testing.assert_array_equal(run.x, x_want)
        np.testing.assert_array_equal(run.y, y_want)
        np.testing.assert_array_equal(run.x_hat["ekf"], ekf_want)
        assert run.stamps[0, 3] == 999 and run.stamps[1, 4] == -1 and run.stamps[1, 5] == 51
        assert run.duplicates == {"estimates/ekf": 1, "observation": 1}
        assert run.outside == {"observation": 2}
        assert run.rejected == {"ground_truth": 1}
        assert run.received == {"observation": 12, "ground_truth": 11, "estimates/ekf": 12}
        assert run.missing == {"observation": 1, "ground_truth": 1, "estimates/ekf": 1}
        assert not run.present["observation"][1, 4] and run.present["observation"].sum() == 11


def test_without_an_announcement_the_span_error_names_the_first_cell_at_the_largest_step(tmp_path, monkeypatch):
    scen = make_scenario("bearings")
    obs = MSG.observation_labels(scen)
    items = [
        ("/observation", MSG.encode_vector(0, "b", n, k, obs, np.zeros(len(obs)))) for n, k in ((0, 0), (3, 10**8))
    ]
    items.append(("/observation", MSG.encode_vector(0, "b", 1, 10**8, obs, np.zeros(len(obs)))))
    path = tmp_path / "span.mcap"
    _write(path, scen, items, announce=False)
    with pytest.raises(BagError, match=r"largest step index 100000000, in trajectory 3\)"):
        bag_to_arrays(path)


def test_reading_holds_a_small_multiple_of_the_arrays(tmp_path):
    scen = make_scenario("bearings")
    rng = np.random.default_rng(0)
    n, t = 20, 500
    x, y = rng.normal(size=(n, t, scen.dx)), rng.normal(size=(n, t, scen.dy))
    cov = np.broadcast_to(np.eye(scen.dx), (n, t, scen.dx, scen.dx))
    path = tmp_path / "run.mcap"
    arrays_to_bag(path, scen, x, y, estimates={"ekf": x, "ukf": x}, covariances={"ekf": cov, "ukf": cov})
    tracemalloc.start()
    try:
        run = bag_to_arrays(path)
        held, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    arrays = sum(a.nbytes for a in (run.x, run.y, run.u_prev, *run.x_hat.values(), *run.P_hat.values()))
    # measured (tracemalloc): 2.93x the arrays with the compact buffers, 13.31x with the dict of
    # (stamp, array) per cell they replaced
    assert peak < 5 * arrays, (peak / arrays, peak, arrays)
