"""Player node: publishes a bag's messages on their topics at the recorded rate times ``rate``.

    ros2 run neural_estimator player --ros-args -p bag:=bags/lorenz96.mcap -p rate:=2.0
    python -m neural_estimator.nodes.player_node --ros-args -p bag:=bags/lorenz96.mcap

Messages go out as recorded (raw CDR bytes, no decoding) on the recorded topic names taken
relative to the player's namespace (``-r __ns:=/robot1`` plays ``/observation`` on
``/robot1/observation``; global topics such as ``/clock``, ``/tf`` and ``/diagnostics`` stay
global), in log-time order, message i at
``start + (t_i - t_0) / rate``; each topic with the QoS profile its publishers offered when it was
recorded (depth at least ``min_depth``). Estimate streams are left out unless ``play_estimates``,
so that live estimator nodes can be compared on the bag's observations; the ``run_status``
"complete" of the bag then tells the evaluator that the run ended (a bag without it, e.g. from
``ros2 bag record``, ends the evaluator by its ``idle_timeout``). ``bag`` is a ``.mcap`` file or a
rosbag2 directory. With ``publish_clock`` the player publishes ``/clock`` at each message's log
time, so nodes with ``use_sim_time:=true`` run on the bag's time. Parameters: ``params/player.yaml``.
"""

from __future__ import annotations

import dataclasses
import sys
import threading
import time
import warnings

from rclpy.duration import Duration

from neural_estimator.stream import messages as MSG
from neural_estimator.bags.errors import BagError, BagWarning
from neural_estimator.bags.directory import open_bag
from neural_estimator.bags.writer import QosError, parse_qos_yaml
from neural_estimator.nodes.common import (
    ExitStatusNode,
    InterfaceError,
    StartupError,
    declare_params,
    from_bag_qos,
    message_class,
    param,
    request_shutdown,
    run_node,
    stream_qos,
)


GLOBAL_TOPICS = ("/clock", "/tf", "/tf_static", "/diagnostics", "/rosout", "/parameter_events")


@dataclasses.dataclass(frozen=True)
class PlayerParams:
    """Parameters of the player node (documented in params/player.yaml)."""

    bag: str = param("", "the bag to play: .mcap file or rosbag2 directory")
    rate: float = param(1.0, "speed factor: 2.0 plays twice as fast as recorded")
    topics: tuple[str, ...] = param((), "absolute topic names to play; empty = all (see play_estimates)")
    play_estimates: bool = param(False, "also play estimates/* streams (off: live estimators answer instead)")
    min_depth: int = param(10000, "smallest publisher depth (recorded profiles may be shallower)")
    wait_for_subscribers: int = param(0, "subscriptions to wait for on wait_topic before playing")
    wait_topic: str = param("/observation", "recorded topic whose subscribers are counted")
    wait_timeout: float = param(30.0, "seconds to wait for them (then play anyway); 0 = forever")
    start_delay: float = param(1.0, "extra seconds before the first message (discovery)")
    exit_when_done: bool = param(True, "shut down after the last message (after linger seconds)")
    linger: float = param(30.0, "most seconds to wait after the last message until every subscriber acknowledged it")
    publish_clock: bool = param(False, "publish /clock at each message's log time (for nodes with use_sim_time:=true)")


class PlayerNode(ExitStatusNode):
    def __init__(self) -> None:
        super().__init__("player")
        self.p = p = declare_params(self, PlayerParams)
        if not p.bag:
            raise StartupError("parameter bag is empty: which .mcap should be played?")
        if p.rate <= 0:
            raise StartupError(f"rate must be > 0, got {p.rate}")
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always", BagWarning)
                self.reader = open_bag(p.bag).open()
        except BagError as exc:
            raise StartupError(str(exc)) from None
        for w in caught:
            self.get_logger().warning(str(w.message))
        self.pubs = {}
        for conn in self.reader.connections:
            if p.topics and conn.topic not in p.topics:
                continue
            if not p.topics and not p.play_estimates and f"/{MSG.ESTIMATES}/" in conn.topic:
                continue
            try:
                cls = message_class(conn.msgtype)
            except InterfaceError as exc:
                self.get_logger().warning(f"'{conn.topic}': {exc}; not played")
                continue
            try:  # recorded metadata is untrusted: out-of-bounds profiles are refused, never offered
                offered = parse_qos_yaml(conn.offered_qos_profiles)
            except QosError as exc:
                self.get_logger().warning(f"'{conn.topic}': recorded QoS ignored, defaults used: {exc}")
                offered = []
            qos = from_bag_qos(offered[0], p.min_depth) if offered else stream_qos(p.min_depth)
            name = conn.topic if conn.topic in GLOBAL_TOPICS else conn.topic.lstrip("/")  # in the node's namespace
            self.pubs[conn.topic] = self.create_publisher(cls, name, qos)
        if not self.pubs:
            raise StartupError(f"{p.bag}: no topic to play")
        self.pub_clock = None
        if p.publish_clock:
            from rosgraph_msgs.msg import Clock as ClockMsg

            self._clock_cls = ClockMsg
            self.pub_clock = self.create_publisher(ClockMsg, "/clock", 10)
        self.wait_pub = None
        if p.wait_for_subscribers > 0:
            self.wait_pub = self.pubs.get(p.wait_topic)
            if self.wait_pub is None:
                raise StartupError(f"wait_topic {p.wait_topic!r} is not played from {p.bag}")
        self.get_logger().info(
            f"playing {p.bag} at x{p.rate:g}: {', '.join(sorted(pub.topic_name for pub in self.pubs.values()))} "
            f"({sum(self.reader.topics[t].msgcount for t in self.pubs)} messages)"
        )
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._play, name="player", daemon=True)
        self._thread.start()

    def _play(self) -> None:
        p = self.p
        try:
            if self.wait_pub is not None:
                t0 = time.monotonic()
                while self.wait_pub.get_subscription_count() < p.wait_for_subscribers:
                    if self._stop.wait(0.05):
                        return
                    if p.wait_timeout > 0 and time.monotonic() - t0 > p.wait_timeout:
                        self.get_logger().warning("not all subscribers arrived: playing anyway")
                        break
            if self._stop.wait(p.start_delay):
                return
            first = None
            start = time.perf_counter()
            sent = 0
            for conn, t, raw in self.reader.messages(list(self.pubs)):
                first = t if first is None else first
                wait = start + (t - first) / 1e9 / p.rate - time.perf_counter()
                if wait > 0 and self._stop.wait(wait):
                    return
                if self._stop.is_set():
                    return
                if self.pub_clock is not None:
                    clock = self._clock_cls()
                    clock.clock.sec, clock.clock.nanosec = divmod(int(t), 1_000_000_000)
                    self.pub_clock.publish(clock)
                self.pubs[conn.topic].publish(raw)
                sent += 1
            self.get_logger().info(f"played {sent} messages in {time.perf_counter() - start:.2f} s")
            if p.exit_when_done:
                deadline = time.monotonic() + p.linger
                for pub in self.pubs.values():  # exiting drops what subscribers have not acknowledged
                    left = deadline - time.monotonic()
                    if left <= 0 or self._stop.is_set() or not pub.wait_for_all_acked(Duration(seconds=left)):
                        break
                request_shutdown(self, 0)
        except Exception as exc:
            self.get_logger().fatal(f"playback failed: {exc!r}")
            request_shutdown(self, 1)

    def on_shutdown(self) -> int:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self.reader.close()
        return self.exit_code


def main(args: list[str] | None = None) -> int:
    return run_node(PlayerNode, "player", args)


if __name__ == "__main__":
    sys.exit(main())
