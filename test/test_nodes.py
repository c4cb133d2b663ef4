"""The ROS 2 nodes, live in an isolated ROS domain per test (processes started as the launcher does).

The scenario is a small controlled system written to a plugin file, so that the nodes (separate
processes) load it through their ``plugins`` parameter: observations carry a control u_{k-1}.
"""

from __future__ import annotations

import itertools
import json
import signal
import subprocess
import sys
import textwrap
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
from ros_tester import Tester, fresh_domain

from neural_estimator.bags import BagReader, BagWarning, arrays_to_bag, bag_to_arrays
from neural_estimator.stream import messages as MSG
from neural_estimator.data import simulate
from neural_estimator.nodes.launch import (
    ESTIMATOR,
    EVALUATOR,
    SIMULATOR,
    PipelineConfig,
    isolated_env,
    node_command,
    run_pipeline,
    start_node,
)
from neural_estimator.evaluation.replay import replay

pytestmark = pytest.mark.ros  # every test here runs ROS 2 nodes

pytest.importorskip("rclpy")

PLUGIN = textwrap.dedent(
    '''
    """A cart pushed by a force (test scenario with a control input)."""
    from dataclasses import dataclass

    import numpy as np

    from neural_estimator.scenarios import Scenario, register_scenario


    @dataclass(frozen=True)
    class CartConfig:
        dt: float = 0.05
        horizon: int = 40
        noise_scale: float = 1.0
        obs_noise_std: float = 0.1


    class NodeCart(Scenario):
        name = "nodecart"
        Config = CartConfig
        state_names = ("position", "velocity")
        state_units = ("m", "m/s")
        obs_names = ("position",)
        obs_units = ("m",)
        control_names = ("force",)
        control_units = ("N",)

        def f(self, x, u):
            dt = self.config.dt
            return np.stack([x[..., 0] + dt * x[..., 1], x[..., 1] + dt * u[..., 0]], axis=-1)

        def h(self, x):
            return x[..., :1]

        def process_cov(self):
            return np.diag([1e-6, 1e-3])

        def obs_cov_nominal(self):
            return np.array([[self.config.obs_noise_std ** 2]])

        def prior(self):
            return np.zeros(2), np.eye(2)

        def sample_controls(self, rng, n, horizon):
            return rng.standard_normal((n, horizon, 1))


    register_scenario(NodeCart, replace=True)
    '''
)


@pytest.fixture(scope="module")
def plugin(tmp_path_factory) -> str:
    path = tmp_path_factory.mktemp("plugin") / "nodecart.py"
    path.write_text(PLUGIN)
    return str(path)


@pytest.fixture(scope="module")
def cart(plugin):
    import importlib.util

    spec = importlib.util.spec_from_file_location("nodecart_plugin", plugin)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.NodeCart()


@pytest.fixture
def domain() -> int:
    """A ROS domain of its own for each test (ros_tester.fresh_domain: NEURAL_ESTIMATOR_DOMAINS or 200..232)."""
    return fresh_domain()


class Nodes:
    """Node processes of one test; stopped (SIGINT, then SIGKILL) at the end."""

    def __init__(self, domain: int, log_dir: Path) -> None:
        self.env = isolated_env(domain)
        self.log_dir = log_dir
        self.procs: dict[str, subprocess.Popen] = {}

    def start(self, module: str, name: str, extra_args: tuple[str, ...] = (), **params) -> subprocess.Popen:
        cmd = node_command(sys.executable, module, name, params) + list(extra_args)  # extra ROS args (remaps)
        proc = start_node(cmd, self.log_dir / f"{name}.log", self.env)
        self.procs[name] = proc
        return proc

    def log(self, name: str) -> str:
        return (self.log_dir / f"{name}.log").read_text(errors="replace")

    def wait(self, name: str, timeout: float) -> int:
        try:
            return self.procs[name].wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            raise AssertionError(f"{name} still running after {timeout} s; log:\n{self.log(name)}") from None

    def stop_all(self) -> None:
        for p in self.procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for p in self.procs.values():
            try:
                p.wait(timeout=5)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


@pytest.fixture
def nodes(domain, tmp_path):
    n = Nodes(domain, tmp_path)
    yield n
    n.stop_all()


