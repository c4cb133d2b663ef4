"""Estimator node: one method, updated once per observation message, B = 1.

    ros2 run neural_estimator estimator --ros-args -p method:=ukf -p scenario:=lorenz96
    python -m neural_estimator.nodes.estimator_node --ros-args -p method:=ukf   # without ros2

Subscribes ``observation`` (raw CDR, sensor_msgs/JointState); publishes ``estimates/<method>`` and,
where the method has one, ``estimates/<method>/covariance`` with the observation's stamp and
identity (header.frame_id = ``frame_id``); the standard outputs of
:mod:`neural_estimator.nodes.outputs` by parameter (where the scenario declares a pose,
``Scenario.pose_states``: ``<output>/odometry`` nav_msgs/Odometry and/or ``<output>/pose``
PoseWithCovarianceStamped with the method's covariance; ``<output>/state`` for every method;
optional ``/tf``); ``/diagnostics`` every ``diagnostics_period`` s (with the observation input's
frequency and staleness, :mod:`neural_estimator.nodes.diagnostics`); service ``~/reset``
(std_srvs/Trigger) and topic ``set_pose`` (PoseWithCovarianceStamped, filters).

Nothing lost when started by hand: the observation subscription is created when the first
publisher of the topic appears, with that publisher's durability (transient_local when every
publisher offers it, like ``ros2 bag record``), so an estimator started after the simulator still
receives the run from its first step out of the simulator's history. Reliability is the
``observation_qos`` parameter: ``reliable`` (default) or ``sensor_data`` (best effort, matches any
publisher, e.g. a driver's sensor-data QoS). Estimate publishers are reliable + transient_local
with a history bounded in messages (``history_depth``) and in memory (``history_mb``), so a late
recorder or ``ros2 topic echo --qos-durability transient_local`` gets the start of the stream.
Timers run on the steady clock, so ``use_sim_time`` without ``/clock`` silences nothing.
The per-message work is :class:`neural_estimator.stream.online.OnlineEstimator` (the same code as offline
replay); this node only wires it to topics. Parameters: ``params/estimator.yaml``.

Staying current. Each wake-up of the executor takes every observation waiting in the subscription
queue (``drain``) and steps them in arrival order, publishing every estimate, so the executor's
per-wake-up cost is paid once per backlog, not once per message. Diagnostics report how long
observations waited (published -> estimate published, p50/p99), the wake-ups and the largest backlog
taken, and go WARN when the window's p99 wait exceeds ``delay_warn``. The degradation policy, off by
default (``max_delay`` 0: every observation is stepped however late, as replay would): with
``max_delay`` > 0, when the oldest waiting observation was published longer ago than that, only the
newest is stepped; the older ones are dropped and counted (``late observations dropped``, WARN), and
the estimator meets the hole as lost observations (predict-only steps within ``max_gap`` /
``max_gap_seconds``, else a restart from the prior, both counted).

A message that cannot be used (wrong width or names, NaN control, empty, unparsable, larger than any valid one) is
logged (throttled), counted in the diagnostics and dropped; the node never stops on one. No single message moves the
stream: a jump in trajectory or step (or stamps that go back, a restarted publisher) is held until the next message
confirms it (``confirm``) or the stream falls silent (``quarantine_seconds``; :mod:`neural_estimator.stream.online`).
Diagnostics are WARN whenever messages are dropped, skipped, held or the node is busy more than 90 % of the time. An
unknown method, scenario or a missing checkpoint is one fatal line at start-up and exit status 1.
"""

from __future__ import annotations

import sys
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.clock import Clock, ClockType
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import String
from std_srvs.srv import Trigger

from neural_estimator.stream import messages as MSG
from neural_estimator.bags.errors import MessageError
from neural_estimator.methods import table
from neural_estimator.methods.registry import EstimatorError, check_method
from neural_estimator.nodes.common import (
    ExitStatusNode,
    StartupError,
    build_scenario,
    declare_params,
    executor_choice,
    latched_qos,
    load_plugins,
    peek_param,
    run_node,
    stream_qos,
    trim_heap,
    warn_throttled,
)
from neural_estimator.nodes.diagnostics import InputDiagnosticsParams, hardware_id, status_message
from neural_estimator.nodes.estimator_stats import EstimatorStats, diagnostic_values, health, stats_summary
from neural_estimator.nodes.heap_trace import HeapTrace
from neural_estimator.nodes.outputs import OutputParams, SetPose
from neural_estimator.nodes.estimator_params import EstimatorParams
from neural_estimator.nodes.estimator_setup import (
    build_online,
    checked_method,
    model_note,
    publish_result,
    standard_outputs,
)
from neural_estimator.stream.online import OnlineEstimator
from neural_estimator.serving.card import recorded_data_checkpoint

