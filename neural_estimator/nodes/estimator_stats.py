"""The estimator node's counters and what it reports of them (diagnostics, the stats file): plain Python,
no rclpy, so the reporting rules are tested without a ROS graph."""

from __future__ import annotations

import array
import dataclasses

import numpy as np

OK, WARN, ERROR = 0, 1, 2  # diagnostic_msgs/DiagnosticStatus levels


@dataclasses.dataclass
class EstimatorStats:
    """Counters of the node; ``window`` reports the part since the previous call."""

    estimated: int = 0
    bad: int = 0
    errors: int = 0  # exceptions inside the method (stream restarted)
    early: int = 0
    nonfinite: int = 0
    gap_steps: int = 0
    restarts: int = 0
    resets: int = 0
    manual_resets: int = 0
    diverged: bool = False
    position: tuple[int, int] = (-1, -1)
    skipped: dict = dataclasses.field(default_factory=lambda: {"duplicate": 0, "stale": 0})
    latency: array.array = dataclasses.field(default_factory=lambda: array.array("d"))
    # staying current: observation published -> estimate published (s), wake-ups, the largest backlog
    # taken in one wake-up, observations dropped because they waited longer than max_delay
    delay: array.array = dataclasses.field(default_factory=lambda: array.array("d"))
    wakeups: int = 0
    max_batch: int = 0
    late_dropped: int = 0
    _mark: dict = dataclasses.field(default_factory=dict)

    _MAX_KEPT = 200_000  # latencies kept for the since-start percentiles (the most recent ones)

    def window(self, now: float) -> dict:
        m = self._mark or {
            "t": now,
            "estimated": 0,
            "bad": 0,
            "early": 0,
            "gap_steps": 0,
            "nonfinite": 0,
            "errors": 0,
            "n_lat": 0,
            "n_delay": 0,
            "late_dropped": 0,
        }
        lat = np.frombuffer(self.latency, dtype=np.float64)[m["n_lat"] :]
        delay = np.frombuffer(self.delay, dtype=np.float64)[m["n_delay"] :]
        dt = max(now - m["t"], 1e-9)
        out = {
            "rate": (self.estimated - m["estimated"]) / dt if self._mark else 0.0,
            "bad": self.bad - m["bad"],
            "early": self.early - m["early"],
            "gap_steps": self.gap_steps - m["gap_steps"],
            "nonfinite": self.nonfinite - m["nonfinite"],
            "errors": self.errors - m["errors"],
            "p50": float(np.percentile(lat, 50)) if lat.size else float("nan"),
            "p99": float(np.percentile(lat, 99)) if lat.size else float("nan"),
            "delay_p99": float(np.percentile(delay, 99)) if delay.size else float("nan"),
            "late_dropped": self.late_dropped - m["late_dropped"],
        }
        if len(self.latency) > self._MAX_KEPT:
            del self.latency[: len(self.latency) - self._MAX_KEPT // 2]
        if len(self.delay) > self._MAX_KEPT:
            del self.delay[: len(self.delay) - self._MAX_KEPT // 2]
        self._mark = {
            "t": now,
            "estimated": self.estimated,
            "bad": self.bad,
            "early": self.early,
            "gap_steps": self.gap_steps,
            "nonfinite": self.nonfinite,
            "errors": self.errors,
            "n_lat": len(self.latency),
            "n_delay": len(self.delay),
            "late_dropped": self.late_dropped,
        }
        return out

    def percentiles(self) -> tuple[float, float]:
        lat = np.frombuffer(self.latency, dtype=np.float64)
        if not lat.size:
            return float("nan"), float("nan")
        return float(np.percentile(lat, 50)), float(np.percentile(lat, 99))


def health(
    stats: EstimatorStats, window: dict, *, waiting: bool, foreign: set[str], delay_warn: float = 0.1
) -> tuple[int, list[str]]:
    """(level OK/WARN/ERROR, problems) of the node over the last diagnostics window.

    ERROR: the estimate diverged, or the method failed (its stream restarted). WARN: bad messages,
    missing steps, non-finite observations or publishers of the wrong type in the window, still
    waiting for the scenario, or behind: observations waited longer than ``delay_warn`` s (p99 of the
    window, published -> estimate published) or were dropped for waiting longer than ``max_delay``.
    """
    problems = []
    level = ERROR if stats.diverged else OK
    if stats.diverged:
        problems.append("diverged (estimates NaN until reset)")
    if window["errors"]:
        level = ERROR
        problems.append(f"{window['errors']} failures inside the method (stream restarted)")
    recent_bad = window["bad"] + window["early"]
    if recent_bad or window["gap_steps"] or window["nonfinite"] or foreign:
        level = max(level, WARN)
        problems += [f"{recent_bad} bad messages"] * bool(recent_bad)
        problems += [f"{window['gap_steps']} missing steps"] * bool(window["gap_steps"])
        problems += [f"{window['nonfinite']} non-finite observations"] * bool(window["nonfinite"])
        problems += [f"foreign publishers: {', '.join(sorted(foreign))}"] * bool(foreign)
    behind = window.get("delay_p99", float("nan"))
    if delay_warn > 0 and behind > delay_warn:
        level = max(level, WARN)
        problems.append(f"behind: observations wait {behind * 1e3:.0f} ms (p99) for their estimate")
    if window.get("late_dropped"):
        level = max(level, WARN)
        problems.append(f"behind: {window['late_dropped']} late observations dropped")
    if waiting:
        level = max(level, WARN)
        problems.append("waiting for the scenario")
    return level, problems


def diagnostic_values(stats: EstimatorStats, window: dict, method: str) -> dict[str, str]:
    """The key-value pairs of the node's /diagnostics status."""
    a50, a99 = stats.percentiles()
    d = np.frombuffer(stats.delay, dtype=np.float64)
    d50, d99 = (float(np.percentile(d, 50)), float(np.percentile(d, 99))) if d.size else (float("nan"),) * 2
    return {
        "method": method,
        "update rate (Hz)": f"{window['rate']:.1f}",
        "latency p50 (ms)": f"{window['p50'] * 1e3:.3f}",
        "latency p99 (ms)": f"{window['p99'] * 1e3:.3f}",
        "latency p50 since start (ms)": f"{a50 * 1e3:.3f}",
        "latency p99 since start (ms)": f"{a99 * 1e3:.3f}",
        "observation delay p99 (ms)": f"{window.get('delay_p99', float('nan')) * 1e3:.3f}",
        "observation delay p50 since start (ms)": f"{d50 * 1e3:.3f}",
        "observation delay p99 since start (ms)": f"{d99 * 1e3:.3f}",
        "late observations dropped": str(stats.late_dropped),
        "wake-ups": str(stats.wakeups),
        "largest backlog taken": str(stats.max_batch),
        "estimates published": str(stats.estimated),
        "bad messages": str(stats.bad + stats.early),
        "method failures": str(stats.errors),
        "non-finite observations": str(stats.nonfinite),
        "duplicate steps": str(stats.skipped["duplicate"]),
        "out-of-order steps": str(stats.skipped["stale"]),
        "missing steps bridged": str(stats.gap_steps),
        "stream restarts": str(stats.restarts),
        "trajectory resets": str(stats.resets),
        "manual resets": str(stats.manual_resets),
        "diverged": str(stats.diverged).lower(),
        "trajectory": str(stats.position[0]),
        "step": str(stats.position[1]),
    }


def stats_summary(stats: EstimatorStats, node: str, method: str) -> dict:
    """The counters and latency percentiles written to the ``stats_file`` at shutdown (JSON-ready)."""
    lat = np.frombuffer(stats.latency, dtype=np.float64)
    pct = {f"latency_p{q}_ms": float(np.percentile(lat, q)) * 1e3 if lat.size else None for q in (50, 90, 99)}
    d = np.frombuffer(stats.delay, dtype=np.float64)
    pct |= {f"delay_p{q}_ms": float(np.percentile(d, q)) * 1e3 if d.size else None for q in (50, 99)}
    return {
        "node": node,
        "method": method,
        "estimates": stats.estimated,
        "bad": stats.bad + stats.early,
        "method_failures": stats.errors,
        "nonfinite": stats.nonfinite,
        "duplicates": stats.skipped["duplicate"],
        "out_of_order": stats.skipped["stale"],
        "gap_steps": stats.gap_steps,
        "restarts": stats.restarts,
        "resets": stats.resets,
        "diverged": stats.diverged,
        "late_dropped": stats.late_dropped,
        "wakeups": stats.wakeups,
        "max_batch": stats.max_batch,
        "latency_samples": int(lat.size),
        "latency_max_ms": float(lat.max()) * 1e3 if lat.size else None,
        **pct,
    }
