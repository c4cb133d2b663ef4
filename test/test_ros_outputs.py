"""Standard outputs (pose, state vector, TF, set_pose) and input diagnostics, as plain code; and a live
run that records them."""

from __future__ import annotations

import types

import numpy as np
import pytest
from ros_tester import Tester, fresh_domain

from neural_estimator.nodes import diagnostics as D
from neural_estimator.nodes import outputs as O
from neural_estimator.nodes.odometry import UNKNOWN_VARIANCE, quaternion

pytestmark = pytest.mark.ros  # every test here runs ROS 2 nodes


def _msg(**fields):
    return types.SimpleNamespace(**fields)


def _stamped():
    return _msg(header=_msg(stamp=_msg(sec=0, nanosec=0), frame_id=""))


class Pose:  # geometry_msgs/PoseWithCovarianceStamped's shape
    def __init__(self):
        self.header = _stamped().header
        self.pose = _msg(
            pose=_msg(position=_msg(x=0.0, y=0.0, z=0.0), orientation=_msg(x=0.0, y=0.0, z=0.0, w=1.0)),
            covariance=[0.0] * 36,
        )


class Dim:
    def __init__(self, label="", size=0, stride=0):
        self.label, self.size, self.stride = label, size, stride


class MultiArray:
    def __init__(self):
        self.layout = _msg(dim=[], data_offset=0)
        self.data = []


BEARINGS_POSE = {"x": 0, "y": 1, "vx": 2, "vy": 3}


def test_pose_message_carries_the_methods_covariance_or_unknown_never_zeros():
    x = np.array([1.0, 2.0, 0.5, -0.5])
    P = np.diag([0.1, 0.2, 0.3, 0.4])
    P[0, 1] = P[1, 0] = 0.05
    msg = O.make_pose(Pose, 1_500_000_000, "odom", x, P, BEARINGS_POSE)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id) == (1, 500_000_000, "odom")
    assert (msg.pose.pose.position.x, msg.pose.pose.position.y) == (1.0, 2.0)
    cov = np.array(msg.pose.covariance).reshape(6, 6)
    assert cov[0, 0] == 0.1 and cov[1, 1] == 0.2 and cov[0, 1] == 0.05
    assert cov[2, 2] == UNKNOWN_VARIANCE and cov[5, 5] == UNKNOWN_VARIANCE  # z, yaw: not in this state
    none = np.array(O.make_pose(Pose, 0, "odom", x, None, BEARINGS_POSE).pose.covariance).reshape(6, 6)
    assert np.all(np.diag(none) == UNKNOWN_VARIANCE) and np.count_nonzero(none - np.diag(np.diag(none))) == 0


def test_state_vector_message_round_trips_with_and_without_covariance():
    x = np.array([1.0, -2.0, 3.0])
    P = np.arange(9.0).reshape(3, 3)
    msg = O.make_state(MultiArray, Dim, x, P, ["a", "b", "c"])
    assert [(d.label, d.size, d.stride) for d in msg.layout.dim] == [("state:a,b,c", 3, 12), ("mean|covariance", 4, 4)]
    names, x2, P2 = O.read_state(msg.data, [(d.label, d.size) for d in msg.layout.dim])
    assert names == ["a", "b", "c"] and np.array_equal(x2, x) and np.array_equal(P2, P)
    bare = O.make_state(MultiArray, Dim, x, None, ["a", "b", "c"])
    assert len(bare.data) == 3 and bare.layout.dim[1].label == "mean"
    assert O.read_state(bare.data, [(d.label, d.size) for d in bare.layout.dim])[2] is None


def test_state_encoder_writes_the_message_rclpy_reads():
    from rclpy.serialization import deserialize_message, serialize_message
    from std_msgs.msg import Float64MultiArray, MultiArrayDimension

    rng = np.random.default_rng(0)
    for n, cov, names in [
        (3, True, "abc"),
        (3, False, "abc"),
        (5, True, "abcde"),
        (1, False, ["x1"]),
        (2, True, ["longer", "q"]),
    ]:
        enc = O.StateEncoder(list(names))
        for _ in range(2):  # the cached layout serves the next estimate
            x = rng.standard_normal(n)
            P = rng.standard_normal((n, n)) if cov else None
            want = O.make_state(Float64MultiArray, MultiArrayDimension, x, P, list(names))
            got = deserialize_message(enc.encode(x, P), Float64MultiArray)
            assert got == want, (n, cov)
            # and what rclpy serialises reads back the same (its padding bytes may differ)
            assert deserialize_message(serialize_message(want), Float64MultiArray) == got