EARLY_MAX_BYTES = 1 << 20  # an observation kept while waiting for the scenario (width unknown yet): 1 MiB


class EstimatorNode(ExitStatusNode):
    def __init__(self, node_name: str = "estimator") -> None:
        super().__init__(node_name)
        self.setup()

    def setup(self) -> None:
        """Declare the parameters, build the scenario's estimator (or wait for the scenario), wire the topics."""
        self.p = p = declare_params(self, EstimatorParams)
        self.po = declare_params(self, OutputParams)
        self.pd = declare_params(self, InputDiagnosticsParams)
        self.method = checked_method(p)
        load_plugins(p.plugins)
        self.online: OnlineEstimator | None = None
        self.out_topic = p.output_topic or MSG.estimate_topic(self.method)
        self.pub_est = None  # created with the scenario: their depth depends on the message size
        self.pub_cov = None  # (and a covariance topic that never carries a message would keep a
        self.outputs = None  # recorder waiting for it)
        self.obs_topic = self.resolve_topic_name(p.observation_topic)
        self.sub_obs = None  # created when the topic's first publisher appears (see the docstring)
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._sim_time_warned = False
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.stats = EstimatorStats()
        self.heap = HeapTrace(after=p.history_depth)
        self.input_monitor = self.pd.monitor(self.obs_topic, time.monotonic())
        self.set_pose = SetPose(self, self.po.set_pose_topic, lambda: self.online, p.frame_id)
        self._last_log: dict[str, float] = {}
        self._foreign: set[str] = set()
        self._early: list[bytes] = []
        self._run_start: int | None = None  # start_ns of the announced run (a new one = a restarted publisher)
        if p.scenario:
            self._build(build_scenario(p.scenario, p.set, preset=p.preset))
        else:
            self.get_logger().info(f"waiting for the scenario on '{p.scenario_topic}'")
        self.sub_scenario = self.create_subscription(
            String, p.scenario_topic, self._on_scenario, latched_qos(), raw=True
        )
        self.srv_reset = self.create_service(Trigger, "~/reset", self._on_reset)
        # steady clock: with use_sim_time and no /clock, ROS-clock timers would never fire
        self.timer = self.create_timer(p.diagnostics_period, self._on_diagnostics_timer, clock=self._steady)
        self._last_diagnostics = time.monotonic()
        self.discovery = self.create_timer(0.1, self._subscribe_when_published, clock=self._steady)
        self.quarantine = self.create_timer(0.1, self._on_quarantine, clock=self._steady)
        self._subscribe_when_published()

    def _subscribe_when_published(self) -> None:
        """Create the observation subscription once a JointState publisher exists, with its durability."""
        pubs = [i for i in self.get_publishers_info_by_topic(self.obs_topic) if i.topic_type == MSG.JOINT_STATE]
        p = self.p
        if p.observation_qos == "reliable":
            best_effort = [i for i in pubs if i.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT]
            for i in best_effort:
                self._warn(
                    "besteffort",
                    f"'{self.obs_topic}' has a best-effort publisher ({i.node_name}): it cannot "
                    "reach a reliable subscription; start with -p observation_qos:=sensor_data",
                )
        if self.sub_obs is not None or not pubs:
            return
        transient = all(i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for i in pubs)
        qos = QoSProfile(
            depth=max(1, p.queue_depth),
            reliability=ReliabilityPolicy.RELIABLE
            if p.observation_qos == "reliable"
            else ReliabilityPolicy.BEST_EFFORT,
            durability=DurabilityPolicy.TRANSIENT_LOCAL if transient else DurabilityPolicy.VOLATILE,
        )
        # rclpy 7.1's EventsExecutor cannot call a callback that takes the message info (SystemError):
        # under it the callback takes the message only (see _on_observations)
        callback = self._on_observations if executor_choice() == "events" else self._on_observations_with_info
        self.sub_obs = self.create_subscription(JointState, p.observation_topic, callback, qos, raw=True)
        self.get_logger().info(
            f"subscribed to '{self.obs_topic}' ({p.observation_qos}, "
            f"{'transient_local: the publishers history is received' if transient else 'volatile'})"
        )

    # ---- setup -------------------------------------------------------------------------------------
    def _build(self, scenario, horizon: int | None = None) -> None:
        p = self.p
        est, self.online = build_online(self.method, scenario, p, horizon)
        dx = scenario.dx
        self.depths = {"estimates": self._depth(dx), "covariance": self._depth(dx * dx)}
        self.pub_est = self.create_publisher(JointState, self.out_topic, stream_qos(self.depths["estimates"]))
        if self.online.publish_covariance:
            self.pub_cov = self.create_publisher(
                JointState, f"{self.out_topic}/{MSG.COVARIANCE_SUFFIX}", stream_qos(self.depths["covariance"])
            )
        state_qos = stream_qos(self._depth(dx * (dx + 1)))
        self.outputs = standard_outputs(
            self, self.po, p, self.out_topic, stream_qos(self._depth(90)), scenario, state_qos=state_qos
        )
        self.get_logger().info(
            f"{self.method} on {scenario.name} (dx={scenario.dx}, dy={scenario.dy}, du={scenario.du}): "
            f"'{self.resolve_topic_name(p.observation_topic)}' -> "
            f"'{self.pub_est.topic_name}'"
            + (" + covariance" if self.online.publish_covariance else "")
            + self.outputs.describe()
            + f" (history {self.depths['estimates']}"
            + (f"/{self.depths['covariance']}" if self.pub_cov else "")
            + " msgs)"
            + model_note(self.method, p)
            + (
                "; served by ONNX Runtime without torch"
                if table.has(self.method, uses_torch=True) and not sys.modules.get("torch")
                else ""
            )
        )
        if getattr(est, "context", 0):
            how = (
                f"{est.context_copies} copies, {est.context_copies}x the compute per message"
                if getattr(est, "context_by_copies", True)
                else "its attention window"
            )
            self.get_logger().info(f"{self.method}: context bounded to {est.context} steps ({how})")
        untrained = getattr(est, "untrained_steps", 0)
        if untrained:
            self.get_logger().warning(
                f"{self.method}: the first {untrained} estimates of every trajectory are steps this model's "
                "training loss skipped (the paper's warm-up); they can be far off, and the evaluator does not "
                "score them"
            )

    def _depth(self, n_values: int) -> int:
        """History depth of a stream of ``n_values`` labelled float64s within ``history_mb``
        (per value: 8 bytes in CDR plus its label and the history's bookkeeping, ~24 bytes)."""
        size = 200 + 32 * n_values
        return max(1, min(self.p.history_depth, int(self.p.history_mb * 2**20 // size)))

    def _on_scenario(self, raw: bytes) -> None:
        try:
            desc = MSG.decode_scenario(raw)
        except MessageError as exc:
            self._warn("scenario", f"ignoring a scenario message: {exc}")
            return
        run = desc.get("run") if isinstance(desc.get("run"), dict) else {}
        start, horizon = run.get("start_ns"), run.get("horizon")
        horizon = horizon if isinstance(horizon, int) and 0 < horizon < 2**53 else None
        if self.online is None:
            from neural_estimator.scenarios import ScenarioError, scenario_from_description

            try:
                self._build(scenario_from_description(desc), horizon)
            except (StartupError, ScenarioError, KeyError, TypeError, ValueError) as exc:
                # anyone on the domain can publish a scenario: a bad one is refused, the node keeps waiting
                self._warn("scenario", f"cannot serve the announced scenario, ignored: {exc}")
                return
            self._run_start = start
            early, self._early = self._early, []
            for raw_obs in early:
                self._on_observation(raw_obs)
            return
        if start is not None and start != self._run_start:  # the publisher restarted: a new run
            if self._run_start is not None:  # the stream switches once the new run's messages confirm it
                self.get_logger().warning(  # (a forged announcement alone resets nothing)
                    f"a new run was announced (start_ns {self._run_start} -> {start}): the publisher "
                    "restarted; its stream starts fresh once its first messages confirm each other"
                )
            self._run_start = start
            self.online.horizon = horizon
        if (
            desc.get("scenario") != self.online.scenario.name
            or desc.get("config") != self.online.scenario.describe()["config"]
        ):
            self._warn(
                "mismatch",
                f"the announced scenario {desc.get('scenario')!r} differs from the one this node "
                f"serves ({self.online.scenario.name!r} with its constants); estimates may be wrong",
            )

    # ---- per wake-up ------------------------------------------------------------------------------
    def _on_observations_with_info(self, raw: bytes, info: dict) -> None:
        self._on_observations(raw, info.get("source_timestamp", 0))

    def _on_observations(self, raw: bytes, sent_ns: int = 0) -> None:
        """Subscription callback: this observation and every other one waiting in the queue (``drain``),
        stepped in arrival order (one reliable publisher: time order, and the order replay uses).

        Staying current: one wake-up of the executor costs more than an EKF step, so a node woken once
        per message falls behind at kilohertz rates and its queue grows; taking the whole queue at once
        pays that cost once per backlog. Every taken observation is stepped and its estimate published.
        When the oldest one was published more than ``max_delay`` s ago, the node is behind: only the
        newest is stepped, the older ones are dropped and counted (``late_dropped``), and the estimator
        meets them as lost observations (the gap rule: predict-only steps or a restart, both counted).

        ``sent_ns`` is the observation's DDS source timestamp where the executor passes the message
        info (the single-threaded executor); the events executor passes the message only, and the
        delivered observation's publish time is then taken as that of the next one waiting (it was
        published before it), or as now when none waits: its wait is under-counted by at most one
        inter-arrival time. The messages the node takes itself carry their own timestamps.
        """
        batch = [(raw, sent_ns)]
        sub = self.sub_obs
        if self.p.drain and sub is not None:
            limit = max(1, self.p.queue_depth)
            with sub.handle:
                while len(batch) < limit:
                    taken = sub.handle.take_message(sub.msg_type, True)
                    if taken is None:
                        break
                    batch.append((taken[0], taken[1].get("source_timestamp", 0)))
        if not sent_ns:
            batch[0] = (raw, batch[1][1] if len(batch) > 1 and batch[1][1] else time.time_ns())
        s = self.stats
        s.wakeups += 1
        s.max_batch = max(s.max_batch, len(batch))
        now = time.time_ns()
        if self.p.max_delay > 0 and len(batch) > 1 and now - batch[0][1] > self.p.max_delay * 1e9:
            s.late_dropped += len(batch) - 1
            self._warn(
                "behind",
                f"behind: {len(batch) - 1} observations waited longer than max_delay={self.p.max_delay:g} s; "
                "dropped, the newest is stepped",
            )
            batch = batch[-1:]
        for raw_obs, sent_ns in batch:
            self._on_observation(raw_obs, {"source_timestamp": sent_ns})
            if sent_ns:  # observation published -> its estimate published (or the message dropped)
                s.delay.append((time.time_ns() - sent_ns) * 1e-9)
        # A node that never idles gets its timers late (the events executor serves the queued
        # messages first: a busy GRU published 78 diagnostics in 1,000 s of a soak); when the
        # timer is overdue by half a period, the diagnostics go out from here instead.
        if time.monotonic() - self._last_diagnostics >= 1.5 * self.p.diagnostics_period:
            self._on_diagnostics()
        # the heap trim's timer starves the same way (a GRU behind for 30 minutes never ran it,
        # 18 MiB free heap resident): overdue by half a period, it runs from here
        trim = getattr(self, "heap_trim", None)  # set by run_node (nodes/common.py start_heap_trim)
        if trim is not None and trim.overdue(time.monotonic()):
            trim()

    def _on_diagnostics_timer(self) -> None:
        if time.monotonic() - self._last_diagnostics >= 0.5 * self.p.diagnostics_period:
            self._on_diagnostics()  # not twice in a period when the message path just published

    # ---- per message -------------------------------------------------------------------------------
    def _on_observation(self, raw: bytes, info=None) -> None:
        t0 = time.perf_counter()
        self.input_monitor.tick(time.monotonic())
        if info is not None and info.get("source_timestamp"):  # how long it waited (same clock, same machine)
            self.stats.waited(max(0.0, (time.time_ns() - info["source_timestamp"]) * 1e-9))
        if self.online is None:  # kept until the scenario arrives (messages on two topics race)
            if len(raw) > EARLY_MAX_BYTES:
                self.stats.oversize += 1
                self._warn(
                    "oversize",
                    f"observation of {len(raw)} bytes before the scenario dropped unread "
                    f"(bound {EARLY_MAX_BYTES} bytes while the width is unknown)",
                )
                return
            if len(self._early) < self.p.queue_depth:
                self._early.append(bytes(raw))
            else:
                self.stats.early += 1
                self._warn("early", f"{self.p.queue_depth} observations wait for the scenario: dropping more")
            return
        if len(raw) > self.online.max_message_bytes:  # dropped unread; its memory freed at once
            self.stats.oversize += 1
            self._warn(
                "oversize",
                f"observation of {len(raw)} bytes dropped unread: larger than any valid one of this stream "
                f"(bound {self.online.max_message_bytes} bytes); {self.stats.oversize} so far",
            )
            del raw
            trim_heap()
            return
        try:
            results = self.online.feed(raw)
        except MessageError as exc:
            self.stats.bad += 1
            self._warn("bad", f"bad observation dropped: {exc}")
            return
        except Exception as exc:  # a failure inside a method must not take the node down
            self._method_failed(exc)
            return
        self._handle(results, t0)

    def _on_quarantine(self) -> None:
        """A held jump that nothing confirmed or refuted for ``quarantine_seconds`` is accepted."""
        if self.online is None or not self.online.held:
            return
        t0 = time.perf_counter()
        try:
            results = self.online.poll()
        except Exception as exc:  # a failure inside a method must not take the node down
            self._method_failed(exc)
            return
        self._handle(results, t0)

    def _method_failed(self, exc: Exception) -> None:
        self.stats.errors += 1
        self.online.reset()
        self.get_logger().error(
            f"{self.method} failed on an observation ({exc!r}); the stream restarts from the prior "
            "at the next observation"
        )

    def _handle(self, results, t0: float) -> None:
        """Publish the estimates of ``results`` (see OnlineEstimator.feed), count and log the rest."""
        s = self.stats
        for res in results:
            if res.status == "held":
                s.quarantined += 1
                self._warn(
                    "held",
                    f"observation {res.trajectory}/{res.step} jumps from the current stream "
                    f"({self.online.trajectory}/{self.online.step}): held until the next messages confirm it",
                )
                continue
            if res.status != "estimated":
                s.skipped[res.status] += 1
                self._warn(
                    res.status,
                    f"{res.status} observation (trajectory {res.trajectory}, step {res.step}; "
                    f"current stream {self.online.trajectory}/{self.online.step}) dropped; "
                    f"{s.skipped[res.status]} so far",
                )
                continue
            self._publish(res)
            s.estimated += 1
            s.resets += res.reset
            s.gap_steps += res.filled
            s.missed += res.missed
            s.restarts += res.restarted
            s.nonfinite += res.nonfinite
            s.diverged = res.diverged or not np.all(np.isfinite(res.x_hat))
            s.position = (res.trajectory, res.step)
            if res.new_run:
                s.publisher_restarts += 1
                self.get_logger().warning(
                    f"the observation stamps went back at {res.trajectory}/{res.step}, confirmed by the next "
                    "message: the publisher restarted; a fresh stream starts from the prior"
                )
            if res.filled:
                self._warn(
                    "gap",
                    f"{res.filled} observation(s) missing before step {res.step} of trajectory "
                    f"{res.trajectory}: bridged by predict-only steps",
                )
            if res.restarted:
                self._warn(
                    "restart",
                    f"gap before step {res.step} longer than max_gap={self.p.max_gap} steps or "
                    f"max_gap_seconds={self.p.max_gap_seconds:g} s: restarted from the prior",
                )
            if res.nonfinite:
                self._warn("nonfinite", f"observation {res.trajectory}/{res.step} has NaN/inf: predict only")
        s.record(time.perf_counter() - t0)

    def _publish(self, res) -> None:
        publish_result(res, self.pub_est, self.pub_cov, self.outputs)
        self.set_pose.last = res.x_hat

    def _on_reset(self, request, response):
        if self.online is not None:
            self.online.reset()
        self.stats.diverged = False
        self.stats.manual_resets += 1
        response.success = True
        response.message = "reset: the next observation starts a new stream from the prior"
        self.get_logger().info(response.message)
        return response

    # ---- diagnostics -------------------------------------------------------------------------------
    def _on_diagnostics(self) -> None:
        self._last_diagnostics = time.monotonic()
        self._check_foreign_publishers()
        if (
            not self._sim_time_warned
            and self.get_parameter("use_sim_time").value
            and not self.count_publishers("/clock")
        ):
            self._sim_time_warned = True
            self.get_logger().warning(
                "use_sim_time is true but nothing publishes /clock: the ROS clock stands "
                "still (timers here use the steady clock; start the simulator or player "
                "with -p publish_clock:=true)"
            )
        window = self.stats.window(time.monotonic())
        self.heap.tick(self.stats.estimated)  # a baseline once the histories are full (-X tracemalloc only)
        level, problems = health(
            self.stats, window, waiting=self.online is None, foreign=self._foreign, delay_warn=self.p.delay_warn
        )
        status = DiagnosticStatus()
        status.name = f"{self.get_fully_qualified_name()}: {self.method} estimator"
        status.hardware_id = hardware_id(self.get_fully_qualified_name(), self.method)
        status.level = (DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR)[level]
        status.message = "; ".join(problems) if problems else "ok"
        values = diagnostic_values(self.stats, window, self.method)
        if model_note(self.method, self.p):  # beside the run's identity: the model it was told
            values["model_set"] = self.p.model_set.strip()
        status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
        msg = DiagnosticArray()
        msg.header.stamp = self.get_clock().now().to_msg()
        inputs = self.input_monitor.status(time.monotonic())
        msg.status = [status, status_message(inputs, status.name, status.hardware_id, DiagnosticStatus, KeyValue)]
        self.pub_diag.publish(msg)

    def _check_foreign_publishers(self) -> None:
        """Publishers of another type on the observation topic never reach this node (DDS does not
        match them): say so instead of waiting silently."""
        for info in self.get_publishers_info_by_topic(self.obs_topic):
            if info.topic_type != MSG.JOINT_STATE:
                key = f"{info.node_namespace.rstrip('/')}/{info.node_name} ({info.topic_type})"
                if key not in self._foreign:
                    self._foreign.add(key)
                    self.get_logger().error(
                        f"'{self.obs_topic}' has a publisher of the wrong type: {key}; "
                        f"expected {MSG.JOINT_STATE}. Its messages cannot reach this node."
                    )

    def on_shutdown(self) -> int:
        if self.p.stats_file:
            import json
            from pathlib import Path

            path = Path(self.p.stats_file)
            path.parent.mkdir(parents=True, exist_ok=True)
            summary = stats_summary(self.stats, self.get_fully_qualified_name(), self.method)
            summary["heap_growth"] = self.heap.report(self.stats.estimated)
            trim = getattr(self, "heap_trim", None)  # set by run_node (nodes/common.py start_heap_trim)
            summary["heap_trim"] = trim.report() if trim is not None else None
            path.write_text(json.dumps(summary, indent=1))
        return self.exit_code

    def _warn(self, kind: str, text: str) -> None:
        warn_throttled(self, self._last_log, kind, text, self.p.log_throttle)


def _make_node() -> ExitStatusNode:
    """The estimator node, or, when ``checkpoint`` is a model trained on recorded data (its card holds a
    spec, docs/robot.md), the robot estimator on the spec's own topics: a recorded-data model
    needs no scenario.

    One node is made: an :class:`ExitStatusNode` named ``estimator`` (its name and parameter overrides
    resolved by rcl from the command line, remappings and parameter files), whose ``checkpoint`` and
    ``method`` are peeked at (:func:`~neural_estimator.nodes.common.peek_param`); the card is read
    once, and the node becomes the kind it names: its class set, then that class's ``setup``, which
    declares every parameter as the class's fields (those two again)."""
    node = ExitStatusNode("estimator")
    try:
        checkpoint = str(peek_param(node, "checkpoint") or "")
        method = str(peek_param(node, "method") or "")
        read = recorded_data_checkpoint(checkpoint) if checkpoint else None
        if read is not None:
            from neural_estimator.nodes.robot_estimator_node import RobotEstimatorNode

            try:
                wrong = bool(method) and check_method(method) != read.card.get("method")
            except EstimatorError as exc:
                raise StartupError(str(exc)) from None
            if wrong:
                raise StartupError(
                    f"parameter method is {method!r} but {checkpoint} holds a {read.card['method']} model"
                )
            node.__class__ = RobotEstimatorNode
            node.setup(read)
        else:
            node.__class__ = EstimatorNode
            node.setup()
    except BaseException:
        node.destroy_node()
        raise
    return node


def main(args: list[str] | None = None) -> int:
    return run_node(_make_node, "estimator", args)


if __name__ == "__main__":
    sys.exit(main())
