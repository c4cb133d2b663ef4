"""Simulator node: publishes a scenario's observations and ground truth at a fixed rate.

    ros2 run neural_estimator simulator --ros-args -p scenario:=lorenz96 -p trajectories:=2
    python -m neural_estimator.nodes.simulator_node --ros-args -p scenario:=lorenz96       # without ros2

Publishes (relative names, layout of :mod:`neural_estimator.stream.messages`):

- ``scenario`` (std_msgs/String, JSON, reliable + transient_local depth 1) once, first;
- ``run_status`` (std_msgs/String, JSON, reliable + transient_local depth 1): "started", then
  "complete" with the message count;
- per step, ``observation`` then ``ground_truth`` (sensor_msgs/JointState, reliable +
  transient_local, KEEP_LAST ``history_depth``);
- per step, where the scenario's state holds a pose or a position (``Scenario.pose_states``:
  bearings, quadrotor), the truth also as ``ground_truth/odometry`` (nav_msgs/Odometry, frame
  ``frame_id`` -> ``child_frame_id``, same stamp; components the state lacks get the "unknown"
  variance of :mod:`neural_estimator.nodes.odometry`, the others zero): what pose tools (evo,
  Foxglove's 3D panel) read, beside the estimators' ``estimates/<method>/odometry``.

Losing nothing at start-up, whatever order the nodes are started in: the node waits until
``wait_for_subscribers`` subscriptions match the observation topic (default 1: started by hand,
it waits for its first estimator or recorder; the launcher sets it to the number of estimators
plus the evaluator; ``wait_timeout`` bounds the wait), then ``start_delay`` more seconds. The
streams are transient_local with a deep history, and the estimator and evaluator subscribe
transient_local, so a subscriber that joins later, even after the run, receives the first
``history_depth`` messages it missed as long as this node is up: after the run it stays
``stay_after_run`` seconds for such late joiners, then until every subscriber acknowledged every
message (``linger``). The same depth is the backlog a slow subscriber may build without loss.

Time: with ``publish_clock`` the node publishes ``/clock`` (rosgraph_msgs/Clock) at each step's
stamp, so nodes started with ``use_sim_time:=true`` live on the simulation's time.

The data are :func:`neural_estimator.data.simulate` of (scenario, trajectories, horizon, seed):
the same bytes as ``neural-estimator simulate`` writes. Parameters: ``params/simulator.yaml``.
"""

from __future__ import annotations

import dataclasses
import sys
import threading
import time

import numpy as np
from rclpy.duration import Duration
from sensor_msgs.msg import JointState
from rosgraph_msgs.msg import Clock as ClockMsg
from std_msgs.msg import String

from neural_estimator.nodes.odometry import has_pose, make_odometry
from neural_estimator.nodes.outputs import TRUTH_ODOMETRY

from neural_estimator.stream import messages as MSG
from neural_estimator.nodes.common import (
    ExitStatusNode,
    StartupError,
    build_scenario,
    declare_params,
    latched_qos,
    load_plugins,
    param,
    request_shutdown,
    run_node,
    stream_qos,
)