def test_euler_inverts_quaternion_and_set_pose_values():
    for rpy in [(0.1, -0.2, 0.3), (0.0, 0.0, -3.0), (-0.5, 0.4, 2.5)]:
        assert np.allclose(O.euler(*quaternion(*rpy)), rpy)
    msg = Pose()
    msg.pose.pose.position.x = 4.0
    o = msg.pose.pose.orientation
    o.x, o.y, o.z, o.w = quaternion(0.0, 0.0, 1.0)
    assert O.pose_values(msg)["yaw"] == pytest.approx(1.0) and O.pose_values(msg)["x"] == 4.0
    o.x = o.y = o.z = o.w = 0.0
    with pytest.raises(O.OutputError, match="zero or non-finite norm"):
        O.pose_values(msg)


def test_set_pose_restarts_a_filter_at_the_pose_and_refuses_neural_models():
    from neural_estimator.methods.registry import make_estimator
    from neural_estimator.scenarios import make_scenario

    scen = make_scenario("bearings")
    ekf = make_estimator("ekf", scen)
    ekf.reset(1)
    last = np.array([10.0, 20.0, 1.0, 2.0])
    mean = O.set_pose(ekf, {"x": -3.0, "y": 7.0, "z": 0, "roll": 0, "pitch": 0, "yaw": 0}, scen.pose_states, last)
    assert np.allclose(mean, [-3.0, 7.0, 1.0, 2.0])  # pose replaced, velocities kept
    # the next step is an update of the set state: with a huge R it stays near the set pose
    ref = make_estimator("ekf", scen)
    ref.reset(1, initial_mean=mean[None])
    y = np.zeros((1, scen.dy))
    assert np.allclose(ekf.step(y), ref.step(y))
    gru = make_estimator("gru", scen)
    with pytest.raises(O.OutputError, match="filters only"):
        O.set_pose(gru, {"x": 0.0}, scen.pose_states, None)
    with pytest.raises(O.OutputError, match="no pose components"):
        O.state_at_pose(np.zeros(3), {"x": 0.0}, {})


def test_set_pose_starts_every_filter_at_the_pose_covariance():
    """A pose message's covariance replaces the prior's pose block (its cross terms dropped): the
    EKF/UKF start at it, the EnKF's members and the PF's particles spread by it; all zeros = P0;
    a covariance that is not one is refused in one line and the stream restarts from the prior."""
    from neural_estimator.methods.registry import make_estimator
    from neural_estimator.scenarios import make_scenario

    scen = make_scenario("bearings")
    pose_cov = np.diag([4.0, 9.0, 1.0, 1.0, 1.0, 0.25])
    pose_cov[0, 1] = pose_cov[1, 0] = 1.5
    want = O.state_covariance(make_estimator("ekf", scen).P0, pose_cov, scen.pose_states)
    assert want[0, 0] == 4.0 and want[1, 1] == 9.0 and want[0, 1] == 1.5 and want[0, 2] == 0.0
    pose = {"x": -3.0, "y": 7.0, "z": 0, "roll": 0, "pitch": 0, "yaw": 0}
    for method in ("ekf", "ukf"):
        f = make_estimator(method, scen)
        f.reset(1)
        O.set_pose(f, pose, scen.pose_states, None, pose_cov)
        np.testing.assert_allclose(f._P[0], want)
    for method, options in (("enkf", {"n_members": 4000}), ("pf", {"n_particles": 4000})):
        f = make_estimator(method, scen, **options)
        f.reset(1)
        mean = O.set_pose(f, pose, scen.pose_states, None, pose_cov)
        X = f._X[0]
        np.testing.assert_allclose(X.mean(axis=0)[:2], mean[:2], atol=0.2)
        np.testing.assert_allclose(np.cov(X.T)[:2, :2], want[:2, :2], rtol=0.1, atol=0.1)
    ekf = make_estimator("ekf", scen)
    ekf.reset(1)
    O.set_pose(ekf, pose, scen.pose_states, None, None)
    np.testing.assert_allclose(ekf._P[0], ekf.P0)
    bad = np.diag([-4.0, 9.0, 1.0, 1.0, 1.0, 1.0])
    with pytest.raises(O.OutputError, match="not positive semi-definite"):
        O.set_pose(ekf, pose, scen.pose_states, None, bad)
    np.testing.assert_allclose(ekf._P[0], ekf.P0)


