"""The estimator node's counters and what it reports of them (diagnostics, the stats file): plain Python,
no rclpy, so the reporting rules are tested without a ROS graph."""

from __future__ import annotations

import dataclasses

import numpy as np

OK, WARN, ERROR = 0, 1, 2  # diagnostic_msgs/DiagnosticStatus levels

SKIP_REASONS = ("duplicate", "stale", "unconfirmed")  # messages skipped without an estimate (see stream/online.py)


class LatencyRing:
    """The most recent ``capacity`` latencies (seconds) in a preallocated float64 ring.

    Never resized, so its memory is fixed (8 bytes x capacity) whatever the run length, and a
    numpy view of it can never block a later append (an ``array.array`` trimmed while a
    ``np.frombuffer`` view of it is alive raises BufferError). ``total`` counts every sample ever
    appended; :meth:`since` returns (a copy of) the samples appended after a given total.
    """

    def __init__(self, capacity: int = 200_000) -> None:
        self.capacity = int(capacity)
        # np.full writes every page now: np.zeros is calloc, whose untouched pages the kernel maps
        # only when first written, so a zeros ring grew the node's RSS by 8 bytes per sample until
        # it wrapped (2 rings x 1.6 MB over the first 200,000 messages: a 400 s "leak" at 500 Hz)
        self._buf = np.full(self.capacity, 0.0, dtype=np.float64)
        self.total = 0

    def append(self, value: float) -> None:
        self._buf[self.total % self.capacity] = value
        self.total += 1

    def extend(self, values) -> None:
        for v in values:
            self.append(v)

    def __len__(self) -> int:
        return min(self.total, self.capacity)

    def since(self, total: int) -> np.ndarray:
        """The samples appended after the ``total``-th one (at most ``capacity``, the newest), a copy."""
        n = min(self.total - max(0, total), self.capacity)
        if n <= 0:
            return np.zeros(0)
        end = self.total % self.capacity
        if n <= end:
            return self._buf[end - n : end].copy()
        return np.concatenate([self._buf[self.capacity - (n - end) :], self._buf[:end]])

    def values(self) -> np.ndarray:
        """Every kept sample (the newest ``capacity``), oldest first, a copy."""
        return self.since(0)


_COUNTERS = (
    "estimated",
    "bad",
    "early",
    "gap_steps",
    "nonfinite",
    "errors",
    "restarts",
    "quarantined",
    "oversize",
    "late_dropped",
    "missed",
)


@dataclasses.dataclass
class EstimatorStats:
    """Counters of the node; ``window`` reports the part since the previous call."""

    estimated: int = 0
    bad: int = 0
    errors: int = 0  # exceptions inside the method (stream restarted)
    early: int = 0
    nonfinite: int = 0
    gap_steps: int = 0
    # steps of the stream that never reached the estimator: lost upstream (DDS queue overflow, network)
    # or dropped here as late; bridged (gap_steps) or not (a restart)
    missed: int = 0
    restarts: int = 0
    resets: int = 0
    manual_resets: int = 0
    quarantined: int = 0  # messages held until the stream confirmed (or dropped) them
    oversize: int = 0  # messages over the size bound, dropped unread
    publisher_restarts: int = 0  # new runs detected (announcement or stamp epoch)
    busy: float = 0.0  # seconds spent processing messages
    lag: float = 0.0  # the longest a message waited (sent -> processing started) in the current window
    diverged: bool = False
    position: tuple[int, int] = (-1, -1)
    skipped: dict = dataclasses.field(default_factory=lambda: dict.fromkeys(SKIP_REASONS, 0))
    latency: LatencyRing = dataclasses.field(default_factory=LatencyRing)
    # staying current: observation published -> estimate published (s), wake-ups, the largest backlog
    # taken in one wake-up, observations dropped because they waited longer than max_delay
    delay: LatencyRing = dataclasses.field(default_factory=LatencyRing)
    wakeups: int = 0
    max_batch: int = 0
    late_dropped: int = 0
    _mark: dict = dataclasses.field(default_factory=dict)

    def waited(self, seconds: float) -> None:
        """A message reached the node ``seconds`` after it was sent (queued in DDS meanwhile)."""
        self.lag = max(self.lag, seconds)

    def record(self, seconds: float) -> None:
        """One processed message took ``seconds``."""
        self.latency.append(seconds)
        self.busy += seconds

    def _snapshot(self, now: float) -> dict:
        return {
            "t": now,
            **{k: getattr(self, k) for k in _COUNTERS},
            "skipped": sum(self.skipped.values()),
            "busy": self.busy,
            "n_lat": self.latency.total,
            "n_delay": self.delay.total,
        }

    def window(self, now: float) -> dict:
        """The counters since the previous call (the first call: since the start), the window's
        estimate rate, latency percentiles and busy fraction (time spent processing / wall time)."""
        m = self._mark or {"t": now, **dict.fromkeys(_COUNTERS, 0), "skipped": 0, "busy": 0.0, "n_lat": 0, "n_delay": 0}
        lat = self.latency.since(m["n_lat"])
        delay = self.delay.since(m["n_delay"])
        dt = max(now - m["t"], 1e-9)
        out = {k: getattr(self, k) - m[k] for k in _COUNTERS}
        out.update(
            rate=out["estimated"] / dt if self._mark else 0.0,
            skipped=sum(self.skipped.values()) - m["skipped"],
            busy=(self.busy - m["busy"]) / dt if self._mark else 0.0,
            lag=self.lag,
            p50=float(np.percentile(lat, 50)) if lat.size else float("nan"),
            p99=float(np.percentile(lat, 99)) if lat.size else float("nan"),
            delay_p99=float(np.percentile(delay, 99)) if delay.size else float("nan"),
        )
        self._mark = self._snapshot(now)
        self.lag = 0.0
        return out

    def percentiles(self) -> tuple[float, float]:
        lat = self.latency.values()
        if not lat.size:
            return float("nan"), float("nan")
        return float(np.percentile(lat, 50)), float(np.percentile(lat, 99))


