"""A node's heap: where its Python heap grew (tracemalloc, on request) and the periodic trim that
gives the C heap's freed memory back to the system.

A node started with ``python -X tracemalloc=<frames>`` (``benchmarks/soak.py --tracemalloc 8``)
takes a baseline snapshot once it has published ``after`` estimates (its bounded histories are full
by then: growth before that is the fill-up) and, at shutdown, compares a second snapshot with it:
the allocation sites whose live memory grew most since the baseline, each as its call stack. That
is what a leak looks like from inside; RSS alone cannot tell a leak from fragmentation or a
history filling. Without ``-X tracemalloc`` nothing is traced and nothing is reported (tracemalloc
costs each allocation a stack walk: a measuring tool, not a production setting).

No rclpy: the estimator node calls :meth:`HeapTrace.tick` from its diagnostics and writes
:meth:`HeapTrace.report` into its stats file.

:class:`HeapTrim` and :func:`pin_malloc_thresholds`, set up for every node by ``nodes.common.run_node``
(``NEURAL_ESTIMATOR_HEAP_TRIM``: seconds between trims, default 10; 0 = neither). Why: glibc gives
freed memory back to the system only from the top of a heap, and raises its mmap threshold (up to
32 MiB, the trim threshold to twice that) each time a block it had mapped on its own is freed, so a
node that freed one large block at start-up carves every later large temporary out of the heap,
where its hole outlives it. Measured with ``benchmarks/soak.py --minutes 4 --rate-hz 500 --methods
ekf --depth 10000`` and glibc's own counts (``mallinfo2``): the EKF node's bytes in use stayed at
60.6 MiB while its heap grew 62.0 -> 64.2 MiB in 200 s, all of it free, and its RSS with it (slope
0.0059-0.0071 MiB/s after the warm-up, with the trim alone); with both thresholds pinned at glibc's
initial 128 KiB (``mallopt``) the heap grew 0.3 MiB and the slope was 0.0011. And a backlog: with
three estimators behind the stream (``--methods ekf,ukf,gru``) the EKF's bytes in use rose 61 ->
74 MiB while it held the queued observations and came back once it had drained, but without the trim
16 MiB of its RSS (14 of the UKF's, 11 of the GRU's) stayed resident as free heap for the rest of
the process's life; ``malloc_trim(0)`` returns every whole free page inside the heaps
(``madvise(MADV_DONTNEED)``): the same run with it took the EKF's anonymous memory from 144 back to
129 MiB within 10 s of the drain. A trim walks the free lists under the arenas' locks: 1-3 ms on
average on this machine, at most 18 ms at load 7.5 on 2 cores, once every 10 s (counted:
:meth:`HeapTrim.report`, the estimator's stats file).
"""

from __future__ import annotations

import ctypes
import math
import os
import time
import tracemalloc
from collections.abc import Mapping

HEAP_TRIM_ENV = "NEURAL_ESTIMATOR_HEAP_TRIM"
DEFAULT_HEAP_TRIM_PERIOD = 10.0  # seconds between trims (see the module docstring)


def heap_trim_period(environ: Mapping[str, str] | None = None) -> float:
    """Seconds between heap trims, from ``NEURAL_ESTIMATOR_HEAP_TRIM`` (unset or empty: 10; 0: off);
    ValueError naming the variable for anything but a finite number >= 0."""
    raw = (os.environ if environ is None else environ).get(HEAP_TRIM_ENV, "").strip()
    if not raw:
        return DEFAULT_HEAP_TRIM_PERIOD
    try:
        period = float(raw)
    except ValueError:
        period = -1.0
    if not (math.isfinite(period) and period >= 0):
        raise ValueError(f"{HEAP_TRIM_ENV} must be seconds between heap trims (>= 0; 0: off), got {raw!r}")
    return period


M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  # glibc's mallopt parameters (malloc.h)
PINNED_THRESHOLD = 128 * 1024  # bytes: glibc's initial mmap and trim thresholds
_GLIBC_OWN = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_")


