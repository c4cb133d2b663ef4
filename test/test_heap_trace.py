"""HeapTrace (nodes/heap_trace.py): the allocation site that grew after the baseline is named, and
nothing is traced or reported unless tracemalloc runs (``python -X tracemalloc``)."""

from __future__ import annotations

import tracemalloc

from neural_estimator.nodes.heap_trace import HeapTrace

_LEAK: list[bytes] = []


def _leak(n: int) -> None:
    for _ in range(n):
        _LEAK.append(bytes(1000))  # the growth the report must point at


def test_the_growing_site_is_named_after_the_baseline():
    was_tracing = tracemalloc.is_tracing()
    if not was_tracing:
        tracemalloc.start(4)
    try:
        heap = HeapTrace(after=10)
        heap.tick(5)
        assert heap.baseline is None and heap.report(5) is None  # before the histories are full
        _leak(500)  # the fill-up: before the baseline, not reported
        heap.tick(10)
        _leak(2000)
        report = heap.report(20)
        assert report["baseline_estimates"] == 10 and report["estimates"] == 20
        first = report["top"][0]
        assert "test_heap_trace.py" in first["where"].split(" <- ")[0] and 1900 <= first["blocks"] <= 2100
        assert first["kib"] > 1900 and report["traced_growth_kib"] > 1900
    finally:
        _LEAK.clear()
        if not was_tracing:
            tracemalloc.stop()


def test_nothing_without_tracemalloc():
    if tracemalloc.is_tracing():
        return  # the whole run traces: the first test covers it
    heap = HeapTrace(after=0)
    heap.tick(100)
    assert heap.baseline is None and heap.report(100) is None
