"""What the nodes share: parameters as frozen dataclasses, QoS profiles, the main() shape.

Parameters: every field of a node's frozen dataclass is one ROS parameter, declared read-only with
a :class:`ParameterDescriptor` whose description is the field's ``help`` metadata (the same text
as the comment in ``params/<node>.yaml``). Values are converted to the field's type here, so
``-p rate_hz:=1000`` and ``-p rate_hz:=1000.0`` both work and a wrong value is one clear line
naming the parameter; a list parameter also accepts one comma-separated string.
"""

from __future__ import annotations

import dataclasses
import gc
import importlib
import os
import time
import typing
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import rclpy
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.clock import Clock, ClockType
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, LivelinessPolicy, QoSProfile, ReliabilityPolicy

from neural_estimator.bags.writer import Qos
from neural_estimator.core.interfaces import InterfaceError, check_message_type, is_message_class
from neural_estimator.nodes.heap_trace import HeapTrim, heap_trim_period, pin_malloc_thresholds
from neural_estimator.nodes.realtime import RealtimeError, apply_realtime_priority, requested_priority
from neural_estimator.core.options import OptionError, parse_value

RCLError = _rclpy.RCLError  # rclpy's error type for rcl failures (not exported elsewhere in rclpy 7.1)

P = TypeVar("P")


class StartupError(Exception):
    """A node cannot start (bad parameter, unknown method, missing checkpoint): one clear line."""


def param(default: Any, help: str) -> Any:  # noqa: A002 - the dataclass metadata key
    """A dataclass field that is a ROS parameter with its description."""
    if isinstance(default, (list, tuple)):
        return dataclasses.field(default=tuple(default), metadata={"help": help})
    return dataclasses.field(default=default, metadata={"help": help})


def declare_params(node: Node, cls: type[P]) -> P:
    """Declare every field of the frozen dataclass ``cls`` as a parameter and return the values."""
    hints = typing.get_type_hints(cls)
    values = {}
    for f in dataclasses.fields(cls):
        kind = hints[f.name]
        default = f.default
        desc = ParameterDescriptor(
            description=f.metadata.get("help", ""),
            additional_constraints=f"type: {_type_name(kind)}",
            read_only=True,
            dynamic_typing=True,
        )
        if node.has_parameter(f.name):  # peeked at before the node's kind was known (see peek_param)
            node.undeclare_parameter(f.name)
        value = node.declare_parameter(
            f.name,
            list(default)
            if isinstance(default, tuple) and default
            else (None if isinstance(default, tuple) else default),
            desc,
        ).value
        values[f.name] = _coerce(f.name, value, kind, default)
    try:
        return cls(**values)
    except (TypeError, ValueError) as exc:
        raise StartupError(str(exc)) from None


def peek_param(node: Node, name: str) -> Any:
    """The value the command line or a parameter file gives ``name`` on ``node`` (None if none), read
    by declaring it untyped and writable; :func:`declare_params` declares it again, as its field."""
    return node.declare_parameter(name, None, ParameterDescriptor(dynamic_typing=True)).value


def _type_name(kind: Any) -> str:
    if typing.get_origin(kind) is tuple:
        return "string list"
    return getattr(kind, "__name__", str(kind))


def _coerce(name: str, value: Any, kind: Any, default: Any) -> Any:
    """A parameter's value of its declared type, by the package's one grammar
    (:mod:`neural_estimator.core.options`: ``true/yes/on/1`` are true for a bool, as on the command line)."""
    if value is None:
        return default
    # a typed stand-in for the default: the parameter kinds are bool, int, float, str and tuple[str, ...]
    like = ("",) if typing.get_origin(kind) is tuple else kind()
    try:
        return parse_value(value, like, f"parameter {name}")
    except OptionError as exc:
        raise StartupError(str(exc)) from None


# ---- QoS -----------------------------------------------------------------------------------------------
def stream_qos(depth: int, transient_local: bool = True) -> QoSProfile:
    """Reliable, KEEP_LAST ``depth``; transient_local so that a recorder that joins a little late
    still gets the first ``depth`` messages (the evaluator subscribes when it discovers a topic)."""
    return QoSProfile(
        depth=max(1, int(depth)),
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if transient_local else DurabilityPolicy.VOLATILE,
        history=HistoryPolicy.KEEP_LAST,
    )


def latched_qos() -> QoSProfile:
    """Reliable + transient_local, depth 1: the last value reaches late joiners (scenario, status)."""
    return stream_qos(1, transient_local=True)


_INF_NS = 9223372036854775807