@dataclasses.dataclass(frozen=True)
class SimulatorParams:
    """Parameters of the simulator node (documented in params/simulator.yaml)."""

    scenario: str = param("lorenz96", "scenario name (built-in or registered by a plugin)")
    set: tuple[str, ...] = param((), "scenario constants as name=value, e.g. ['forcing=10.0']")
    preset: str = param("", "named constants of the scenario, applied before set (empty = the defaults; e.g. v3)")
    plugins: tuple[str, ...] = param((), "Python files registering user scenarios")
    noise_scale: float = param(-1.0, "observation-noise scale; negative = the scenario's (or set's) value")
    seed: int = param(0, "seed of the simulated data (same seed, same data)")
    trajectories: int = param(1, "number of trajectories, published one after the other")
    horizon: int = param(0, "steps per trajectory; 0 = the scenario's default")
    rate_hz: float = param(0.0, "steps published per second; 0 = real time (1 / dt)")
    wait_for_subscribers: int = param(1, "observation subscriptions to wait for before starting (0 = start at once)")
    wait_timeout: float = param(30.0, "seconds to wait for them (then start anyway, with a warning); 0 = forever")
    start_delay: float = param(0.5, "extra seconds before the first step (discovery of the other topics)")
    history_depth: int = param(
        10000,
        "depth of the observation / ground-truth publishers (transient_local): "
        "the backlog a slow subscriber may build without loss",
    )
    publish_ground_truth: bool = param(True, "publish ground_truth")
    truth_odometry: bool = param(
        True, "also publish the truth as nav_msgs/Odometry on ground_truth/odometry where the state holds a pose"
    )
    frame_id: str = param("map", "header.frame_id of ground_truth/odometry")
    child_frame_id: str = param("base_link", "child_frame_id of ground_truth/odometry")
    exit_when_done: bool = param(True, "shut down after the run (after linger seconds)")
    linger: float = param(30.0, "most seconds to wait after the run until every subscriber acknowledged every message")
    stay_after_run: float = param(
        10.0, "seconds to stay up after the run so that late subscribers still get the history"
    )
    publish_clock: bool = param(False, "publish /clock at each step's stamp (for nodes with use_sim_time:=true)")