def test_output_topics_the_evaluator_records():
    assert O.is_output_topic("/estimates/ekf/odometry") and O.is_output_topic("/r1/estimates/gru/state", "/r1")
    assert not O.is_output_topic("/estimates/ekf/covariance") and not O.is_output_topic("/estimates/ekf")
    assert not O.is_output_topic("/r1/estimates/ekf/pose") and not O.is_output_topic("/estimates//pose")
    with pytest.raises(O.OutputError, match="pose_output must be one of"):
        O.check_output_params(O.OutputParams(pose_output="Odometry"))


class Transform:  # geometry_msgs/TransformStamped's shape
    def __init__(self):
        self.header = _stamped().header
        self.child_frame_id = ""
        self.transform = _msg(translation=_msg(x=0.0, y=0.0, z=0.0), rotation=_msg(x=0.0, y=0.0, z=0.0, w=1.0))


def test_transform_at_the_estimated_pose():
    quad = {"x": 0, "z": 1, "pitch": 2, "vx": 3, "vz": 4, "wy": 5}  # the quadrotor's pose states
    x = np.array([1.0, 2.0, 0.3, 0.0, 0.0, 0.0])
    t = O.make_transform(Transform, 2_000_000_001, "odom", "base_link", x, quad)
    assert (t.header.frame_id, t.child_frame_id, t.header.stamp.sec, t.header.stamp.nanosec) == (
        "odom",
        "base_link",
        2,
        1,
    )
    tr, r = t.transform.translation, t.transform.rotation
    assert (tr.x, tr.y, tr.z) == (1.0, 0.0, 2.0)
    assert np.allclose(O.euler(r.x, r.y, r.z, r.w), (0.0, 0.3, 0.0))


def test_publish_tf_is_refused_in_one_line_without_tf2_msgs():
    import importlib.util

    pytest.importorskip("geometry_msgs")

    class FakeNode:
        def create_publisher(self, cls, topic, qos):
            return (cls.__name__, topic)

    p = O.OutputParams(pose_output="none", publish_state=False, publish_tf=True)
    args = (FakeNode(), p, "estimates/ekf", 10, "map", "base_link", ["px", "py", "vx", "vy"])
    with pytest.raises(O.OutputError, match="no pose components"):
        O.Outputs(*args, {})
    if importlib.util.find_spec("tf2_msgs") is None:  # pip: no wheel
        with pytest.raises(O.OutputError, match="publish_tf needs the tf2_msgs package") as err:
            O.Outputs(*args, BEARINGS_POSE)
        assert "\n" not in str(err.value)
    else:  # a ROS install
        assert O.Outputs(*args, BEARINGS_POSE).pub_tf == ("TFMessage", "/tf")


# ---- diagnostics ----------------------------------------------------------------------------------------
def test_frequency_band_and_staleness_like_diagnostic_updater():
    m = D.InputMonitor("/observation", expected_rate=10.0, tolerance=0.1, stale_after=1.0, window=2.0, start=0.0)
    st = m.status(0.5)
    assert st.level == D.OK  # not stale yet, and no full window to judge the band
    assert m.status(1.5).level == D.ERROR and m.status(1.5).message == "no message yet"
    for k in range(1, 41):  # 10 Hz for 4 s
        m.tick(1.5 + 0.1 * k)
    assert m.status(5.5).level == D.OK and float(m.status(5.5).values["frequency (Hz)"]) == pytest.approx(10, rel=0.06)
    for k in range(1, 41):  # then 5 Hz
        m.tick(5.5 + 0.2 * k)
    st = m.status(13.5)
    assert st.level == D.WARN and st.message.startswith("frequency too low")
    for k in range(1, 61):  # then 30 Hz
        m.tick(13.5 + k / 30)
    assert m.status(15.5).message.startswith("frequency too high")
    st = m.status(17.0)
    assert st.level == D.ERROR and st.message.startswith("stale: no message for 1.5 s")
    free = D.InputMonitor("/x", expected_rate=0.0, stale_after=1.0, start=0.0)
    free.tick(0.1)
    assert free.status(0.5).level == D.OK and free.status(0.5).values["expected frequency (Hz)"] == "any"