BUSY_WARN = 0.9  # a node busy more than this share of the wall time is falling behind
LAG_WARN = 1.0  # s: a message that waited longer than this in the queue means the node is behind


def lost_upstream(counts) -> int:
    """Observations the publisher sent that never reached the node: the stream's missed steps less
    those the node itself dropped as late (``max_delay``; each of those is a missed step too).
    ``counts``: a window dict or the stats' totals (a dict of the counters)."""
    return max(0, counts.get("missed", 0) - counts.get("late_dropped", 0))


def health(
    stats: EstimatorStats, window: dict, *, waiting: bool, foreign: set[str], delay_warn: float = 0.1
) -> tuple[int, list[str]]:
    """(level OK/WARN/ERROR, problems) of the node over the last diagnostics window.

    ERROR: the estimate diverged, the method failed (its stream restarted), or the window lost at
    least as many messages as it estimated (missed steps included, whether bridged or skipped by a
    restart). WARN: any message dropped, skipped or held in the window (bad, oversize, duplicate,
    out of order, unconfirmed, quarantined, waiting for the scenario), observations lost upstream
    (never received), missing steps, stream restarts, non-finite observations, busy more than 90 % of the time or a
    message that waited more than 1 s in the queue (falling behind: the queue grows and DDS drops
    the oldest), observations that waited longer than ``delay_warn`` s for their estimate (p99 of
    the window, published -> estimate published) or were dropped for waiting longer than
    ``max_delay``, publishers of the wrong type, or still waiting for the scenario. Every problem
    names its count.
    """
    problems = []
    level = ERROR if stats.diverged else OK
    if stats.diverged:
        problems.append("diverged (estimates NaN until reset)")
    if window["errors"]:
        level = ERROR
        problems.append(f"{window['errors']} failures inside the method (stream restarted)")
    recent_bad = window["bad"] + window["early"]
    # every missed step: bridged ones (gap_steps) and those a restart skipped, which were counted nowhere
    missed = max(window["gap_steps"], window.get("missed", 0))
    dropped = recent_bad + window["oversize"] + window["skipped"] + missed
    notes = [
        (recent_bad, "bad messages dropped"),
        (window["oversize"], "oversize messages dropped"),
        (window["skipped"], "messages skipped (duplicate, out of order or unconfirmed)"),
        (window["quarantined"], "messages quarantined (jump awaiting confirmation)"),
        (lost_upstream(window), "observations lost upstream (never received)"),
        (window["gap_steps"], "missing steps"),
        (window["restarts"], "stream restarts (gap too long)"),
        (window["nonfinite"], "non-finite observations"),
    ]
    for count, what in notes:
        if count:
            level = max(level, WARN)
            problems.append(f"{count} {what}")
    if window["busy"] > BUSY_WARN:
        level = max(level, WARN)
        problems.append(f"falling behind: busy {100 * window['busy']:.0f}% of the time")
    if window.get("lag", 0.0) > LAG_WARN:
        level = max(level, WARN)
        problems.append(f"falling behind: a message waited {window['lag']:.1f} s in the queue")
    behind = window.get("delay_p99", float("nan"))
    if delay_warn > 0 and behind > delay_warn:
        level = max(level, WARN)
        problems.append(f"behind: observations wait {behind * 1e3:.0f} ms (p99) for their estimate")
    if window.get("late_dropped"):
        level = max(level, WARN)
        problems.append(f"behind: {window['late_dropped']} late observations dropped")
    if foreign:
        level = max(level, WARN)
        problems.append(f"foreign publishers: {', '.join(sorted(foreign))}")
    if dropped and dropped >= max(1, window["estimated"]):
        level = ERROR
        problems.insert(0, f"lost {dropped} messages against {window['estimated']} estimates")
    if waiting:
        level = max(level, WARN)
        problems.append("waiting for the scenario")
    return level, problems