class SimulatorNode(ExitStatusNode):
    def __init__(self) -> None:
        super().__init__("simulator")
        self.p = p = declare_params(self, SimulatorParams)
        if p.trajectories < 1:
            raise StartupError(f"trajectories must be >= 1, got {p.trajectories}")
        if p.horizon < 0 or p.rate_hz < 0:
            raise StartupError("horizon and rate_hz must be >= 0")
        load_plugins(p.plugins)
        self.scenario = build_scenario(
            p.scenario, p.set, p.noise_scale if p.noise_scale >= 0 else None, preset=p.preset
        )
        from neural_estimator.data import simulate

        self.horizon = p.horizon or self.scenario.horizon
        self.rate = p.rate_hz or 1.0 / self.scenario.dt
        self.data = simulate(self.scenario, p.trajectories, self.horizon, p.seed)
        self.pub_scenario = self.create_publisher(String, MSG.SCENARIO, latched_qos())
        self.pub_status = self.create_publisher(String, MSG.RUN_STATUS, latched_qos())
        self.pub_obs = self.create_publisher(JointState, MSG.OBSERVATION, stream_qos(p.history_depth))
        self.pub_truth = self.create_publisher(JointState, MSG.GROUND_TRUTH, stream_qos(p.history_depth))
        self.pub_clock = self.create_publisher(ClockMsg, "/clock", 10) if p.publish_clock else None
        self.pub_odom = None
        if p.publish_ground_truth and p.truth_odometry and has_pose(self.scenario.pose_states):
            from nav_msgs.msg import Odometry

            self._odometry = Odometry
            self.pub_odom = self.create_publisher(Odometry, TRUTH_ODOMETRY, stream_qos(p.history_depth))
        self.get_logger().info(
            f"{self.scenario.name}: {p.trajectories} trajectories x {self.horizon} steps at {self.rate:g} Hz "
            f"(seed {p.seed}, dt {self.scenario.dt:g} s)"
        )
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="simulator", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            self._wait_for_subscribers()
            if not self._stop.wait(self.p.start_delay):
                self._publish_run()
        except Exception as exc:  # never leave the node spinning without its run
            if self._stop.is_set() or not self.context.ok():
                return  # stopped (SIGINT, SIGTERM) while waiting or publishing: the context went away, no failure
            self.get_logger().fatal(f"simulation failed: {exc!r}")
            request_shutdown(self, 1)

    def _wait_for_subscribers(self) -> None:
        want, timeout = self.p.wait_for_subscribers, self.p.wait_timeout
        if want <= 0:
            return
        self.get_logger().info(f"waiting for {want} subscriber(s) on '{self.pub_obs.topic_name}'")
        t0 = time.monotonic()
        while self.pub_obs.get_subscription_count() < want:
            if self._stop.wait(0.05):
                return
            if timeout > 0 and time.monotonic() - t0 > timeout:
                self.get_logger().warning(
                    f"only {self.pub_obs.get_subscription_count()} of {want} subscribers after {timeout:g} s: "
                    "starting anyway"
                )
                return

    def _publish_run(self) -> None:
        p, s, d = self.p, self.scenario, self.data
        N, T = d.n, d.horizon
        period = MSG.dt_ns(s.dt)
        start_ns = time.time_ns()
        info = {"trajectories": N, "horizon": T, "messages": N * T}
        self.pub_scenario.publish(
            MSG.encode_scenario(
                s.describe(),
                seed=p.seed,
                trajectories=N,
                horizon=T,
                rate_hz=self.rate,
                start_ns=start_ns,
                dt_ns=period,
                messages=N * T,
                node=self.get_fully_qualified_name(),
            )
        )
        self.pub_status.publish(MSG.encode_run_status(MSG.STATUS_STARTED, **info))
        obs_codec = MSG.VectorCodec(s.name, MSG.observation_labels(s))
        truth_codec = MSG.VectorCodec(s.name, MSG.state_labels(s))
        zeros = np.zeros(s.du)
        t0 = time.perf_counter()
        late = 0
        for n in range(N):
            for k in range(T):
                g = n * T + k
                due = t0 + g / self.rate
                wait = due - time.perf_counter()
                if wait > 0:
                    if self._stop.wait(wait):
                        return
                elif wait < -0.01:
                    late += 1
                stamp = MSG.step_stamp_ns(start_ns, g, period)
                if self.pub_clock is not None:
                    clock = ClockMsg()
                    clock.clock.sec, clock.clock.nanosec = divmod(stamp, 1_000_000_000)
                    self.pub_clock.publish(clock)
                u_prev = d.u[n, k - 1] if k else zeros
                self.pub_obs.publish(obs_codec.encode(stamp, n, k, np.concatenate([d.y[n, k], u_prev])))
                if p.publish_ground_truth:
                    self.pub_truth.publish(truth_codec.encode(stamp, n, k, d.x[n, k]))
                if self.pub_odom is not None:
                    self.pub_odom.publish(self._truth_odometry(stamp, d.x[n, k]))
            if self._stop.is_set():
                return
        elapsed = time.perf_counter() - t0
        self.pub_status.publish(MSG.encode_run_status(MSG.STATUS_COMPLETE, elapsed_s=elapsed, **info))
        self.get_logger().info(
            f"run complete: {N * T} observations in {elapsed:.2f} s ({N * T / max(elapsed, 1e-9):.0f} Hz achieved, "
            f"{late} steps more than 10 ms late)"
        )
        if p.exit_when_done:
            if p.stay_after_run > 0 and self._stop.wait(p.stay_after_run):
                return
            self._wait_for_acks()
            request_shutdown(self, 0)

    def _truth_odometry(self, stamp: int, x: np.ndarray):
        """The true state as Odometry: exact (zero variance) where the state has the component."""
        s = self.scenario
        return make_odometry(
            self._odometry, stamp, self.p.frame_id, self.p.child_frame_id, x, np.zeros((s.dx, s.dx)), s.pose_states
        )

    def _wait_for_acks(self) -> None:
        """Exiting drops what subscribers have not acknowledged yet (a slow recorder's backlog)."""
        deadline = time.monotonic() + self.p.linger
        for pub in (self.pub_obs, self.pub_truth, self.pub_status, *([self.pub_odom] if self.pub_odom else [])):
            left = deadline - time.monotonic()
            if left <= 0 or self._stop.is_set():
                break
            if not pub.wait_for_all_acked(Duration(seconds=left)):
                self.get_logger().warning(
                    f"'{pub.topic_name}': not every subscriber acknowledged within {self.p.linger:g} s"
                )

    def on_shutdown(self) -> int:
        self._stop.set()
        self._thread.join(timeout=2.0)
        return self.exit_code


def main(args: list[str] | None = None) -> int:
    return run_node(SimulatorNode, "simulator", args)


if __name__ == "__main__":
    sys.exit(main())
