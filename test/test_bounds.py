"""Every allocation sized by input is bounded before it happens, and the bound is named in a
one-line error (bags, recorded runs, cards, robot specs); disk full and read-only outputs."""

from __future__ import annotations

import pytest

from neural_estimator.bags import BagError, BagWriter
from neural_estimator.bags import messages as M
from neural_estimator.bags.dataset import arrays_to_bag, bag_to_arrays
from neural_estimator.data import simulate
from neural_estimator.scenarios import make_scenario


@pytest.fixture(scope="module")
def scen():
    return make_scenario("bearings")


def _bag_with(path, scen, extra, *, announce=True, N=2, T=6):
    """A small run bag plus the (trajectory, step) observation messages ``extra`` (one each)."""
    data = simulate(scen, N, T, seed=3)
    arrays_to_bag(path, scen, data.x, data.y, data.u, estimates={"ekf": data.x})
    if not extra and announce:
        return path
    from neural_estimator.bags.reader import open_bag

    with open_bag(path) as bag:
        msgs = [(c.topic, t, bytes(raw)) for c, t, raw in bag.messages()]
    out = path.with_name("x" + path.name)
    with BagWriter(out) as w:
        for topic, t, raw in msgs:
            if topic == "/scenario" and not announce:
                continue
            if not w.has_topic(topic):
                w.add_topic(topic, M.STRING if topic in ("/scenario", "/run_status") else M.JOINT_STATE)
            w.write(topic, t, raw)
        for n, k in extra:
            w.write("/observation", msgs[-1][1], M.encode_observation(scen, msgs[-1][1] + 1, n, k, data.y[0, 0], []))
    return out


def test_a_step_index_of_a_billion_is_rejected_not_allocated(scen, tmp_path):
    """It made the evaluator, ``metrics`` and ``replay`` allocate (N, 10**9, width): 224 GiB."""
    run = bag_to_arrays(_bag_with(tmp_path / "a.mcap", scen, [(0, 10**9), (3 * 10**7, 0)]))
    assert run.x.shape[:2] == (2, 6) and run.outside == {"observation": 2}
    assert run.received["observation"] == 12


def test_without_an_announcement_the_array_bound_is_named(scen, tmp_path, monkeypatch):
    bag = _bag_with(tmp_path / "b.mcap", scen, [(0, 10**9)], announce=False)
    with pytest.raises(BagError) as e:
        bag_to_arrays(bag, description=scen.describe())
    msg = str(e.value)
    assert "\n" not in msg and "largest step index 1000000000" in msg and "NEURAL_ESTIMATOR_MAX_ARRAY_GB" in msg
    monkeypatch.setenv("NEURAL_ESTIMATOR_MAX_ARRAY_GB", "0.0000001")  # the bound is the setting's
    with pytest.raises(BagError, match="over the bound of 0.0 GiB"):
        bag_to_arrays(_bag_with(tmp_path / "c.mcap", scen, []))


@pytest.mark.parametrize("run", [{"trajectories": 3 * 10**7, "horizon": 10}, {"trajectories": 2, "horizon": 10**9}])
def test_an_announced_run_too_large_is_refused_before_allocation(scen, tmp_path, run):
    desc = scen.describe()
    desc["run"] = run
    bag = _bag_with(tmp_path / "d.mcap", scen, [], announce=False)
    with pytest.raises(
        BagError, match=r"the run announces .* over the bound of 4.0 GiB \(NEURAL_ESTIMATOR_MAX_ARRAY_GB\)"
    ):
        bag_to_arrays(bag, description=desc)