def pin_malloc_thresholds(environ: Mapping[str, str] | None = None) -> bool:
    """Pin glibc's mmap and trim thresholds at 128 KiB (see the module docstring): a block of
    128 KiB or more is mapped on its own and unmapped when freed, and the heap's free top beyond
    128 KiB goes back at once, whatever the process freed before. Setting them by ``mallopt`` also
    stops glibc's dynamic adjustment. Left to the user where one of glibc's own variables
    (``MALLOC_MMAP_THRESHOLD_``, ``MALLOC_TRIM_THRESHOLD_``, ``MALLOC_TOP_PAD_``) is set; False there
    and where the C library is not glibc."""
    env = os.environ if environ is None else environ
    if any(v in env for v in _GLIBC_OWN):
        return False
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(M_MMAP_THRESHOLD, PINNED_THRESHOLD)) and bool(mallopt(M_TRIM_THRESHOLD, PINNED_THRESHOLD))


def _malloc_trim():
    try:
        fn = ctypes.CDLL("libc.so.6").malloc_trim
    except (OSError, AttributeError):  # not glibc: nothing to trim this way
        return None
    fn.argtypes, fn.restype = [ctypes.c_size_t], ctypes.c_int
    return fn


class HeapTrim:
    """Calls ``malloc_trim(0)`` (see the module docstring) and counts the calls and their time."""

    def __init__(self, period: float = DEFAULT_HEAP_TRIM_PERIOD) -> None:
        self.period = float(period)
        self._trim = _malloc_trim()
        self.calls = 0
        self.released = 0  # calls after which glibc reported memory given back
        self.seconds = 0.0
        self.max_seconds = 0.0
        self.last = time.monotonic()  # of the latest trim (or of the start)

    @property
    def available(self) -> bool:
        return self._trim is not None

    def overdue(self, now: float) -> bool:
        """True when no trim ran for 1.5 periods: its timer is starved (a node that never idles
        gets its timers late), and the caller trims instead."""
        return self.period > 0 and now - self.last >= 1.5 * self.period

    def __call__(self) -> bool:
        """One trim; True when glibc gave memory back."""
        if self._trim is None:
            return False
        t0 = time.perf_counter()
        released = bool(self._trim(0))
        dt = time.perf_counter() - t0
        self.last = time.monotonic()
        self.calls += 1
        self.released += released
        self.seconds += dt
        self.max_seconds = max(self.max_seconds, dt)
        return released

    def report(self) -> dict:
        """{period_s, calls, released, mean_ms, max_ms}: what the trims cost (the stats file)."""
        return {
            "period_s": self.period,
            "calls": self.calls,
            "released": self.released,
            "mean_ms": round(1e3 * self.seconds / self.calls, 3) if self.calls else None,
            "max_ms": round(1e3 * self.max_seconds, 3),
        }


class HeapTrace:
    """The baseline snapshot after ``after`` estimates, and the growth since it (see the module docstring)."""

    def __init__(self, after: int) -> None:
        self.after = int(after)
        self.baseline: tracemalloc.Snapshot | None = None
        self.baseline_estimates = 0

    def tick(self, estimated: int) -> None:
        if self.baseline is None and estimated >= self.after and tracemalloc.is_tracing():
            self.baseline = _snapshot()
            self.baseline_estimates = int(estimated)

    def report(self, estimated: int, top: int = 15) -> dict | None:
        """{estimates at the baseline and now, the traced heap's growth (KiB), and the ``top``
        allocation sites by growth: KiB, blocks, call stack (innermost first)}; None when not traced."""
        if self.baseline is None or not tracemalloc.is_tracing():
            return None
        diff = _snapshot().compare_to(self.baseline, "traceback")
        return {
            "baseline_estimates": self.baseline_estimates,
            "estimates": int(estimated),
            "traced_growth_kib": round(sum(d.size_diff for d in diff) / 1024, 1),
            "top": [
                {
                    "kib": round(d.size_diff / 1024, 1),
                    "blocks": d.count_diff,
                    "where": " <- ".join(f"{f.filename}:{f.lineno}" for f in reversed(d.traceback)),
                }
                for d in diff[:top]
            ],
        }


def _snapshot() -> tracemalloc.Snapshot:
    return tracemalloc.take_snapshot().filter_traces([tracemalloc.Filter(False, tracemalloc.__file__)])