def to_bag_qos(profile: QoSProfile) -> Qos:
    """The rosbag2 record of an (offered) rclpy QoS profile."""

    def dur(d: Any) -> tuple[int, int] | None:
        ns = int(d.nanoseconds) if d is not None else 0
        return None if ns <= 0 or ns >= _INF_NS else divmod(ns, 1_000_000_000)  # 0 = rmw default = infinite

    def name(policy: Any, default: str) -> str:
        n = getattr(policy, "name", "").lower()
        return n if n and n not in ("system_default", "unknown", "best_available") else default

    return Qos(
        reliability=name(profile.reliability, "reliable"),
        durability=name(profile.durability, "volatile"),
        history=name(profile.history, "keep_last"),
        depth=int(profile.depth),
        deadline=dur(profile.deadline),
        lifespan=dur(profile.lifespan),
        liveliness=name(profile.liveliness, "automatic"),
        liveliness_lease_duration=dur(profile.liveliness_lease_duration),
        avoid_ros_namespace_conventions=bool(profile.avoid_ros_namespace_conventions),
    )


def from_bag_qos(q: Qos, min_depth: int = 1) -> QoSProfile:
    """An rclpy profile from a recorded one (reliability, durability, history, depth)."""
    return QoSProfile(
        depth=max(int(q.depth), int(min_depth)),
        reliability=ReliabilityPolicy.BEST_EFFORT if q.reliability == "best_effort" else ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if q.durability == "transient_local" else DurabilityPolicy.VOLATILE,
        history=HistoryPolicy.KEEP_ALL if q.history == "keep_all" else HistoryPolicy.KEEP_LAST,
        liveliness=LivelinessPolicy.MANUAL_BY_TOPIC
        if q.liveliness == "manual_by_topic"
        else LivelinessPolicy.AUTOMATIC,
    )


def message_class(msgtype: str) -> type:
    """The rclpy message class of ``pkg/msg/Type``, for a name someone else chose (a bag, the graph).

    The name is checked first (:func:`neural_estimator.core.interfaces.check_message_type`: the form
    ``<package>/msg/<Type>`` and a package the ament index declares as a ROS interface package),
    so no other package's import-time code runs; then only ``<package>.msg`` is imported and the
    class must be a rosidl message class. Every refusal is an :class:`InterfaceError` (one line).
    """
    package, name = check_message_type(msgtype)
    try:
        module = importlib.import_module(f"{package}.msg")
    except ImportError as exc:
        raise InterfaceError(f"message type {msgtype!r}: its Python module is not installed here ({exc})") from None
    cls = getattr(module, name, None)
    if not is_message_class(cls, name):
        raise InterfaceError(f"message type {msgtype!r}: {package}.msg.{name} is not a ROS message class")
    return cls


def subscribable_class(node: Node, topic: str, msgtype: str, refused: set[str], what: str) -> type | None:
    """The class to subscribe ``topic`` with (:func:`message_class` of the type it is published with),
    or None where the type is refused: one ERROR line the first time (``'<topic>': <why>; not <what>``),
    the topic then kept in ``refused`` (the evaluator and the robot estimator alike)."""
    try:
        return message_class(msgtype)
    except InterfaceError as exc:
        if topic not in refused:
            refused.add(topic)
            node.get_logger().error(f"'{topic}': {exc}; not {what}")
        return None


def warn_throttled(node: Node, last_log: dict[str, float], kind: str, text: str, every: float) -> None:
    """``text`` as one WARN line of ``node``, unless a warning of the same ``kind`` went out less than
    ``every`` seconds ago (``last_log``: kind -> when its last one went out, monotonic seconds)."""
    now = time.monotonic()
    if now - last_log.get(kind, -1e9) >= every:
        last_log[kind] = now
        node.get_logger().warning(text)


# ---- scenarios -----------------------------------------------------------------------------------------
def load_plugins(paths: tuple[str, ...]) -> None:
    """Import user files that register scenarios (the nodes' ``plugins`` parameter)."""
    from neural_estimator.scenarios import ScenarioError
    from neural_estimator.scenarios import load_plugins as load

    try:
        load(paths)
    except ScenarioError as exc:
        raise StartupError(f"plugins: {exc}") from None


def build_scenario(name: str, assignments: tuple[str, ...], noise_scale: float | None = None, preset: str = ""):
    """The scenario ``name``: its ``preset`` (empty: the defaults), then ``name=value`` constants
    (and noise scale) applied."""
    from neural_estimator.scenarios import ScenarioError, make_scenario, parse_assignments

    try:
        overrides: dict[str, Any] = parse_assignments(assignments)
        if noise_scale is not None:
            overrides["noise_scale"] = noise_scale
        return make_scenario(name, preset=preset or None, **overrides)
    except ScenarioError as exc:
        raise StartupError(str(exc)) from None