def diagnostic_values(stats: EstimatorStats, window: dict, method: str) -> dict[str, str]:
    """The key-value pairs of the node's /diagnostics status."""
    a50, a99 = stats.percentiles()
    d = stats.delay.values()
    d50, d99 = (float(np.percentile(d, 50)), float(np.percentile(d, 99))) if d.size else (float("nan"),) * 2
    return {
        "method": method,
        "update rate (Hz)": f"{window['rate']:.1f}",
        "busy (%)": f"{100 * window['busy']:.1f}",
        "longest wait in the queue (s)": f"{window.get('lag', 0.0):.3f}",
        "latency p50 (ms)": f"{window['p50'] * 1e3:.3f}",
        "latency p99 (ms)": f"{window['p99'] * 1e3:.3f}",
        "latency p50 since start (ms)": f"{a50 * 1e3:.3f}",
        "latency p99 since start (ms)": f"{a99 * 1e3:.3f}",
        "observation delay p99 (ms)": f"{window.get('delay_p99', float('nan')) * 1e3:.3f}",
        "observation delay p50 since start (ms)": f"{d50 * 1e3:.3f}",
        "observation delay p99 since start (ms)": f"{d99 * 1e3:.3f}",
        "late observations dropped": str(stats.late_dropped),
        "observations lost upstream": str(lost_upstream(vars(stats))),
        "wake-ups": str(stats.wakeups),
        "largest backlog taken": str(stats.max_batch),
        "estimates published": str(stats.estimated),
        "bad messages": str(stats.bad + stats.early),
        "oversize messages": str(stats.oversize),
        "method failures": str(stats.errors),
        "non-finite observations": str(stats.nonfinite),
        "duplicate steps": str(stats.skipped["duplicate"]),
        "out-of-order steps": str(stats.skipped["stale"]),
        "unconfirmed jumps dropped": str(stats.skipped["unconfirmed"]),
        "quarantined messages": str(stats.quarantined),
        "missing steps bridged": str(stats.gap_steps),
        "stream restarts": str(stats.restarts),
        "publisher restarts": str(stats.publisher_restarts),
        "trajectory resets": str(stats.resets),
        "manual resets": str(stats.manual_resets),
        "diverged": str(stats.diverged).lower(),
        "trajectory": str(stats.position[0]),
        "step": str(stats.position[1]),
    }


def stats_summary(stats: EstimatorStats, node: str, method: str) -> dict:
    """The counters and latency percentiles written to the ``stats_file`` at shutdown (JSON-ready)."""
    lat = stats.latency.values()
    pct = {f"latency_p{q}_ms": float(np.percentile(lat, q)) * 1e3 if lat.size else None for q in (50, 90, 99)}
    d = stats.delay.values()
    pct |= {f"delay_p{q}_ms": float(np.percentile(d, q)) * 1e3 if d.size else None for q in (50, 99)}
    return {
        "node": node,
        "method": method,
        "estimates": stats.estimated,
        "bad": stats.bad + stats.early,
        "oversize": stats.oversize,
        "method_failures": stats.errors,
        "nonfinite": stats.nonfinite,
        "duplicates": stats.skipped["duplicate"],
        "out_of_order": stats.skipped["stale"],
        "unconfirmed": stats.skipped["unconfirmed"],
        "quarantined": stats.quarantined,
        "gap_steps": stats.gap_steps,
        "missed": stats.missed,
        "lost_upstream": lost_upstream(vars(stats)),
        "restarts": stats.restarts,
        "publisher_restarts": stats.publisher_restarts,
        "resets": stats.resets,
        "diverged": stats.diverged,
        "late_dropped": stats.late_dropped,
        "wakeups": stats.wakeups,
        "max_batch": stats.max_batch,
        "busy_s": stats.busy,
        "latency_samples": stats.latency.total,
        "latency_kept": len(stats.latency),
        "latency_max_ms": float(lat.max()) * 1e3 if lat.size else None,
        **pct,
    }
