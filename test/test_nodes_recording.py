"""The evaluator and the player live, in an isolated ROS domain per test: recording ends cleanly on signals,
a killed recorder's file is recovered, a full disk is one line; a bag (ours, or a foreign rosbag2
directory in a namespace) played into a live estimator scores like replay.
"""

from __future__ import annotations

import signal
import time
import warnings

import numpy as np
import pytest

from neural_estimator.bags import BagReader, BagWarning, arrays_to_bag, bag_to_arrays
from neural_estimator.stream import messages as MSG
from neural_estimator.data import simulate
from neural_estimator.nodes.launch import (
    ESTIMATOR,
    EVALUATOR,
    SIMULATOR,
)
from neural_estimator.evaluation.replay import replay

pytestmark = pytest.mark.ros  # every test here runs ROS 2 nodes

pytest.importorskip("rclpy")


# ---- recording ends cleanly on signals; a killed recorder's file is recovered --------------------------------
def test_evaluator_signals_and_crash_recovery(plugin, nodes, tmp_path):
    term_bag, kill_bag = tmp_path / "term.mcap", tmp_path / "kill.mcap"
    for name, bag in (("rec_term", term_bag), ("rec_kill", kill_bag)):
        nodes.start(EVALUATOR, name, output=str(bag), chunk_size=2048, compute_metrics=False)
    nodes.start(
        SIMULATOR,
        "sim",
        scenario="nodecart",
        plugins=[plugin],
        trajectories=1,
        horizon=100000,
        rate_hz=200.0,
        wait_for_subscribers=2,
        start_delay=0.5,
    )
    t0 = time.monotonic()
    while "run started" not in nodes.log("rec_kill") or "run started" not in nodes.log("rec_term"):
        assert time.monotonic() - t0 < 30, nodes.log("sim") + nodes.log("rec_kill")
        time.sleep(0.1)
    time.sleep(1.5)
    nodes.procs["rec_term"].send_signal(signal.SIGTERM)
    nodes.procs["rec_kill"].send_signal(signal.SIGKILL)
    code = nodes.wait("rec_term", 20)
    assert code == 0, nodes.log("rec_term")
    nodes.wait("rec_kill", 20)

    with BagReader(term_bag, strict=True) as reader:  # SIGTERM: a complete, closed file
        n_obs = reader.topics["/observation"].msgcount
        assert n_obs > 50 and reader.topics["/scenario"].msgcount == 1
    assert "closing the bag" in nodes.log("rec_term")

    with warnings.catch_warnings(record=True) as caught:  # SIGKILL: no summary; complete chunks recovered
        warnings.simplefilter("always")
        run = bag_to_arrays(kill_bag)
    damage = [str(w.message) for w in caught if issubclass(w.category, BagWarning)]
    assert damage and ("without its summary" in damage[0] or "inside a" in damage[0])
    got = run.present["observation"]
    assert got.sum() > 20
    assert np.array_equal(got[0, : got.sum()], np.ones(got.sum(), dtype=bool))  # a prefix, no holes


def test_evaluator_on_a_full_disk_exits_with_one_line(plugin, nodes, tmp_path):
    """It printed two OSError tracebacks; now: one error line, the bag closed as far as possible, exit 1."""
    full = tmp_path / "full.mcap"
    full.symlink_to("/dev/full")  # every write: ENOSPC
    nodes.start(EVALUATOR, "rec", output=str(full), overwrite=True, chunk_size=2048)
    nodes.start(SIMULATOR, "sim", scenario="nodecart", plugins=[plugin], trajectories=2, horizon=200, rate_hz=400.0)
    assert nodes.wait("rec", 60) == 1
    log = nodes.log("rec")
    assert "recording stopped" in log and "No space left on device" in log and "Traceback" not in log


