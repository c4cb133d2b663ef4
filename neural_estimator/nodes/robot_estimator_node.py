"""Robot estimator node: a neural estimator trained on recorded data, served on the robot's own topics.

    ros2 run neural_estimator robot_estimator --ros-args -p checkpoint:=runs/robot-mamba
    python -m neural_estimator.nodes.robot_estimator_node --ros-args -p checkpoint:=runs/robot-mamba

The checkpoint's card (``neural-estimator train --data``) carries the spec the model was trained
with (docs/robot.md). The node needs no scenario: it subscribes to the spec's
observation and control topics with their own message types (found on the graph when a publisher
appears, and checked as the evaluator checks foreign types: ``neural_estimator.interfaces``),
reads the spec's fields from every message, and at every tick of the spec's rate (or on every
message of its ``trigger`` topic) assembles the observation from each topic's latest message and
steps the estimator once. A tick at which some topic has no message received within the spec's
``max_age`` is skipped and counted (the model was trained on ticks with every input fresh).
Live, ages are measured on receipt (the node's steady clock), since a recording's header stamps
are of another clock when a bag is played without ``/clock``.

On sim time (``use_sim_time:=true``, a player with ``publish_clock:=true``: launch/robot_estimator.launch.py
with ``bag:=``) the ticks are the multiples of dt of the recording's clock, each run once every input
has delivered a message stamped after it (or the clock is ``sim_delay`` past it), on every input's
latest message stamped (header, as the spec says) at or before the tick: the dataset builder's
rule, so a bag played at 4x gives the estimates of 1x.

Publishes ``estimates/<method>`` (sensor_msgs/JointState with the spec's state names, stamped at
the tick), the standard outputs of :mod:`neural_estimator.nodes.outputs` (Odometry or
PoseWithCovarianceStamped when the state is named like a pose (x, y, yaw, ...), unknown components
with variance 1e6; the state vector; optional /tf); ``/diagnostics`` every ``diagnostics_period`` s
(with each input's frequency and staleness, :mod:`neural_estimator.nodes.diagnostics`). A message
missing a field the spec names is counted and logged
(throttled), never fatal; a missing checkpoint, a checkpoint without a spec or an unknown method
is one fatal line at start-up (exit status 1).
"""

from __future__ import annotations

import collections
import dataclasses
import sys
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.clock import Clock, ClockType
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState

from neural_estimator.bags import messages as M
from neural_estimator.nodes.diagnostics import (
    OK,
    WARN,
    InputDiagnosticsParams,
    hardware_id,
    merge,
    parse_rates,
    status_message,
)
from neural_estimator.nodes.outputs import OutputError, OutputParams, Outputs
from neural_estimator.robot.dataset import topic_fields
from neural_estimator.robot.spec import SpecError, topic_values
from neural_estimator.nodes.common import (
    ExitStatusNode,
    InterfaceError,
    StartupError,
    declare_params,
    message_class,
    param,
    run_node,
    stream_qos,
)


@dataclasses.dataclass(frozen=True)
class RobotEstimatorParams:
    """Parameters of the robot estimator node."""

    checkpoint: str = param("", "checkpoint directory (or card.json) trained with neural-estimator train --data")
    device: str = param("cpu", "torch device: cpu, cuda, cuda:N, auto")
    threads: int = param(1, "torch intra-op threads (one suits one-step updates); 0 = torch's default")
    output_topic: str = param("", "estimate topic; empty = estimates/<method>")
    publish_odometry: bool = param(True, "publish the pose output (pose_output) when the state is a pose")
    frame_id: str = param("map", "header.frame_id of the estimates and the odometry")
    child_frame_id: str = param("base_link", "child_frame_id of the odometry")
    input_qos: str = param(
        "sensor_data", "input subscriptions' reliability: sensor_data (best effort, matches any publisher) or reliable"
    )
    discovery_period: float = param(0.2, "seconds between looks at the graph for the spec's topics")
    queue_depth: int = param(1000, "input subscriptions' depth (KEEP_LAST): messages buffered while busy")
    sim_delay: float = param(
        2.0,
        "on sim time: a tick at T waits for a message stamped after T on every input, or for the clock to "
        "reach T + sim_delay (s) when an input is silent",
    )
    diagnostics_period: float = param(1.0, "seconds between /diagnostics messages")
    expected_rates: tuple[str, ...] = param(
        (), "expected rate of each input as topic=Hz (e.g. /imu=100): WARN outside the band; others: expected_rate"
    )
    log_throttle: float = param(2.0, "seconds between repeated warnings of one kind")


