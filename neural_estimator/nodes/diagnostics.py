"""Frequency and staleness of a node's inputs, with diagnostic_updater's semantics (no rclpy here).

``diagnostic_updater.FrequencyStatus`` and ``TimeStampStatus`` are C++/Python helpers of a package
that has no pip wheel; this is their behaviour for one input stream, as plain code the nodes turn
into ``diagnostic_msgs/DiagnosticStatus``:

- frequency: messages per second over the last ``window`` seconds, OK inside
  ``[expected_rate * (1 - tolerance), expected_rate * (1 + tolerance)]``, WARN outside the band
  ("Frequency too low" / "Frequency too high"); ``expected_rate`` 0 checks no band.
- staleness: ERROR when no message arrived for ``stale_after`` seconds (diagnostic_updater's
  "No events recorded"), including before the first one.

Levels are 0 OK, 1 WARN, 2 ERROR (``DiagnosticStatus``'s byte values). Every status names the
node and method in ``hardware_id`` (:func:`hardware_id`). Other checks (drops, quarantine) add
their own levels to the same status: :func:`merge` keeps the worst level and every message.
"""

from __future__ import annotations

import collections
import dataclasses
from collections.abc import Iterable

OK, WARN, ERROR = 0, 1, 2


def hardware_id(node_name: str, method: str) -> str:
    """``/ns/estimator_ukf/ukf``: the node's full name and its method (what diagnostics aggregators group by)."""
    return f"{node_name.rstrip('/')}/{method}"


@dataclasses.dataclass(frozen=True)
class InputStatus:
    """One input's diagnostic: level, message and values (strings, as KeyValue wants)."""

    name: str
    level: int
    message: str
    values: dict[str, str]


class InputMonitor:
    """Receipt times of one input; :meth:`status` rates them against the expected rate.

    Args:
        name: the input (a topic name).
        expected_rate: messages per second expected (0 = no band check, staleness only).
        tolerance: relative width of the band around ``expected_rate`` (diagnostic_updater's 0.1).
        stale_after: seconds without a message after which the input is stale (ERROR).
        window: seconds over which the frequency is measured.
        start: the time monitoring started (staleness before the first message counts from it).
    """

    def __init__(
        self,
        name: str,
        expected_rate: float = 0.0,
        tolerance: float = 0.1,
        stale_after: float = 2.0,
        window: float = 5.0,
        start: float = 0.0,
    ) -> None:
        if expected_rate < 0 or tolerance < 0 or stale_after <= 0 or window <= 0:
            raise ValueError(f"input {name}: expected_rate and tolerance must be >= 0, stale_after and window > 0")
        self.name = name
        self.expected_rate = float(expected_rate)
        self.tolerance = float(tolerance)
        self.stale_after = float(stale_after)
        self.window = float(window)
        self.start = float(start)
        self.count = 0
        self._times: collections.deque[float] = collections.deque()

    def tick(self, now: float) -> None:
        """One message received at ``now`` (seconds, any monotonic clock shared with :meth:`status`)."""
        self.count += 1
        self._times.append(now)
        self._trim(now)

    def _trim(self, now: float) -> None:
        while self._times and self._times[0] < now - self.window:
            self._times.popleft()

    def frequency(self, now: float) -> float:
        """Messages per second over the window (over the time since start while shorter than it)."""
        self._trim(now)
        span = min(self.window, max(now - self.start, 1e-9))
        return len(self._times) / span

    def status(self, now: float) -> InputStatus:
        freq = self.frequency(now)
        last = self._times[-1] if self._times else None
        age = now - (last if last is not None else self.start)
        values = {
            "topic": self.name,
            "frequency (Hz)": f"{freq:.3g}",
            "expected frequency (Hz)": f"{self.expected_rate:g}" if self.expected_rate else "any",
            "messages": str(self.count),
            "seconds since last message": f"{age:.3g}" if last is not None else "never",
        }
        if age > self.stale_after:
            what = "no message yet" if self.count == 0 else f"stale: no message for {age:.1f} s"
            return InputStatus(self.name, ERROR, what, values)
        if self.expected_rate > 0 and now - self.start >= self.window:  # a full window before judging the band
            low = self.expected_rate * (1 - self.tolerance)
            high = self.expected_rate * (1 + self.tolerance)
            if freq < low:
                return InputStatus(self.name, WARN, f"frequency too low ({freq:.3g} < {low:.3g} Hz)", values)
            if freq > high:
                return InputStatus(self.name, WARN, f"frequency too high ({freq:.3g} > {high:.3g} Hz)", values)
        return InputStatus(self.name, OK, "ok", values)


def merge(statuses: Iterable[tuple[int, str]]) -> tuple[int, str]:
    """The worst level and the non-ok messages joined by '; ' ("ok" when none)."""
    level, messages = OK, []
    for lvl, msg in statuses:
        level = max(level, int(lvl))
        if lvl > OK and msg:
            messages.append(msg)
    return level, "; ".join(messages) if messages else "ok"


def parse_rates(items: Iterable[str]) -> dict[str, float]:
    """``["/imu=100", "/gps/fix=1"]`` -> {topic: Hz}; ValueError naming the bad item."""
    rates = {}
    for item in items:
        topic, sep, value = item.partition("=")
        try:
            rate = float(value)
        except ValueError:
            rate = -1.0
        if not sep or not topic or rate < 0:
            raise ValueError(f"expected_rates item {item!r} is not topic=Hz (Hz >= 0)")
        rates[topic] = rate
    return rates


def _param(default, help):  # noqa: A002 - the dataclass metadata key of nodes.common.param
    return dataclasses.field(default=default, metadata={"help": help})


@dataclasses.dataclass(frozen=True)
class InputDiagnosticsParams:
    """Input frequency/staleness parameters of the estimator nodes (params/*.yaml)."""

    expected_rate: float = _param(
        0.0, "expected input messages per second (0 = no band check): WARN outside rate_tolerance of it"
    )
    rate_tolerance: float = _param(0.1, "relative width of the frequency band around expected_rate")
    stale_timeout: float = _param(2.0, "seconds without an input message after which /diagnostics is ERROR (stale)")
    rate_window: float = _param(5.0, "seconds over which input frequencies are measured")

    def monitor(self, topic: str, now: float, expected_rate: float | None = None) -> InputMonitor:
        return InputMonitor(
            topic,
            self.expected_rate if expected_rate is None else expected_rate,
            self.rate_tolerance,
            self.stale_timeout,
            self.rate_window,
            start=now,
        )


def status_message(st: InputStatus, prefix: str, hwid: str, status_cls, key_value_cls):
    """A ``diagnostic_msgs/DiagnosticStatus`` (``status_cls``) named ``<prefix> input <topic>``."""
    msg = status_cls()
    msg.name = f"{prefix}: input {st.name}"
    msg.hardware_id = hwid
    msg.level = (status_cls.OK, status_cls.WARN, status_cls.ERROR)[st.level]
    msg.message = st.message
    msg.values = [key_value_cls(key=k, value=v) for k, v in st.values.items()]
    return msg
