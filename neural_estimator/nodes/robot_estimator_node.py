"""Robot estimator node: a neural estimator trained on recorded data, served on the robot's own topics.

    ros2 run neural_estimator robot_estimator --ros-args -p checkpoint:=runs/robot-mamba
    python -m neural_estimator.nodes.robot_estimator_node --ros-args -p checkpoint:=runs/robot-mamba

The checkpoint's card (``neural-estimator train --data``) carries the spec the model was trained
with (docs/robot.md). The node needs no scenario: it subscribes to the spec's
observation and control topics with their own message types (found on the graph when a publisher
appears, and checked as the evaluator checks foreign types: ``neural_estimator.core.interfaces``),
reads the spec's fields from every message, and hands them to a
:class:`~neural_estimator.robot.ticker.Ticker`: the dataset builder's ticks and sampling on the
messages' own stamps (header stamps, or receipt times for a ``stamp: log`` spec), the model
restarted where ``evaluate`` starts a trajectory (``restart_every``, the card's trajectory
length by default). So a recording played into the node, at any speed, with or without
``/clock``, gives the estimates ``neural-estimator evaluate`` scored on the dataset of that
recording. Every estimate is stamped with its tick: the time, on the recording's (the sensors')
clock, of the observation it answers.

Publishes ``estimates/<method>`` (sensor_msgs/JointState with the spec's state names, stamped with
the tick), the standard outputs of :mod:`neural_estimator.nodes.outputs` (Odometry or
PoseWithCovarianceStamped when the state is named like a pose (x, y, yaw, ...), unknown components
with variance 1e6; the state vector; optional /tf); ``/diagnostics`` every ``diagnostics_period`` s
(with each input's frequency and staleness, :mod:`neural_estimator.nodes.diagnostics`). A message
missing a field the spec names is counted and logged
(throttled), never fatal; a missing checkpoint, a checkpoint without a spec, an unknown method or a
hybrid (``kalmannet``) whose spec names no model is one fatal line at start-up (exit status 1).

A hybrid trained on a recording whose spec names the system's model (``model:``, docs/robot.md)
is served as a network is: the card's scenario delegates f, h and the prior to that model
(:class:`~neural_estimator.robot.DataScenario`), which the hybrid runs on each tick.
"""

from __future__ import annotations

import dataclasses
import sys
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.clock import Clock, ClockType
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState

