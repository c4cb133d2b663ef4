"""One estimator node live, in an isolated ROS domain per test: bad messages survived, bad parameters
refused at start-up, the ROS conventions and stream identity under hostile messages, diagnostics from a
busy node, the heap settled once built.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from ros_tester import Tester

from neural_estimator.stream import messages as MSG
from neural_estimator.data import simulate
from neural_estimator.nodes.launch import (
    ESTIMATOR,
)

pytestmark = pytest.mark.ros  # every test here runs ROS 2 nodes

pytest.importorskip("rclpy")


# ---- one estimator node and bad input ----------------------------------------------------------------------
def test_estimator_survives_bad_messages(plugin, cart, nodes, domain, monkeypatch):
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import JointState
    from std_msgs.msg import String
    from std_srvs.srv import Trigger

    from neural_estimator.nodes.common import stream_qos

    nodes.start(
        ESTIMATOR, "est", method="ekf", scenario="nodecart", plugins=[plugin], diagnostics_period=0.3, log_throttle=0.0
    )
    ctx2 = rclpy.Context()
    tester = Tester(monkeypatch, domain, lambda: f"estimator log:\n{nodes.log('est')}", timeout=20.0)
    try:
        node, spin_until = tester.node, tester.spin_until

        estimates, diags = [], []
        node.create_subscription(
            JointState, "estimates/ekf", lambda raw: estimates.append(MSG.decode_vector(raw)), stream_qos(100), raw=True
        )
        node.create_subscription(DiagnosticArray, "/diagnostics", diags.append, 10)
        pub = node.create_publisher(JointState, "observation", stream_qos(100, transient_local=False))
        # another type on the same topic needs another DDS participant: a second context
        rclpy.init(context=ctx2, domain_id=domain)
        foreign = rclpy.create_node("foreign", context=ctx2).create_publisher(String, "observation", 10)

        spin_until(lambda: pub.get_subscription_count() >= 1 and node.count_publishers("estimates/ekf") >= 1)
        labels = MSG.observation_labels(cart)

        def obs(step, values, names=labels, trajectory=0):
            return MSG.encode_vector(step, cart.name, trajectory, step, names, values)

        J = MSG.TYPESTORE.types[MSG.JOINT_STATE]
        empty_joint_state = bytes(
            MSG.TYPESTORE.serialize_cdr(
                J(
                    header=MSG.TYPESTORE.types["std_msgs/msg/Header"](
                        stamp=MSG.TYPESTORE.types["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id=""
                    ),
                    name=[],
                    position=np.zeros(0),
                    velocity=np.zeros(0),
                    effort=np.zeros(0),
                ),
                MSG.JOINT_STATE,
            )
        )
        sequence = [
            obs(0, [0.1, 0.0]),
            obs(1, [0.2, 0.5]),
            obs(2, [0.3], names=("position",)),  # bad: wrong width
            obs(2, [np.nan, 0.5]),  # NaN observation: predict only
            obs(3, [0.4, np.inf]),  # bad: non-finite control
            empty_joint_state,  # bad: empty JointState
            b"\x00\x01\x00\x00\x07garbage",  # bad: unparsable
            obs(3, [0.4, 0.1], names=("velocity", "u_prev/force")),  # bad: wrong names
            obs(3, [0.4, 0.1]),
            obs(1, [0.2, 0.5]),  # out of order: skipped
            obs(3, [0.4, 0.1]),  # duplicate: skipped
            obs(6, [0.7, 0.1]),  # gap: steps 4, 5 bridged
        ]
        for raw in sequence:
            pub.publish(raw)
        foreign.publish(String(data="wrong type on the observation topic"))
        spin_until(lambda: len(estimates) >= 5)

        def diag_values():
            for arr in reversed(diags):
                for st in arr.status:
                    if "ekf estimator" in st.name:
                        return {kv.key: kv.value for kv in st.values}, st
            return None, None

        spin_until(lambda: diag_values()[0] is not None and "foreign" in diag_values()[1].message)
        spin_until(lambda: diag_values()[0]["estimates published"] == "5")
        values, status = diag_values()
        assert [(e.trajectory, e.step) for e in estimates] == [(0, 0), (0, 1), (0, 2), (0, 3), (0, 6)]
        assert all(np.isfinite(e.values).all() for e in estimates)
        assert values["bad messages"] == "5"
        assert values["non-finite observations"] == "1"
        assert values["out-of-order steps"] == "1" and values["duplicate steps"] == "1"
        assert values["missing steps bridged"] == "2"
        assert values["diverged"] == "false" and float(values["latency p99 since start (ms)"]) > 0
        assert "std_msgs/msg/String" in status.message

        client = node.create_client(Trigger, "est/reset")
        spin_until(lambda: client.service_is_ready())
        fut = client.call_async(Trigger.Request())
        spin_until(fut.done)
        assert fut.result().success
        pub.publish(obs(0, [0.0, 0.0], trajectory=1))
        spin_until(lambda: len(estimates) >= 6)
        assert (estimates[-1].trajectory, estimates[-1].step) == (1, 0)
        assert nodes.procs["est"].poll() is None  # still up after all of it
    finally:
        tester.shutdown()
        rclpy.try_shutdown(context=ctx2)
    log = nodes.log("est")
    for text in (
        "bad observation dropped",
        "empty JointState",
        "cannot parse",
        "has 1 values",
        "unexpected names",
        "control u_prev contains NaN",
        "stale observation",
        "duplicate observation",
        "bridged by predict-only steps",
        "NaN/inf: predict only",
        "wrong type",
    ):
        assert text in log, text


@pytest.mark.parametrize(
    "params, text",
    [
        ({"method": "kalman"}, "unknown method 'kalman'"),
        ({"method": "gru", "checkpoint": "/nonexistent/ckpt"}, "does not exist"),
        ({"method": "ukf", "scenario": "no_such_scenario"}, "unknown scenario 'no_such_scenario'"),
        ({"method": "ukf", "queue_depth": "many"}, "parameter queue_depth must be an integer, got 'many'"),
        ({"method": "ukf", "options": ["bogus=1"]}, "ukf: unknown option(s) bogus"),
        ({"method": "mamba", "options": ["bogus=1"]}, "mamba: unknown option(s) bogus"),
        ({"method": "mamba", "options": ["threads=1"]}, "mamba: unknown option(s) threads"),
        ({"method": "ukf", "options": ["noequals"]}, "options must be name=value"),
        ({"method": "ukf", "observation_qos": "fast"}, "observation_qos must be one of reliable, sensor_data"),
        ({"method": "ukf", "init": "sideways"}, "ukf: init must be one of prior, observation"),
        ({"method": "pf", "scenario": "bearings", "init": "observation"}, "pf: init=observation needs an observation"),
        ({"method": "ukf", "preset": "v9"}, "scenario 'lorenz96' has no preset 'v9'; valid: v4, v3"),
    ],
)
def test_estimator_refuses_to_start(params, text, nodes):
    nodes.start(ESTIMATOR, "bad", **{"scenario": "lorenz96", **params})
    assert nodes.wait("bad", 60) == 1
    log = nodes.log("bad")
    assert text in log and "Traceback" not in log


def test_nodes_build_their_scenario_from_a_preset_and_set():
    from neural_estimator.nodes.common import StartupError, build_scenario

    s = build_scenario("ballistic", ("obs_noise_std=0.05",), 2.0, preset="v3")
    assert s.config.dt == 0.1 and s.config.obs_noise_std == 0.05 and s.config.noise_scale == 2.0
    assert build_scenario("ballistic", ()).describe()["preset"] == "v4"
    with pytest.raises(StartupError, match="no preset 'v9'"):
        build_scenario("ballistic", (), preset="v9")


# ---- conventions and hostile messages on one estimator ---------------------------------------------------------
def test_estimator_conventions_and_stream_identity(nodes, domain, monkeypatch):
    """bearings (a declared pose): best-effort publisher with observation_qos:=sensor_data, frame_id,
    Odometry with covariance, use_sim_time without /clock (diagnostics go on), a stray message of an
    earlier trajectory (skipped, no reset), a huge step jump (bounded time, /diagnostics go on)."""
    from diagnostic_msgs.msg import DiagnosticArray
    from nav_msgs.msg import Odometry
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import JointState

    from neural_estimator.methods.registry import make_estimator
    from neural_estimator.nodes.common import stream_qos
    from neural_estimator.stream.online import OnlineEstimator
    from neural_estimator.scenarios import make_scenario

    scen = make_scenario("bearings")
    data = simulate(scen, 2, 10, seed=1)
    nodes.start(
        ESTIMATOR,
        "est",
        method="ukf",
        scenario="bearings",
        observation_qos="sensor_data",
        frame_id="odom_test",
        use_sim_time=True,
        diagnostics_period=0.2,
        max_gap=10**9,
        max_gap_seconds=0.2,
        log_throttle=0.0,
    )
    tester = Tester(monkeypatch, domain, lambda: f"estimator log:\n{nodes.log('est')}", timeout=30.0)
    try:
        node, spin_until = tester.node, tester.spin_until

        estimates, odoms, diags = [], [], []
        node.create_subscription(
            JointState, "estimates/ukf", lambda raw: estimates.append(MSG.decode_vector(raw)), stream_qos(100), raw=True
        )
        node.create_subscription(Odometry, "estimates/ukf/odometry", odoms.append, stream_qos(100))
        node.create_subscription(DiagnosticArray, "/diagnostics", diags.append, 10)
        pub = node.create_publisher(JointState, "observation", qos_profile_sensor_data)  # a driver's QoS

        spin_until(lambda: pub.get_subscription_count() >= 1 and node.count_publishers("estimates/ukf/odometry") >= 1)

        def diag_values():
            for arr in reversed(diags):
                for st in arr.status:
                    if "ukf estimator" in st.name:
                        return {kv.key: kv.value for kv in st.values}
            return {}

        # best effort drops what is sent before the node's reader has matched this writer (our side
        # matching first says nothing of its side): an empty message, counted bad and otherwise
        # ignored, is sent until the node's diagnostics count one, so the stream below is not lost
        def probed() -> bool:
            pub.publish(JointState())
            time.sleep(0.05)
            return diag_values().get("bad messages", "0") != "0"

        spin_until(probed)

        def obs(n, k, start=10**18):
            t = MSG.step_stamp_ns(start, n * 10 + k, MSG.dt_ns(scen.dt))
            return MSG.encode_observation(scen, t, n, k, data.y[n, k], np.zeros(0))

        sent = (
            [obs(0, k) for k in range(10)]
            + [obs(1, k) for k in range(4)]
            + [obs(0, 7)]
            + [obs(1, k) for k in range(4, 10)]
        )
        ref = OnlineEstimator(make_estimator("ukf", scen), "ukf")
        expected = []
        for raw in sent:  # best effort: paced, and each waited for, so nothing is dropped
            expected += ref.feed(raw, 0.0)
            pub.publish(raw)
            want = sum(r.status == "estimated" for r in expected)
            spin_until(lambda: len(estimates) >= want)
        assert not ref.flush()  # nothing is held at the end
        assert [r.status for r in expected].count("stale") == 1
        assert [(e.trajectory, e.step) for e in estimates] == [
            (r.trajectory, r.step) for r in expected if r.x_hat is not None
        ]
        np.testing.assert_allclose(
            np.array([e.values for e in estimates]),
            np.array([r.x_hat for r in expected if r.x_hat is not None]),
            rtol=0,
            atol=1e-9,
        )
        assert {e.frame_id for e in estimates} == {"odom_test"}
        spin_until(lambda: len(odoms) >= 20)
        o = odoms[-1]
        assert o.header.frame_id == "odom_test" and o.child_frame_id == "base_link"
        assert o.pose.pose.position.x == pytest.approx(estimates[-1].values[0])
        assert o.pose.pose.position.y == pytest.approx(estimates[-1].values[1])
        assert o.twist.twist.linear.x == pytest.approx(estimates[-1].values[2])
        assert o.pose.covariance[0] > 0 and o.pose.covariance[2 * 6 + 2] == 1e6  # z: not estimated

        # a step jump of ten million: held (nothing confirms or refutes it) and accepted after
        # quarantine_seconds, then bounded time; diagnostics keep coming during and after it
        n_diag = len(diags)
        t0 = time.monotonic()
        pub.publish(MSG.encode_observation(scen, 2 * 10**18, 1, 10_000_000, data.y[1, 9], np.zeros(0)))
        spin_until(lambda: len(estimates) >= 21, timeout=20)
        assert time.monotonic() - t0 < 15
        spin_until(lambda: len(diags) >= n_diag + 3)

        spin_until(lambda: diag_values().get("estimates published") == "21")
        values = diag_values()
        assert values["out-of-order steps"] == "1" and values["stream restarts"] == "1"
        assert values["trajectory resets"] == "2"  # trajectory 0, trajectory 1: the stray one reset nothing
        assert values["quarantined messages"] == "3"  # (1, 0) until (1, 1); the stray (0, 7); the jump
    finally:
        tester.shutdown()
    log = nodes.log("est")
    assert "nothing publishes /clock" in log and "restarted from the prior" in log


def test_settle_heap_freezes_what_is_alive_out_of_the_collectors_walk():
    # a full collection walks every tracked object; the nodes freeze theirs once built, so the
    # collections Python starts on its own mid-run walk only what was allocated since
    import gc

    from neural_estimator.nodes.common import settle_heap

    gc.unfreeze()
    alive = [[i] for i in range(10_000)]  # tracked objects
    try:
        settle_heap()
        assert gc.get_freeze_count() >= len(alive)
        assert all(gc.is_tracked(x) for x in alive[:3])
        assert sum(gc.get_count()) < 100  # the young generations start empty after it
        # a rebuild settles again: what was frozen and has become cyclic garbage is freed, not kept
        import weakref

        class Node:
            pass

        a, b = Node(), Node()
        a.other, b.other = b, a  # a cycle: only the collector frees it
        gone = weakref.ref(a)
        settle_heap()  # a and b frozen while alive
        del a, b
        settle_heap()
        assert gone() is None
    finally:
        gc.unfreeze()


def _message_path_node(**extra):
    """A stand-in for an estimator node with what ``EstimatorNode._on_observations`` reads."""
    import types

    from neural_estimator.nodes.estimator_stats import EstimatorStats

    return types.SimpleNamespace(
        p=types.SimpleNamespace(drain=False, max_delay=0.0, diagnostics_period=1.0, queue_depth=10),
        sub_obs=None,
        stats=EstimatorStats(),
        _on_observation=lambda raw, info: None,
        _last_diagnostics=time.monotonic(),
        **extra,
    )


def test_a_busy_estimator_publishes_its_diagnostics_from_the_message_path():
    # the events executor serves queued messages before a due timer: a node that never idles
    # must still report, so the observation callback publishes when the timer is overdue
    from neural_estimator.nodes.estimator_node import EstimatorNode

    published = []
    node = _message_path_node()

    def on_diagnostics():
        published.append(time.monotonic())
        node._last_diagnostics = time.monotonic()

    node._on_diagnostics = on_diagnostics
    EstimatorNode._on_observations(node, b"obs", 1)
    assert published == []  # the timer is not overdue: nothing from the message path
    node._last_diagnostics -= 1.6  # 1.6 periods without a diagnostics message
    EstimatorNode._on_observations(node, b"obs", 1)
    assert len(published) == 1
    EstimatorNode._on_diagnostics_timer(node)  # the late timer right after: not a second message
    assert len(published) == 1
    node._last_diagnostics -= 0.6
    EstimatorNode._on_diagnostics_timer(node)  # an on-time timer publishes as before
    assert len(published) == 2


def test_a_busy_estimator_trims_its_heap_from_the_message_path():
    # the heap trim's timer starves like the diagnostics timer: a GRU node behind the stream for
    # 30 minutes never ran it. Overdue by half a period, the observation callback trims.
    from neural_estimator.nodes.estimator_node import EstimatorNode
    from neural_estimator.nodes.heap_trace import HeapTrim

    trim = HeapTrim(10.0)
    node = _message_path_node(_on_diagnostics=lambda: None, heap_trim=trim)
    EstimatorNode._on_observations(node, b"obs", 1)
    assert trim.calls == 0  # trimmed less than 1.5 periods ago: the timer's turn
    trim.last -= 16.0  # 1.6 periods without a trim
    EstimatorNode._on_observations(node, b"obs", 1)
    assert trim.calls == (1 if trim.available else 0)
    EstimatorNode._on_observations(node, b"obs", 1)
    assert trim.calls == (1 if trim.available else 0)  # just trimmed: not again
    del node.heap_trim  # started with NEURAL_ESTIMATOR_HEAP_TRIM=0: no trim, no error
    EstimatorNode._on_observations(node, b"obs", 1)