# ---- playing a bag into a live estimator ----------------------------------------------------------------------
def test_player_feeds_live_estimator_like_replay(plugin, cart, nodes, tmp_path):
    data = simulate(cart, 2, 30, seed=7)
    sample = arrays_to_bag(
        tmp_path / "sample.mcap",
        cart,
        data.x,
        data.y,
        data.u,
        start_ns=10**18,
        estimates={"ukf": np.zeros_like(data.x)},
    )  # played estimates are left out
    rec = tmp_path / "played.mcap"
    nodes.start(EVALUATOR, "rec", output=str(rec), methods=["ukf"], compute_metrics=True)
    nodes.start(ESTIMATOR, "est", method="ukf", plugins=[plugin])  # scenario from the bag's scenario topic
    nodes.start(
        "neural_estimator.nodes.player_node",
        "player",
        bag=str(sample),
        rate=10.0,
        wait_for_subscribers=2,
        start_delay=0.5,
    )
    assert nodes.wait("rec", 90) == 0, nodes.log("rec") + nodes.log("est") + nodes.log("player")
    assert nodes.wait("player", 30) == 0
    live = bag_to_arrays(rec)
    np.testing.assert_array_equal(live.x, data.x)
    assert live.received["estimates/ukf"] == 60 and np.isfinite(live.x_hat["ukf"]).all()
    offline = bag_to_arrays(replay(sample, ["ukf"], tmp_path / "offline.mcap").path)
    np.testing.assert_allclose(live.x_hat["ukf"], offline.x_hat["ukf"], rtol=0, atol=1e-12)
    assert "ukf" in rec.with_name("played.metrics.md").read_text()


# ---- a foreign rosbag2 directory without /scenario, played in a namespace --------------------------------------
def test_player_plays_a_foreign_directory_in_its_namespace(plugin, cart, nodes, tmp_path):
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    data = simulate(cart, 2, 20, seed=5)
    src = arrays_to_bag(tmp_path / "src.mcap", cart, data.x, data.y, data.u, start_ns=10**18)
    store = get_typestore(Stores.ROS2_JAZZY)
    foreign = tmp_path / "foreign"
    with BagReader(src) as reader, Writer(foreign, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conns = {}
        for c, t, raw in reader.messages(["/observation", "/ground_truth"]):  # no /scenario, no /run_status
            if c.topic not in conns:
                conns[c.topic] = w.add_connection(c.topic, MSG.JOINT_STATE, typestore=store)
            w.write(conns[c.topic], t, raw)
    rec = tmp_path / "ns.mcap"
    ns = ("-r", "__ns:=/robot1")
    nodes.start(
        EVALUATOR,
        "rec",
        output=str(rec),
        methods=["ukf"],
        scenario="nodecart",
        plugins=[plugin],
        idle_timeout=3.0,
        topics=["/clock"],
        use_sim_time=True,
        extra_args=ns,
    )
    nodes.start(ESTIMATOR, "est", method="ukf", scenario="nodecart", plugins=[plugin], extra_args=ns)
    nodes.start(
        "neural_estimator.nodes.player_node",
        "player",
        bag=str(foreign),
        rate=10.0,
        wait_for_subscribers=2,
        start_delay=0.5,
        publish_clock=True,
        extra_args=ns,
    )
    assert nodes.wait("rec", 90) == 0, nodes.log("rec") + nodes.log("est") + nodes.log("player")
    with BagReader(rec) as reader:
        assert {"/robot1/observation", "/robot1/estimates/ukf"} <= set(reader.topics)
        assert reader.topics["/robot1/estimates/ukf"].msgcount == 40
        clock = [
            MSG.TYPESTORE.deserialize_cdr(raw, "rosgraph_msgs/msg/Clock").clock
            for _, _, raw in reader.messages(["/clock"])
        ]
    assert len(clock) > 0 and clock[0].sec >= 10**9  # the bag's time (start 10**18 ns), not the wall clock
    assert "idle" in nodes.log("rec") or "no run_status" in nodes.log("rec")
    assert "ukf" in rec.with_name("ns.metrics.md").read_text()