class RobotEstimatorNode(ExitStatusNode):
    def __init__(self, node_name: str = "robot_estimator") -> None:
        super().__init__(node_name)
        self.setup()

    def setup(self, card: tuple | None = None) -> None:
        """Declare the parameters, load the model and wire the topics; ``card``: the checkpoint
        (:class:`~neural_estimator.serving.card.Checkpoint`) when already resolved (the estimator
        executable decides from its card which node to be)."""
        self.p = p = declare_params(self, RobotEstimatorParams)
        self.po = declare_params(self, OutputParams)
        self.pd = declare_params(self, InputDiagnosticsParams)
        try:
            rates = parse_rates(p.expected_rates)
        except ValueError as exc:
            raise StartupError(str(exc)) from None
        if p.input_qos not in ("sensor_data", "reliable"):
            raise StartupError(f"parameter input_qos must be sensor_data or reliable, got {p.input_qos!r}")
        self.scenario, self.spec, self.method, self.est = _load(p, card)
        fields = topic_fields(self.spec)
        inputs = [f.topic for name in ("observation", "control") for f in self.spec.vectors[name]]
        if self.spec.trigger:
            inputs.append(self.spec.trigger)
        self.fields = {t: fields.get(t, ()) for t in dict.fromkeys(inputs)}  # topic -> its fields, in order
        # each vector's components as (topic, column of that topic's values), resolved once, not per tick
        self.columns = {
            name: [(f.topic, self.fields[f.topic].index(f)) for f in self.spec.vectors[name]]
            for name in ("observation", "control")
        }
        self.latest: dict[str, tuple[int, np.ndarray]] = {}  # topic -> (receipt time ns, values)
        self.history: dict[str, collections.deque] = {}  # on sim time: topic -> (stamp ns, values) not yet used
        self.subs: dict[str, object] = {}
        self.counts = {"ticks": 0, "estimates": 0, "stale": 0, "bad_messages": 0, "messages": 0}
        self._last_log: dict[str, float] = {}
        self._refused: set[str] = set()
        self._u_prev = np.zeros((1, self.scenario.du))
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        # On sim time (a bag played with /clock), ticks follow the player's clock: at every tick time
        # T_k = k * dt of the sim clock passed, so a bag played at any rate gives the same ticks.
        self.sim_time = bool(self.get_parameter("use_sim_time").value)
        self._clock = self.get_clock() if self.sim_time else self._steady
        self._next_tick: int | None = None  # sim time [ns] of the next tick
        now = time.monotonic()
        self.monitors = {t: self.pd.monitor(t, now, rates.get(t)) for t in self.fields}
        self.est.reset(1)
        out = p.output_topic or M.estimate_topic(self.method)
        self.pub_est = self.create_publisher(JointState, out, stream_qos(1000))
        try:
            self.outputs = Outputs(
                self,
                self.po,
                out,
                stream_qos(1000),
                p.frame_id,
                p.child_frame_id,
                self.scenario.state_names,
                self.scenario.pose_states,
                p.publish_odometry,
            )
        except OutputError as exc:
            raise StartupError(str(exc)) from None
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_timer(p.discovery_period, self._discover, clock=self._steady)
        self.create_timer(p.diagnostics_period, self._diagnostics, clock=self._steady)
        if not self.spec.trigger and not self.sim_time:
            self.create_timer(self.spec.dt, self._tick, clock=self._steady)
        self.get_logger().info(
            f"{self.method} on recorded-data spec {self.spec.digest()[:12]}: {', '.join(self.fields)} -> '{out}'"
            + self.outputs.describe()
            + f" at {self.spec.rate:g} Hz"
            + (" of the sim clock (/clock)" if self.sim_time and not self.spec.trigger else "")
            + (f" (on {self.spec.trigger})" if self.spec.trigger else "")
        )
        self._discover()

    # ---- inputs ------------------------------------------------------------------------------------
    def _discover(self) -> None:
        """Subscribe to every spec topic that has a publisher, with the type it is published with."""
        if len(self.subs) == len(self.fields):
            return
        types = dict(self.get_topic_names_and_types())
        for topic in self.fields:
            if topic in self.subs or topic not in types or topic in self._refused:
                continue
            msgtype = types[topic][0]
            try:
                cls = message_class(msgtype)
            except InterfaceError as exc:
                self._refused.add(topic)
                self.get_logger().error(f"'{topic}': {exc}; not subscribed")
                continue
            qos = QoSProfile(
                depth=max(1, self.p.queue_depth),
                durability=DurabilityPolicy.VOLATILE,
                reliability=ReliabilityPolicy.BEST_EFFORT
                if self.p.input_qos == "sensor_data"
                else ReliabilityPolicy.RELIABLE,
            )
            self.subs[topic] = self.create_subscription(
                cls, topic, lambda msg, t=topic, m=msgtype: self._on_message(t, m, msg), qos
            )
            self.get_logger().info(f"subscribed to '{topic}' ({msgtype})")

    def _on_message(self, topic: str, msgtype: str, msg) -> None:
        self.counts["messages"] += 1
        self.monitors[topic].tick(time.monotonic())
        try:
            values = topic_values(msg, self.fields[topic], msgtype)
        except SpecError as exc:
            self.counts["bad_messages"] += 1
            self._warn(f"field:{topic}", str(exc))
            return
        now = self._clock.now().nanoseconds
        self.latest[topic] = (now, values)
        if self.sim_time and not self.spec.trigger:
            header = getattr(msg, "header", None)
            stamp = now
            if self.spec.stamp == "header" and header is not None:
                stamp = int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)
            self.history.setdefault(topic, collections.deque(maxlen=10_000)).append((stamp, values))
            self._sim_ticks()
        elif self.spec.trigger == topic:
            self._tick()

    # ---- one estimate per tick ------------------------------------------------------------------------
    def _sim_ticks(self) -> None:
        """Run every tick T of the sim-time grid (multiples of dt) that is settled, on each input's latest
        message stamped at or before T (the dataset builder's rule). T is settled when every input has
        delivered a message stamped after T (messages of one topic arrive in order), or when the sim
        clock is ``sim_delay`` past T (an input that went silent). Neither depends on the playback rate,
        so a bag played at 4x gives the ticks and inputs of 1x."""
        period = int(round(self.spec.dt * 1e9))
        if self._next_tick is None:
            first = min(q[0][0] for q in self.history.values())
            self._next_tick = -(-first // period) * period
        marks = [self.history[t][-1][0] if self.history.get(t) else None for t in self.fields]
        settled = min(marks) if None not in marks else -1
        clock = self.get_clock().now().nanoseconds - int(self.p.sim_delay * 1e9)
        until = max(settled, clock)
        if (until - self._next_tick) // period > 100_000:  # a jump of the clock: no input at those ticks
            skipped = (until - self._next_tick) // period
            self.counts["ticks"] += int(skipped)
            self.counts["stale"] += int(skipped)
            self._next_tick += int(skipped) * period
        while self._next_tick <= until:
            self._tick(self._next_tick)
            self._next_tick += period

    def _at(self, tick: int) -> dict[str, tuple[int, np.ndarray]]:
        """{topic: (stamp, values)} of each input's latest message stamped at or before ``tick``;
        older messages that no later tick can use are dropped."""
        out = {}
        for topic, queue in self.history.items():
            while len(queue) > 1 and queue[1][0] <= tick:
                queue.popleft()
            if queue and queue[0][0] <= tick:
                out[topic] = queue[0]
        return out

    def _tick(self, stamp: int | None = None) -> None:
        self.counts["ticks"] += 1
        now = self._clock.now().nanoseconds if stamp is None else stamp
        latest = self._at(stamp) if self.sim_time and stamp is not None else self.latest
        max_age = int(self.spec.max_age * 1e9)
        if any(t not in latest or now - latest[t][0] > max_age for t in self.fields):
            self.counts["stale"] += 1
            return
        y, u = self._vector("observation", latest), self._vector("control", latest)
        if not (np.all(np.isfinite(y)) and np.all(np.isfinite(u))):
            self.counts["stale"] += 1
            return
        x = np.asarray(self.est.step(y[None], self._u_prev), dtype=np.float64)[0]
        self._u_prev = u[None]
        self.counts["estimates"] += 1
        stamp = self.get_clock().now().nanoseconds if stamp is None else stamp
        msg = JointState()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
        msg.header.frame_id = self.p.frame_id
        msg.name = list(self.scenario.state_names)
        msg.position = x.tolist()
        self.pub_est.publish(msg)
        cov = self.est.covariance
        self.outputs.publish(stamp, x, None if cov is None else cov[0])

    def _vector(self, name: str, latest: dict[str, tuple[int, np.ndarray]]) -> np.ndarray:
        return np.array([latest[topic][1][col] for topic, col in self.columns[name]], dtype=np.float64)

    # ---- reporting ------------------------------------------------------------------------------------
    def _warn(self, kind: str, text: str) -> None:
        now = time.monotonic()
        if now - self._last_log.get(kind, -1e9) >= self.p.log_throttle:
            self._last_log[kind] = now
            self.get_logger().warning(text)

    def _diagnostics(self) -> None:
        hwid = hardware_id(self.get_fully_qualified_name(), self.method)
        status = DiagnosticStatus(name=f"{self.get_name()}: {self.method} (recorded-data spec)", hardware_id=hwid)
        missing = [t for t in self.fields if t not in self.subs]
        now = time.monotonic()
        inputs = [m.status(now) for m in self.monitors.values()]
        level, message = merge(
            [(WARN if missing else OK, f"waiting for {', '.join(missing)}")]
            + [(st.level, f"{st.name}: {st.message}") for st in inputs]
        )
        status.level = (DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR)[level]
        status.message = "running" if message == "ok" else message
        status.values = [KeyValue(key=k, value=str(v)) for k, v in self.counts.items()]
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status = [status] + [status_message(st, status.name, hwid, DiagnosticStatus, KeyValue) for st in inputs]
        self.pub_diag.publish(arr)


def _load(p: RobotEstimatorParams, read=None):
    """(DataScenario, Spec, method, estimator) from the checkpoint's card (``read``: the
    :class:`~neural_estimator.serving.card.Checkpoint` already resolved); StartupError otherwise."""
    from pathlib import Path

    from neural_estimator.registry import EstimatorError, make_estimator, per_message_options
    from neural_estimator.serving.card import resolve_checkpoint
    from neural_estimator.robot import DataScenario, SpecError, load_spec
    from neural_estimator.scenarios import ScenarioError

    if not p.checkpoint:
        raise StartupError("parameter checkpoint is required: a model trained with neural-estimator train --data")
    path = Path(p.checkpoint)
    if not path.exists():
        raise StartupError(f"checkpoint {p.checkpoint!r} does not exist")
    try:
        ckpt = read if read is not None else resolve_checkpoint(path)  # read once, passed to the estimator
        card = ckpt.card
        desc = card["scenario"]
        if desc.get("scenario") != "data" or not desc.get("spec"):
            raise StartupError(
                f"checkpoint {p.checkpoint}: trained on scenario {desc.get('scenario')!r}, not on recorded "
                "data with a spec; serve it with the estimator node"
            )
        scenario = DataScenario.from_description(desc)
        spec = load_spec(desc["spec"])
        method = str(card["method"])
        est = make_estimator(method, scenario, checkpoint=ckpt, device=p.device, **per_message_options(method, {}))
        torch = sys.modules.get("torch")  # absent when step.onnx serves the model without torch
        if p.threads > 0 and torch is not None:
            torch.set_num_threads(p.threads)
    except (EstimatorError, ScenarioError, SpecError, KeyError, TypeError) as exc:
        raise StartupError(f"checkpoint {p.checkpoint}: {exc}") from None
    return scenario, spec, method, est


def main(args: list[str] | None = None) -> int:
    return run_node(RobotEstimatorNode, "robot_estimator", args)


if __name__ == "__main__":
    sys.exit(main())