# ---- the whole chain -------------------------------------------------------------------------------------
def test_live_chain_records_scores_and_equals_replay(plugin, cart, domain, tmp_path):
    bag = tmp_path / "live.mcap"
    cfg = PipelineConfig(
        scenario="nodecart",
        methods=("ekf", "ukf"),
        trajectories=2,
        horizon=40,
        rate_hz=200.0,
        seed=3,
        plugins=(plugin,),
        output=str(bag),
        domain_id=domain,
        timeout=100.0,
    )
    res = run_pipeline(cfg)
    assert res.returncodes["evaluator"] == 0 and res.bag == bag
    N, T = 2, 40

    # the recorded file: every stream complete, identities right, estimates finite
    with BagReader(bag, strict=True) as reader:
        counts = {t: c.msgcount for t, c in reader.topics.items()}
        assert all(c.message_encoding == "cdr" for c in reader.connections)
    for topic in (
        "/observation",
        "/ground_truth",
        "/estimates/ekf",
        "/estimates/ukf",
        "/estimates/ekf/covariance",
        "/estimates/ukf/covariance",
    ):
        assert counts[topic] == N * T, (topic, counts)
    assert counts["/scenario"] == 1 and counts["/run_status"] == 2
    run = bag_to_arrays(bag)
    assert run.complete and run.trajectories.tolist() == [0, 1]
    assert all(v == 0 for v in run.missing.values()) and not run.rejected and not run.duplicates
    data = simulate(cart, N, T, seed=3)  # the simulator publishes exactly these data
    np.testing.assert_array_equal(run.x, data.x)
    np.testing.assert_array_equal(run.y, data.y)
    np.testing.assert_array_equal(run.u[:, :-1], data.u[:, :-1])
    for m in ("ekf", "ukf"):
        assert np.isfinite(run.x_hat[m]).all() and np.isfinite(run.P_hat[m]).all()
    assert np.all(np.diff(run.stamps.reshape(-1)) > 0)

    # the evaluator's metrics, from the file
    metrics = res.metrics()
    assert set(metrics["methods"]) == {"ekf", "ukf"} and metrics["trajectories"] == N
    for m in ("ekf", "ukf"):
        rmse = metrics["methods"][m]["rmse"]
        assert 0 < rmse < 1.0 and metrics["methods"][m]["n_diverged"] == 0
    assert {"markdown", "json", "png"} <= set(res.reports) and res.reports["png"].stat().st_size > 0

    # offline replay of the recorded observations == the live estimates
    out = replay(bag, ["ekf", "ukf"], tmp_path / "replayed.mcap")
    assert out.estimates == {"ekf": N * T, "ukf": N * T}
    rep = bag_to_arrays(out.path)
    for m in ("ekf", "ukf"):
        np.testing.assert_allclose(rep.x_hat[m], run.x_hat[m], rtol=0, atol=1e-12)
        np.testing.assert_allclose(rep.P_hat[m], run.P_hat[m], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(rep.x, run.x)  # the rest of the bag is carried over


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


# ---- started by hand, in any order -----------------------------------------------------------------------------
_UP = {"sim": ("trajectories x",), "est": ("waiting for the scenario", "ukf on"), "rec": ("recording to",)}


@pytest.mark.parametrize("order", list(itertools.permutations(("sim", "est", "rec"))), ids="-".join)
def test_hand_started_nodes_lose_nothing_in_any_order(order, plugin, nodes, tmp_path):
    """The README's hand-start commands (defaults, no wait_for_subscribers), one node after the
    other once the previous one is up; the evaluator on simulation time (/clock from the simulator)."""
    bag = tmp_path / "hand.mcap"
    N, T = 2, 40
    start = {
        "sim": lambda: nodes.start(
            SIMULATOR,
            "sim",
            scenario="nodecart",
            plugins=[plugin],
            trajectories=N,
            horizon=T,
            rate_hz=100.0,
            publish_clock=True,
        ),
        "est": lambda: nodes.start(ESTIMATOR, "est", method="ukf", plugins=[plugin]),
        "rec": lambda: nodes.start(EVALUATOR, "rec", output=str(bag), plugins=[plugin], use_sim_time=True),
    }
    for name in order:
        start[name]()
        t0 = time.monotonic()
        while not any(text in nodes.log(name) for text in _UP[name]):
            assert time.monotonic() - t0 < 60, nodes.log(name)
            assert nodes.procs[name].poll() is None, nodes.log(name)
            time.sleep(0.1)
    assert nodes.wait("rec", 120) == 0, nodes.log("rec") + nodes.log("est") + nodes.log("sim")
    with BagReader(bag, strict=True) as reader:
        counts = {t: c.msgcount for t, c in reader.topics.items()}
    for topic in ("/observation", "/ground_truth", "/estimates/ukf", "/estimates/ukf/covariance"):
        assert counts.get(topic) == N * T, (order, counts)
    metrics = json.loads(bag.with_name("hand.metrics.json").read_text())
    assert metrics["trajectories"] == N and set(metrics["methods"]) == {"ukf"}


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

        def diag_values():
            for arr in reversed(diags):
                for st in arr.status:
                    if "ukf estimator" in st.name:
                        return {kv.key: kv.value for kv in st.values}
            return {}

        spin_until(lambda: diag_values().get("estimates published") == "21")
        values = diag_values()
        assert values["out-of-order steps"] == "1" and values["stream restarts"] == "1"
        assert values["trajectory resets"] == "2"  # trajectory 0, trajectory 1: the stray one reset nothing
        assert values["quarantined messages"] == "3"  # (1, 0) until (1, 1); the stray (0, 7); the jump
    finally:
        tester.shutdown()
    log = nodes.log("est")
    assert "nothing publishes /clock" in log and "restarted from the prior" in log


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


def test_a_busy_estimator_publishes_its_diagnostics_from_the_message_path():
    # the events executor serves queued messages before a due timer: a node that never idles
    # must still report, so the observation callback publishes when the timer is overdue
    import types

    from neural_estimator.nodes.estimator_node import EstimatorNode
    from neural_estimator.nodes.estimator_stats import EstimatorStats

    published = []
    node = types.SimpleNamespace(
        p=types.SimpleNamespace(drain=False, max_delay=0.0, diagnostics_period=1.0, queue_depth=10),
        sub_obs=None,
        stats=EstimatorStats(),
        _on_observation=lambda raw, info: None,
        _last_diagnostics=time.monotonic(),
    )

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