def test_merge_rates_and_hardware_id():
    assert D.merge([(D.OK, "ok"), (D.WARN, "slow"), (D.ERROR, "stale")]) == (D.ERROR, "slow; stale")
    assert D.merge([(D.OK, "ok")]) == (D.OK, "ok")
    assert D.parse_rates(["/imu=100", "/gps/fix=5"]) == {"/imu": 100.0, "/gps/fix": 5.0}
    with pytest.raises(ValueError, match="'/imu' is not topic=Hz"):
        D.parse_rates(["/imu"])
    assert D.hardware_id("/robot1/estimator_ukf", "ukf") == "/robot1/estimator_ukf/ukf"
    with pytest.raises(ValueError, match="stale_after and window > 0"):
        D.InputMonitor("/x", stale_after=0)


# ---- live: what a run records ------------------------------------------------------------------------------
def test_live_run_records_pose_with_covariance_for_a_filter_and_a_state_vector_for_every_method(tmp_path):
    """simulator -> ekf, gru, lstm -> evaluator, started from the graph description (`neural-estimator
    live`): the bag holds Odometry with the EKF's covariance, with the GRU's covariance head's, and with
    "unknown" variances for the LSTM served without a covariance (`lstm.covariance=false`), and a state
    vector for every method, each matching the estimate stream."""
    pytest.importorskip("rclpy")
    from neural_estimator.bags import BagReader
    from neural_estimator.stream import messages as MSG
    from neural_estimator.nodes.launch import PipelineConfig, run_pipeline

    methods = ("ekf", "gru", "lstm")
    cfg = PipelineConfig(
        scenario="bearings",
        methods=methods,
        trajectories=1,
        horizon=30,
        rate_hz=100.0,
        output=str(tmp_path / "b.mcap"),
        options=("lstm.covariance=false",),
    )
    res = run_pipeline(cfg)
    with BagReader(res.bag) as reader:
        topics = set(reader.topics)
        assert {f"/estimates/{m}/{kind}" for m in methods for kind in ("odometry", "state")} <= topics

        def read(topic, msgtype):
            return [MSG.TYPESTORE.deserialize_cdr(raw, msgtype) for _, _, raw in reader.messages([topic])]

        est = {m: read(f"/estimates/{m}", MSG.JOINT_STATE) for m in methods}
        odom = {m: read(f"/estimates/{m}/odometry", "nav_msgs/msg/Odometry") for m in methods}
        state = {m: read(f"/estimates/{m}/state", "std_msgs/msg/Float64MultiArray") for m in methods}
        truth = read("/ground_truth", MSG.JOINT_STATE)
        truth_odom = read("/ground_truth/odometry", "nav_msgs/msg/Odometry")
    # the simulator's truth as Odometry too (pose tools read it): same stamps, the true position, exact
    assert len(truth_odom) == len(truth) == 30
    for t, o in zip(truth, truth_odom):
        assert (o.header.stamp.sec, o.header.stamp.nanosec) == (t.header.stamp.sec, t.header.stamp.nanosec)
        assert (o.pose.pose.position.x, o.pose.pose.position.y) == (t.position[2], t.position[3])
        assert o.pose.covariance[0] == 0.0 and o.twist.twist.linear.x == t.position[4]
    for m in methods:
        assert len(odom[m]) == len(state[m]) == len(est[m]) == 30
    covs = {m: np.array(odom[m][-1].pose.covariance).reshape(6, 6) for m in methods}
    for m in ("ekf", "gru"):  # the filter's P and the covariance head's
        assert 0 < covs[m][0, 0] < UNKNOWN_VARIANCE and 0 < covs[m][1, 1] < UNKNOWN_VARIANCE
    assert odom["ekf"][-1].header.frame_id == "map" and odom["ekf"][-1].child_frame_id == "base_link"
    assert np.all(np.diag(covs["lstm"]) == UNKNOWN_VARIANCE)
    for m, cols in (("ekf", 5), ("gru", 5), ("lstm", 1)):
        msg = state[m][-1]
        dims = [(d.label, d.size) for d in msg.layout.dim]
        names, x, P = O.read_state(msg.data, dims)
        assert names == ["px", "py", "vx", "vy"] and dims[1][1] == cols
        assert np.allclose(x, est[m][-1].position[2:])  # the JointState carries trajectory, step first
        assert (P is None) == (m == "lstm")
        if P is not None:
            assert np.allclose(P, P.T) and np.all(np.linalg.eigvalsh(P) > 0)
            assert P[0, 0] == pytest.approx(covs[m][0, 0])