# ---- main ----------------------------------------------------------------------------------------------
class ExitStatusNode(Node):
    """What :func:`run_node` needs of a node, declared: an exit status and a clean-up hook (a plain
    rclpy node, not a ROS 2 managed, that is lifecycle, node).

    ``exit_code`` is the process's exit status (:func:`request_shutdown` sets it and ends the
    spin); :meth:`on_shutdown` runs once after the spin ends (Ctrl-C, SIGTERM, a shutdown request)
    and may return a different status (e.g. the evaluator's, once its metrics are written).
    """

    exit_code: int = 0

    def on_shutdown(self) -> int:
        return self.exit_code


DDS_PROFILES = Path(__file__).with_name("fastdds_profiles.xml")


def dds_memory_policy() -> None:
    """Fast DDS frees each sample's payload once taken (``fastdds_profiles.xml``): a huge message
    that a node drops unread does not stay resident. Set before ``rclpy.init``, for Fast DDS only,
    and only where the user configured none of it."""
    rmw = os.environ.get("RMW_IMPLEMENTATION", "")
    own = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE", "RMW_FASTRTPS_USE_QOS_FROM_XML")
    if rmw not in ("", "rmw_fastrtps_cpp", "rmw_fastrtps_dynamic_cpp") or any(v in os.environ for v in own):
        return
    if DDS_PROFILES.is_file():
        os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(DDS_PROFILES)
        os.environ["RMW_FASTRTPS_USE_QOS_FROM_XML"] = "1"


EXECUTOR_ENV = "NEURAL_ESTIMATOR_EXECUTOR"
EXECUTORS = ("events", "single")


def events_executor(context: Any) -> Any:
    """rclpy's ``rclpy.experimental.EventsExecutor`` for ``context``, or None where this rclpy has none."""
    try:
        from rclpy.experimental import EventsExecutor
    except ImportError:
        return None
    try:
        return EventsExecutor(context=context)
    except (AttributeError, RuntimeError, TypeError):  # built without it
        return None


def executor_choice() -> str:
    """The executor ``NEURAL_ESTIMATOR_EXECUTOR`` names (default events); a StartupError otherwise."""
    choice = os.environ.get(EXECUTOR_ENV, "") or "events"
    if choice not in EXECUTORS:
        raise StartupError(f"{EXECUTOR_ENV} must be one of {', '.join(EXECUTORS)}, got {choice!r}")
    return choice


def spin(node: Node, executor: str = "events") -> str:
    """Run ``node``'s callbacks until its context shuts down; returns the executor's name.

    The executor is rclpy's ``EventsExecutor`` where this rclpy has one (Jazzy's experimental
    one): each message, timer and service request arrives as an event from the middleware, without
    the wait set that the ``SingleThreadedExecutor`` rebuilds at every wake-up
    (``benchmarks/bench_executor.py`` measures both). Its ``spin()`` runs no timers in rclpy 7.1
    and does not return at shutdown, so it is driven by ``spin_once`` until the context is shut
    down (SIGINT/SIGTERM, :func:`request_shutdown`; the shutdown wakes it). The environment variable
    ``NEURAL_ESTIMATOR_EXECUTOR=single`` selects the single-threaded executor (also the fall-back
    where rclpy has no events executor), and so does ``executor="single"``: a node with a
    subscription whose callback takes the message info (rclpy 7.1's EventsExecutor raises
    SystemError on those; the evaluator's recorder needs each message's timestamps).
    """
    events = events_executor(node.context) if executor == "events" and executor_choice() == "events" else None
    if events is None:
        single = SingleThreadedExecutor(context=node.context)
        single.add_node(node)
        single.spin()
        return "single"
    events.add_node(node)
    context = node.context
    while context.ok():
        events.spin_once(timeout_sec=1.0)
    return "events"


