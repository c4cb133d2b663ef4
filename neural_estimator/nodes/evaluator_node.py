"""Evaluator node: records a run into one MCAP bag, then scores every estimator from that file.

    ros2 run neural_estimator evaluator --ros-args -p output:=runs/l96.mcap -p methods:="['ekf','ukf']"
    python -m neural_estimator.nodes.evaluator_node --ros-args -p output:=runs/l96.mcap

Recording: ``scenario``, ``run_status``, ``observation``, ``ground_truth`` and every
``estimates/<method>`` (and ``/covariance``; ``/odometry``, ``/pose`` and ``/state`` recorded, not
scored) topic in the node's namespace, found by polling the
graph every ``discovery_period`` s (plus ``topics``), from raw subscriptions: the bytes on the wire
go to the file unchanged (rclpy's serialize_message would pad empty sequences with junk that
rosbags rejects). Like ``ros2 bag record`` it subscribes with the QoS the publishers offer
(transient_local when they all offer it, so the history of a stream that started before discovery
is delivered), logs receive times, and stores the offered profiles in the channel metadata.

End of a run: after ``run_status`` "complete", when every expected stream holds as many messages
as the run announced (or when none of those streams received anything for ``completion_timeout`` s:
messages on other recorded topics, such as a periodic ``/diagnostics``, are not progress; with no estimate
stream discovered yet, it waits that long for one), or, for a source without ``run_status`` (a
foreign bag played, your own nodes), when no stream message arrived for ``idle_timeout`` s, the
bag is closed, the paper's metrics are
computed offline from it (:func:`neural_estimator.evaluation.bag_report.evaluate_bag`), the table is printed
and ``<bag>.metrics.md``, ``.metrics.json`` and ``.rmse.png`` are written beside the bag; exit
status 0 (1 if no metrics could be computed). After the table it prints, per stream, the messages
received and lost and why (malformed, outside the announced run, duplicates, over ``max_message_mb``,
which are dropped unrecorded). Two publishers of one run (two simulators on one topic, or a
restarted one) are detected in-band (:mod:`neural_estimator.nodes.run_identity`: each observation's
stamp names its run's start) and reported: a warning when the second run appears, and a
"MIXED RUNS" line after the table with the count per run. A full or read-only disk stops the
recording with one error line, closes the bag as far as possible and exits 1. Ctrl-C / SIGTERM
close the bag properly too. A bag without ``/scenario`` is scored with the ``scenario`` (+ ``set``,
``plugins``) parameters. Timers run on the steady clock, so ``use_sim_time:=true`` records like
the default.
Parameters: ``params/evaluator.yaml``.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from pathlib import Path
from datetime import datetime

from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from neural_estimator.stream import messages as MSG
from neural_estimator.bags.errors import BagError, MessageError
from neural_estimator.bags.writer import DEFAULT_CHUNK_SIZE, BagWriter
from neural_estimator.metrics import EVALUATION_WARMUP
from neural_estimator.nodes.outputs import is_output_topic
from neural_estimator.nodes.run_identity import RunIdentity
from neural_estimator.nodes.common import (
    ExitStatusNode,
    StartupError,
    declare_params,
    param,
    request_shutdown,
    run_node,
    subscribable_class,
    to_bag_qos,
    trim_heap,
    warn_throttled,
)


@dataclasses.dataclass(frozen=True)
class EvaluatorParams:
    """Parameters of the evaluator node (documented in params/evaluator.yaml)."""

    output: str = param("", "bag to write (.mcap); empty = runs/run-<date>-<time>.mcap")
    overwrite: bool = param(False, "replace an existing output file")
    methods: tuple[str, ...] = param(
        (), "estimate streams that must be complete before the end; empty = all discovered"
    )
    topics: tuple[str, ...] = param((), "extra topics to record (names relative to the namespace, or absolute)")
    discovery_period: float = param(0.25, "seconds between graph scans for new topics")
    record_period: float = param(
        0.01,
        "seconds between two drains of the recorded topics; each takes every waiting message of every topic. "
        "Receive times are the DDS reception stamps, so the period adds no error to them; it only sets how long "
        "a message waits in its subscription queue (at most queue_depth)",
    )
    queue_depth: int = param(10000, "subscription depth (KEEP_LAST): messages buffered while the node is busy")
    completion_timeout: float = param(
        30.0,
        "after 'complete': give up on lagging streams when no scored stream receives anything for this many s",
    )
    chunk_size: int = param(DEFAULT_CHUNK_SIZE, "uncompressed bytes per zstd chunk (what a crash can lose)")
    max_message_mb: float = param(
        16.0, "messages larger than this (MiB) are dropped unrecorded, counted and logged (0 = no bound)"
    )
    idle_timeout: float = param(
        10.0,
        "without run_status 'complete': end when no stream message arrived for this "
        "many seconds after the first (0 = never)",
    )
    scenario: str = param(
        "", "scenario to score a run whose source publishes no 'scenario' topic ('' = from the topic)"
    )
    set: tuple[str, ...] = param((), "constants of that scenario as name=value")
    preset: str = param("", "named constants of that scenario, applied before set (empty = the defaults; e.g. v3)")
    plugins: tuple[str, ...] = param((), "Python files registering user scenarios")
    compute_metrics: bool = param(True, "compute and write the metrics when the run ends")
    spec: str = param(
        "",
        "a recorded-data spec (YAML): score every estimates/<method> stream against the spec's ground truth "
        "(record its topics with 'topics'); '' = the scenario's ground_truth stream",
    )
    spec_length: int = param(200, "with spec: steps per scored trajectory")
    warmup: int = param(
        EVALUATION_WARMUP,
        "leading steps of every trajectory not scored (this project's choice: the paper states its 10-step warm-up "
        "for the training loss only; 0 = every step; a run no longer than that is scored on every step and the "
        "table says so)",
    )
    exit_when_done: bool = param(True, "shut down when the run is evaluated")
    starts: tuple[str, ...] = param(
        (),
        "how the recorded filters started, as method=mode (prior, observation): the table marks the departures "
        "from the paper's prior start and marks expected failures by the start; absent = prior",
    )


class EvaluatorNode(ExitStatusNode):
    def __init__(self) -> None:
        super().__init__("evaluator")
        self.p = p = declare_params(self, EvaluatorParams)
        if p.warmup < 0:
            raise StartupError(f"warmup must be >= 0 (steps not scored), got {p.warmup}")
        if not 0 < p.record_period <= 1:
            raise StartupError(f"record_period must be in (0, 1] seconds, got {p.record_period}")
        if p.spec:  # checked now, not when the run ends: a bad spec would otherwise record a run for nothing
            from neural_estimator.robot import SpecError, load_spec

            if p.spec_length < 2:
                raise StartupError(f"spec_length must be at least 2 steps, got {p.spec_length}")
            try:
                load_spec(p.spec)
            except (SpecError, OSError) as exc:
                raise StartupError(f"spec: {exc}") from None
        out = p.output or f"runs/run-{datetime.now():%Y%m%d-%H%M%S}.mcap"
        if Path(out).exists() and not p.overwrite:
            raise StartupError(f"{out}: file exists; pass -p overwrite:=true to replace it")
        try:
            self.bag = BagWriter(out, overwrite=p.overwrite, chunk_size=p.chunk_size).open()
        except BagError as exc:
            raise StartupError(str(exc)) from None
        self.ns = self.get_namespace()
        self.sim_time = bool(self.get_parameter("use_sim_time").value)
        self.extra = {self.resolve_topic_name(t) for t in p.topics}
        self.required_methods = tuple(p.methods)
        self.subs: dict = {}
        self._records: dict = {}  # topic -> its recorder (what one taken message goes through)
        # The subscriptions live on a second node that no executor waits on: a drain timer takes
        # their messages (_drain), so the executor wakes 1 / record_period times a second instead of
        # once per message (at 1 kHz the per-message wake-ups took 63 % of the node's CPU, measured).
        # No global arguments: the topics are subscribed by the absolute names discovery found.
        self._tap = Node(
            f"{self.get_name()}_recorder",
            namespace=self.ns,
            context=self.context,
            use_global_arguments=False,
            start_parameter_services=False,
        )
        self.counts: dict[str, int] = {}
        self.oversize: dict[str, int] = {}  # messages dropped unrecorded for their size, per topic
        self.unrecorded = 0  # messages that arrived after a write failure
        self.write_error: str | None = None
        self._max_bytes = int(p.max_message_mb * 2**20) if p.max_message_mb > 0 else 0
        self._last_log: dict[str, float] = {}
        self._refused: set[str] = set()
        self.expected: int | None = None
        self.complete_at: float | None = None
        self._progress = (0, time.monotonic())  # (messages recorded, when that number last changed)
        self.identity = RunIdentity()  # the announced run; observations of another one (two publishers)
        self.closed = False
        self._closing = False
        self.description = None
        from neural_estimator.nodes.common import build_scenario, load_plugins

        load_plugins(p.plugins)  # also for scoring a recorded plugin scenario
        if p.scenario:
            self.description = build_scenario(p.scenario, p.set, preset=p.preset).describe()
        self._last_stream = None  # monotonic time of the last observation / truth / estimate message
        self.get_logger().info(f"recording to {self.bag.path}")
        # steady clock: with use_sim_time and no /clock, a ROS-clock timer would never fire
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.timer = self.create_timer(p.discovery_period, self._tick, clock=steady)
        self.drain_timer = self.create_timer(p.record_period, self._drain, clock=steady)
        self._tick()

    # ---- discovery -----------------------------------------------------------------------------------
    def _tick(self) -> None:
        if self.closed:
            return
        self._discover()
        self._check_done()

    def _discover(self) -> None:
        for name, types in self.get_topic_names_and_types():
            if name in self.subs:
                continue
            role = MSG.topic_role(name, self.ns)
            if role is None and name not in self.extra and not is_output_topic(name, self.ns):
                continue
            pubs = self.get_publishers_info_by_topic(name)
            if not pubs:
                continue
            if role is not None:
                want = MSG.STRING if role.kind in (MSG.SCENARIO, MSG.RUN_STATUS) else MSG.JOINT_STATE
                wrong = sorted({i.topic_type for i in pubs if i.topic_type != want})
                if wrong and name not in self._refused:
                    self._refused.add(name)
                    self.get_logger().error(
                        f"'{name}' has publishers of type {', '.join(wrong)}; recording only {want}"
                    )
                pubs = [i for i in pubs if i.topic_type == want]
                if not pubs:
                    continue
            msgtype = pubs[0].topic_type
            offered = [i.qos_profile for i in pubs]
            qos = QoSProfile(
                depth=self.p.queue_depth,
                reliability=ReliabilityPolicy.RELIABLE
                if all(q.reliability == ReliabilityPolicy.RELIABLE for q in offered)
                else ReliabilityPolicy.BEST_EFFORT,
                durability=DurabilityPolicy.TRANSIENT_LOCAL
                if all(q.durability == DurabilityPolicy.TRANSIENT_LOCAL for q in offered)
                else DurabilityPolicy.VOLATILE,
            )
            cls = subscribable_class(self, name, msgtype, self._refused, "recorded")
            if cls is None:
                continue
            self.bag.add_topic(name, msgtype, qos=[to_bag_qos(q) for q in offered])
            self.counts[name] = 0
            # the callback never runs: no executor waits on the tap node; _drain takes the messages
            self.subs[name] = self._tap.create_subscription(cls, name, lambda _msg: None, qos, raw=True)
            self._records[name] = self._recorder(name, role)
            self.get_logger().info(f"recording '{name}' ({msgtype})")

    def _recorder(self, name: str, role: MSG.TopicRole | None):
        is_status = role is not None and role.kind == MSG.RUN_STATUS
        is_stream = role is not None and role.kind not in (MSG.RUN_STATUS, MSG.SCENARIO)
        is_scenario = role is not None and role.kind == MSG.SCENARIO
        is_observation = role is not None and role.kind == MSG.OBSERVATION

        def record(raw: bytes, info) -> None:
            if self.closed:
                self.unrecorded += self.write_error is not None
                return
            if self._max_bytes and len(raw) > self._max_bytes:
                self.oversize[name] = self.oversize.get(name, 0) + 1
                self._warn(
                    "oversize",
                    f"'{name}': a message of {len(raw)} bytes dropped unrecorded (bound max_message_mb="
                    f"{self.p.max_message_mb:g}); {sum(self.oversize.values())} so far",
                )
                del raw
                trim_heap()
                return
            t = self.get_clock().now().nanoseconds if self.sim_time else 0
            try:
                # like `ros2 bag record --use-sim-time`: log times on the sim clock (receipt time until /clock)
                self.bag.write(name, t or info["received_timestamp"], raw, publish_time_ns=info["source_timestamp"])
            except BagError as exc:  # disk full, read-only: stop recording, close what can be closed
                self._write_failed(str(exc))
                return
            self.counts[name] += 1
            if is_stream:
                self._last_stream = time.monotonic()
            if is_status:
                self._on_status(raw)
            elif is_scenario or is_observation:
                mixed = (self.identity.on_scenario if is_scenario else self.identity.on_observation)(raw)
                if mixed:
                    self.get_logger().warning(mixed)

        return record

    def _drain(self) -> None:
        """Every message waiting on every recorded topic, topic by topic (at most queue_depth each)."""
        for name, sub in list(self.subs.items()):
            record = self._records[name]
            with sub.handle:
                for _ in range(self.p.queue_depth):
                    if self.closed:
                        return
                    taken = sub.handle.take_message(sub.msg_type, True)
                    if taken is None:
                        break
                    record(*taken)

    def _on_status(self, raw: bytes) -> None:
        try:
            status = MSG.decode_run_status(raw)
        except MessageError as exc:
            self.get_logger().warning(f"unreadable run_status: {exc}")
            return
        if status["status"] == MSG.STATUS_STARTED:
            self.get_logger().info(
                f"run started: {status.get('trajectories')} trajectories x {status.get('horizon')} steps"
            )
            again = self.identity.on_started()
            if again:
                self.get_logger().warning(again)
        elif status["status"] == MSG.STATUS_COMPLETE:
            messages = status.get("messages", 0)
            if isinstance(messages, bool) or not isinstance(messages, int) or not 0 <= messages < 2**53:
                self.get_logger().warning(
                    f"run_status 'complete' with messages={str(messages)[:40]}: not a count, ignored"
                )
                return
            self.expected = messages
            self.complete_at = time.monotonic()
            self.get_logger().info(f"run complete ({self.expected} observations): waiting for the streams to catch up")

    # ---- end of run -----------------------------------------------------------------------------------
    def _required(self) -> list[str]:
        topic = lambda rel: MSG.resolve_topic(rel, self.ns)  # noqa: E731
        req = [topic(MSG.OBSERVATION)]
        if topic(MSG.GROUND_TRUTH) in self.subs:
            req.append(topic(MSG.GROUND_TRUTH))
        req += [topic(MSG.estimate_topic(m)) for m in self.required_methods]
        req += [
            t
            for t in self.subs
            if MSG.topic_role(t, self.ns) and MSG.topic_role(t, self.ns).kind in ("estimate", "covariance")
        ]
        return sorted(set(req))

    def _check_done(self) -> None:
        if self.complete_at is None or self.expected is None:
            idle = self.p.idle_timeout
            if idle > 0 and self._last_stream is not None and time.monotonic() - self._last_stream > idle:
                self.get_logger().warning(
                    f"no run_status 'complete' and no stream message for {idle:g} s: ending the recording"
                )
                self._finish()
            return
        required = self._required()
        lagging = {t: self.counts.get(t, 0) for t in required if self.counts.get(t, 0) < self.expected}
        now = time.monotonic()
        # progress is what the scored streams received: a periodic topic recorded beside them
        # (/diagnostics, /tf, the viewers' outputs) would otherwise hold completion_timeout off forever
        total = sum(self.counts.get(t, 0) for t in required)
        if total != self._progress[0]:
            self._progress = (total, now)
        stalled = now - max(self._progress[1], self.complete_at) > self.p.completion_timeout
        if lagging and not stalled:
            return
        no_estimates = not any(
            MSG.topic_role(t, self.ns).kind == "estimate" for t in self.subs if MSG.topic_role(t, self.ns)
        )
        if no_estimates and now - self.complete_at <= self.p.completion_timeout:
            return  # an estimator started after the run still serves it from its history: wait for it
        if lagging:
            self.get_logger().warning(
                f"streams still short of {self.expected} messages and nothing new for {self.p.completion_timeout:g} s: "
                + ", ".join(f"{t} {n}" for t, n in lagging.items())
            )
        self._finish()

    def _write_failed(self, why: str) -> None:
        self.write_error = why
        self.unrecorded += 1
        self.get_logger().error(
            f"recording stopped: {why}; {sum(self.counts.values())} messages recorded so far "
            f"(`neural-estimator recover {self.bag.path} --out FIXED.mcap` reads what reached the disk)"
        )
        self._finish()

    def _warn(self, kind: str, text: str, every: float = 2.0) -> None:
        warn_throttled(self, self._last_log, kind, text, every)

    def _close(self) -> None:
        if self.closed or self._closing:
            return
        self._closing = True  # a write failure inside the last drain comes back here: once is enough
        if self.write_error is None:
            try:
                self._drain()  # what arrived since the last drain goes into the bag too
            except Exception:  # the context may already be shut down (Ctrl-C): nothing more to take
                pass
        self.closed = True
        for sub in self.subs.values():
            try:
                self._tap.destroy_subscription(sub)
            except Exception:  # the context may already be shut down (Ctrl-C): nothing to release
                pass
        self.subs.clear()
        self._records.clear()
        try:
            self._tap.destroy_node()
        except Exception:
            pass
        total = sum(self.counts.values())
        starts = dict(item.split("=", 1) for item in self.p.starts if "=" in item)
        if starts:  # how the filters started, so that `metrics` on this bag marks them as this node does
            from neural_estimator.evaluation.bag_report import STARTS_METADATA

            self.bag.metadata[STARTS_METADATA] = starts
        try:
            self.bag.close()
        except BagError as exc:
            if self.write_error is None:
                self.get_logger().error(f"{exc}; {total} messages recorded before it")
            self.write_error = self.write_error or str(exc)
            return
        self.get_logger().info(f"wrote {self.bag.path} ({total} messages on {len(self.counts)} topics)")

    def _finish(self) -> None:
        self._close()
        code = 0
        if self.write_error is not None:
            code = 1  # no metrics from a bag that could not be finished
        elif self.p.compute_metrics:
            code = self._evaluate()
        if self.p.exit_when_done:
            request_shutdown(self, code)

    def _evaluate(self) -> int:
        from neural_estimator.evaluation.bag_report import evaluate_bag, write_report
        from neural_estimator.metrics import MetricsError

        if self.p.spec:
            return self._evaluate_spec()
        try:
            report = evaluate_bag(
                self.bag.path,
                namespace=self.ns,
                description=self.description,
                warmup=self.p.warmup,
                short_runs="score_all",
                starts=dict(item.split("=", 1) for item in self.p.starts if "=" in item),
            )
            paths = write_report(report)
        except (BagError, MetricsError) as exc:
            self.get_logger().error(f"no metrics from {self.bag.path}: {exc}")
            return 1
        except Exception as exc:  # what the topics carried must not take the node down: the bag is written
            self.get_logger().error(f"no metrics from {self.bag.path}: {type(exc).__name__}: {exc}")
            return 1
        print(report.summary(), end="", flush=True)
        print(report.losses(expected=self.expected, dropped=self._dropped()), end="", flush=True)
        for line in self.identity.report():  # two publishers of one run: the table mixes them
            print(line, flush=True)
        if self.identity.mixed:
            self.get_logger().error(self.identity.report()[0])
        self.get_logger().info("wrote " + ", ".join(str(p) for p in paths.values()))
        return 0

    def _dropped(self) -> dict[str, dict[str, int]]:
        """{stream key: {reason: count}} of what this node itself did not record."""
        out: dict[str, dict[str, int]] = {}
        for topic, n in self.oversize.items():
            role = MSG.topic_role(topic, self.ns)
            if role is not None:
                key = MSG.estimate_topic(role.method) if role.kind == "estimate" else role.kind
                if role.kind == "covariance":
                    key = MSG.covariance_topic(role.method)
                out.setdefault(key, {})["oversize (dropped by the evaluator)"] = n
        return out

    def _evaluate_spec(self) -> int:
        """Score the recorded estimate streams through the spec (recorded-data models: no scenario)."""
        from neural_estimator.metrics import format_reports, to_json
        from neural_estimator.robot import SpecError
        from neural_estimator.robot.score import score_recording

        try:
            warmup = min(self.p.warmup, self.p.spec_length - 1)  # a spec's trajectories have spec_length steps
            reports, truth = score_recording(
                self.bag.path,
                self.p.spec,
                self.p.spec_length,
                namespace=self.ns,
                warmup=warmup,
                length_name="spec_length (-p spec_length:=N)",
            )
        except (BagError, SpecError, ValueError) as exc:
            self.get_logger().error(f"no metrics from {self.bag.path}: {exc}")
            return 1
        except Exception as exc:  # what the topics carried must not take the node down: the bag is written
            self.get_logger().error(f"no metrics from {self.bag.path}: {type(exc).__name__}: {exc}")
            return 1
        from neural_estimator.metrics.labelled import scored_line

        partial = scored_line(reports.values())  # partial ground truth: steps scored and not
        table = format_reports(reports, fmt="text")
        print(
            f"recorded run {self.bag.path}: {truth.n} trajectories x {truth.horizon} steps\n"
            + (partial + "\n" if partial else "")
            + table,
            end="",
            flush=True,
        )
        md = Path(str(self.bag.path)).with_suffix(".metrics.md")
        md.write_text(format_reports(reports, fmt="markdown"))
        doc = {
            "bag": str(self.bag.path),
            "spec": self.p.spec,
            "trajectories": truth.n,
            "horizon": truth.horizon,
            "warmup": warmup,
            **({"partial_ground_truth": partial} if partial else {}),
            "methods": reports,
        }
        js = md.with_suffix(".json")  # <bag>.metrics.json, beside the table, as for a scenario's run
        js.write_text(json.dumps(to_json(doc), indent=1, allow_nan=False))
        self.get_logger().info(f"wrote {md}, {js}")
        return 0

    def on_shutdown(self) -> int:
        if not self.closed:
            self.get_logger().info("interrupted: closing the bag")
            self._close()
        return self.exit_code


def main(args: list[str] | None = None) -> int:
    return run_node(EvaluatorNode, "evaluator", args)


if __name__ == "__main__":
    sys.exit(main())