def test_set_pose_topic_restarts_the_estimator_nodes_filter(tmp_path, monkeypatch):
    """estimator (ukf, bearings) <- 5 observations, a set_pose, one more observation: the last estimate
    equals the UKF restarted at the pose (velocities kept) and updated with that observation; a
    set_pose to a GRU node is refused in the log and the node goes on."""
    pytest.importorskip("rclpy")
    import signal
    import sys

    from geometry_msgs.msg import PoseWithCovarianceStamped
    from sensor_msgs.msg import JointState

    from neural_estimator.stream import messages as MSG
    from neural_estimator.data import simulate
    from neural_estimator.methods.registry import make_estimator
    from neural_estimator.nodes.common import stream_qos
    from neural_estimator.nodes.launch import ESTIMATOR, isolated_env, node_command, start_node
    from neural_estimator.stream.online import OnlineEstimator
    from neural_estimator.scenarios import make_scenario

    domain = fresh_domain()
    env = isolated_env(domain)
    procs = [
        start_node(
            node_command(sys.executable, ESTIMATOR, f"est_{m}", {"method": m, "scenario": "bearings"}),
            tmp_path / f"{m}.log",
            env,
        )
        for m in ("ukf", "gru")
    ]
    scen = make_scenario("bearings")
    data = simulate(scen, 1, 10, seed=5)

    def obs(k):
        return MSG.encode_observation(
            scen, MSG.step_stamp_ns(10**18, k, MSG.dt_ns(scen.dt)), 0, k, data.y[0, k], np.zeros(0)
        )

    tester = Tester(
        monkeypatch, domain, lambda: "logs:\n" + "".join((tmp_path / f"{m}.log").read_text() for m in est), timeout=60.0
    )
    try:
        node, spin_until = tester.node, tester.spin_until

        est = {"ukf": [], "gru": []}
        for m in est:
            node.create_subscription(
                JointState,
                f"estimates/{m}",
                lambda raw, m=m: est[m].append(MSG.decode_vector(raw)),
                stream_qos(100),
                raw=True,
            )
        pub = node.create_publisher(JointState, "observation", stream_qos(100, transient_local=False))
        pose_pub = node.create_publisher(PoseWithCovarianceStamped, "set_pose", 10)

        spin_until(lambda: pub.get_subscription_count() >= 2 and pose_pub.get_subscription_count() >= 2)
        spin_until(lambda: node.count_publishers("estimates/ukf") >= 1 and node.count_publishers("estimates/gru") >= 1)
        for k in range(5):
            pub.publish(obs(k))
        spin_until(lambda: len(est["ukf"]) >= 5 and len(est["gru"]) >= 5)
        hostile = PoseWithCovarianceStamped()  # a 1e308 variance once killed the node
        hostile.header.frame_id = "map"
        hostile.pose.pose.orientation.w = 1.0
        hostile.pose.covariance[0] = 1e308
        pose_pub.publish(hostile)
        spin_until(lambda: "set_pose refused: pose covariance" in (tmp_path / "ukf.log").read_text())
        pose = PoseWithCovarianceStamped()
        pose.header.frame_id = "map"  # the node's frame_id: any other is refused
        pose.pose.pose.position.x, pose.pose.pose.position.y = 40.0, -25.0
        pose.pose.pose.orientation.w = 1.0
        pose_pub.publish(pose)
        spin_until(lambda: "set_pose: state restarted" in (tmp_path / "ukf.log").read_text())
        spin_until(lambda: "filters only" in (tmp_path / "gru.log").read_text())
        pub.publish(obs(5))
        spin_until(lambda: len(est["ukf"]) >= 6 and len(est["gru"]) >= 6)
    finally:
        tester.shutdown()
        for p in procs:
            p.send_signal(signal.SIGINT)
        for p in procs:
            try:
                p.wait(timeout=10)
            except Exception:
                p.kill()
    ref = OnlineEstimator(make_estimator("ukf", scen), "ukf")
    for k in range(5):
        (last,) = [r.x_hat for r in ref.feed(obs(k)) if r.status == "estimated"]
    start = np.array([40.0, -25.0, last[2], last[3]])
    ref.estimator.reset(1, initial_mean=start[None])
    (expected,) = [r.x_hat for r in ref.feed(obs(5)) if r.status == "estimated"]
    np.testing.assert_allclose(est["ukf"][5].values, expected, rtol=0, atol=1e-9)
    assert abs(est["ukf"][5].values[0] - est["ukf"][4].values[0]) > 1.0  # the pose moved the estimate