def run_node(factory: Callable[[], Node], name: str, args: list[str] | None = None, executor: str = "events") -> int:
    """The nodes' main(): init, build, spin until shutdown (:func:`spin`, ``executor``), clean up; exit status.

    A :class:`StartupError` while building the node is logged as one fatal line and gives exit
    status 1; otherwise the status is the node's :meth:`ExitStatusNode.on_shutdown`.
    """
    import sys

    from neural_estimator.nodes import entry

    argv = list(sys.argv[1:] if args is None else args)
    if name in entry.PARAMETERS and entry.wants_help(argv):
        print(entry.help_text(name))
        return 0
    dds_memory_policy()
    priority, bad_priority = 0, ""
    try:
        priority = requested_priority()
    except RealtimeError as exc:
        bad_priority = str(exc)  # reported as the start-up error once the logger exists
    applied, line = apply_realtime_priority(priority)  # before rclpy.init: the middleware's threads inherit it
    rclpy.init(args=args)
    if name in entry.PARAMETERS:
        for line in entry.unknown_parameters(name, argv):
            rclpy.logging.get_logger(name).warning(line)
    try:
        if bad_priority:
            raise StartupError(bad_priority)
        executor_choice()
        trim_period = checked_heap_trim_period()
        if trim_period > 0:  # before the node's build: its large temporaries are then unmapped when freed
            pin_malloc_thresholds()
        node = factory()
    except StartupError as exc:
        rclpy.logging.get_logger(name).fatal(str(exc))
        rclpy.try_shutdown()
        return 1
    except KeyboardInterrupt:  # Ctrl-C while the node was still starting (loading a model): a clean stop
        rclpy.try_shutdown()
        return 0
    except RCLError:
        # SIGTERM during start-up: rclpy's handler shut the context down, and the node's next
        # publisher or timer fails on the invalid context. The same clean stop; a real error is raised.
        if rclpy.ok():
            raise
        rclpy.try_shutdown()
        return 0
    try:
        if priority:
            (node.get_logger().info if applied else node.get_logger().warning)(line)
        settle_heap()
        start_heap_trim(node, trim_period)
        spin(node, executor)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RCLError:
        # SIGTERM shuts the context down from rclpy's signal handler; landing while the executor
        # builds its wait set, that surfaces as "context is not valid" instead of
        # ExternalShutdownException. The same shutdown, so the same clean exit; a real error
        # (context still valid) is raised.
        if node.context.ok():
            raise
    finally:
        # an ExitStatusNode reports its exit status; other nodes (the lifecycle estimator, whose
        # on_shutdown is a lifecycle transition) exit 0 unless they set exit_code
        managed = isinstance(node, ExitStatusNode)
        code = int((node.on_shutdown() if managed else 0) or getattr(node, "exit_code", 0))
        node.destroy_node()
        rclpy.try_shutdown()
    return code


def request_shutdown(node: ExitStatusNode, code: int = 0) -> None:
    """End the spin of :func:`run_node` (from a callback) with exit status ``code``."""
    node.exit_code = code
    node.context.try_shutdown()


def settle_heap() -> None:
    """Collect once, then freeze every object alive now out of the garbage collector's reach.

    A node's process holds about 230,000 tracked objects once torch, ONNX Runtime and rclpy are
    imported; each full (generation-2) collection walks all of them and took 125 ms on this
    machine, which Python starts on its own every few thousand messages: at 1 kHz those pauses
    were the end-to-end p99 (60-160 ms stalls in every node). Frozen objects are never walked
    again, so a later collection only scans what was allocated since (microseconds). Called
    once the node is built, and again by a node that builds its estimator later (on /scenario):
    what was frozen before is unfrozen and collected first, so a model replaced by a rebuild is
    freed, not kept frozen for the life of the process.
    """
    gc.unfreeze()
    gc.collect()
    gc.freeze()


def trim_heap() -> None:
    """Give freed heap memory back to the system (glibc), so one huge message does not stay resident."""
    _TRIM()


_TRIM = HeapTrim()


def checked_heap_trim_period() -> float:
    """``NEURAL_ESTIMATOR_HEAP_TRIM`` (nodes/heap_trace.py); a StartupError for a bad value."""
    try:
        return heap_trim_period()
    except ValueError as exc:
        raise StartupError(str(exc)) from None


def start_heap_trim(node: Node, period: float) -> HeapTrim | None:
    """A steady-clock timer on ``node`` that trims the process's heap every ``period`` s
    (:class:`~neural_estimator.nodes.heap_trace.HeapTrim`: without it glibc kept the memory a node
    freed resident, 16 MiB of an EKF node's RSS after a drained backlog); kept as ``node.heap_trim``
    (its counts go into the estimator's stats file). None when ``period`` is 0 or the C library has
    no ``malloc_trim``."""
    trim = HeapTrim(period)
    if period <= 0 or not trim.available:
        return None
    node.heap_trim = trim
    node.create_timer(period, trim, clock=Clock(clock_type=ClockType.STEADY_TIME))
    return trim