from neural_estimator.stream import messages as MSG
from neural_estimator.nodes.diagnostics import (
    OK,
    WARN,
    InputDiagnosticsParams,
    hardware_id,
    merge,
    parse_rates,
    status_message,
)
from neural_estimator.nodes.estimator_setup import standard_outputs
from neural_estimator.nodes.outputs import OutputParams
from neural_estimator.robot.spec import SpecError, topic_values
from neural_estimator.robot.dataset import message_stamp
from neural_estimator.robot.ticker import TickEstimate, Ticker
from neural_estimator.nodes.common import (
    ExitStatusNode,
    StartupError,
    declare_params,
    param,
    run_node,
    stream_qos,
    subscribable_class,
    warn_throttled,
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
    settle_delay: float = param(
        2.0,
        "a tick at T waits for a message stamped at or after T on every input, or for some input's stamps "
        "to reach T + settle_delay (s) when another is silent",
    )
    restart_every: int = param(
        -1,
        "restart the model every N valid ticks (and after a gap), as evaluate starts each trajectory: "
        "-1 = the trajectory length of the model's training data (the card), 0 = never",
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
        if p.restart_every < -1:
            raise StartupError(f"parameter restart_every must be -1, 0 or a number of ticks, got {p.restart_every}")
        restart = self.scenario.config.horizon if p.restart_every == -1 else p.restart_every
        self.ticker = Ticker(self.spec, self.est, restart, p.settle_delay)
        self.fields = self.ticker.fields  # topic -> its fields, in order
        self.subs: dict[str, object] = {}
        self.counts = {"messages": 0, "bad_messages": 0}
        self._last_log: dict[str, float] = {}
        self._refused: set[str] = set()
        now = time.monotonic()
        self.monitors = {t: self.pd.monitor(t, now, rates.get(t)) for t in self.fields}
        out = p.output_topic or MSG.estimate_topic(self.method)
        self.pub_est = self.create_publisher(JointState, out, stream_qos(1000))
        self.outputs = standard_outputs(self, self.po, p, out, stream_qos(1000), self.scenario)
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        steady = Clock(clock_type=ClockType.STEADY_TIME)  # not /clock: discovery runs before a player's clock
        self.create_timer(p.discovery_period, self._discover, clock=steady)
        self.create_timer(p.diagnostics_period, self._diagnostics, clock=steady)
        self.get_logger().info(
            f"{self.method} on recorded-data spec {self.spec.digest()[:12]}: {', '.join(self.fields)} -> '{out}'"
            + self.outputs.describe()
            + (f" on each {self.spec.trigger} message" if self.spec.trigger else f" at {self.spec.rate:g} Hz")
            + f" of the inputs' {'header stamps' if self.spec.stamp == 'header' else 'receipt times'}"
            + (f", restarted every {restart} ticks" if restart else "")
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
            cls = subscribable_class(self, topic, msgtype, self._refused, "subscribed")
            if cls is None:
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
        receipt = self.get_clock().now().nanoseconds  # ROS time: the player's /clock on sim time
        for e in self.ticker.push(topic, message_stamp(msg, receipt, self.spec), values):
            self._publish(e)

    # ---- one estimate per tick ------------------------------------------------------------------------
    def _publish(self, e: TickEstimate) -> None:
        msg = JointState()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(e.stamp, 1_000_000_000)
        msg.header.frame_id = self.p.frame_id
        msg.name = list(self.scenario.state_names)
        msg.position = e.x.tolist()
        self.pub_est.publish(msg)
        self.outputs.publish(e.stamp, e.x, e.cov)

    # ---- reporting ------------------------------------------------------------------------------------
    def _warn(self, kind: str, text: str) -> None:
        warn_throttled(self, self._last_log, kind, text, self.p.log_throttle)

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
        counts = {**self.ticker.counts, **self.counts}
        status.values = [KeyValue(key=k, value=str(v)) for k, v in counts.items()]
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status = [status] + [status_message(st, status.name, hwid, DiagnosticStatus, KeyValue) for st in inputs]
        self.pub_diag.publish(arr)


def _load(p: RobotEstimatorParams, read=None):
    """(DataScenario, Spec, method, estimator) from the checkpoint's card (``read``: the
    :class:`~neural_estimator.serving.card.Checkpoint` already resolved); StartupError otherwise."""
    from pathlib import Path

    from neural_estimator.methods import table
    from neural_estimator.methods.registry import EstimatorError, make_estimator, per_message_options
    from neural_estimator.serving.card import resolve_checkpoint
    from neural_estimator.robot import DataScenario, SpecError, load_spec
    from neural_estimator.robot.spec import topic_order_lost
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
        if topic_order_lost(desc["spec"]):
            raise StartupError(
                f"checkpoint {p.checkpoint}: its card's spec does not keep the order of the input topics "
                "(a card written before the order was recorded): retrain the model (neural-estimator train --data)"
            )
        scenario = DataScenario.from_description(desc)
        spec = load_spec(desc["spec"])
        method = str(card["method"])
        if table.has(method, needs_model=True) and scenario.system is None:
            # refused here, not by the model's build: a hybrid's step.onnx holds an f and h of its
            # own, which a card naming no model would have it serve unchecked
            raise StartupError(
                f"checkpoint {p.checkpoint}: a {method} model runs the system's f and h, but its card's spec "
                "names no model: retrain it on a recording whose spec names one (model: in the spec)"
            )
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
