"""Where a node's Python heap grew after its warm-up: tracemalloc snapshots compared, on request.

A node started with ``python -X tracemalloc=<frames>`` (``benchmarks/soak.py --tracemalloc 8``)
takes a baseline snapshot once it has published ``after`` estimates (its bounded histories are full
by then: growth before that is the fill-up) and, at shutdown, compares a second snapshot with it:
the allocation sites whose live memory grew most since the baseline, each as its call stack. That
is what a leak looks like from inside; RSS alone cannot tell a leak from fragmentation or a
history filling. Without ``-X tracemalloc`` nothing is traced and nothing is reported (tracemalloc
costs each allocation a stack walk: a measuring tool, not a production setting).

No rclpy: the estimator node calls :meth:`HeapTrace.tick` from its diagnostics and writes
:meth:`HeapTrace.report` into its stats file.
"""

from __future__ import annotations

import tracemalloc


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
