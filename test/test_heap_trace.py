"""HeapTrace (nodes/heap_trace.py): the allocation site that grew after the baseline is named, and
nothing is traced or reported unless tracemalloc runs (``python -X tracemalloc``)."""

from __future__ import annotations

import tracemalloc

import pytest

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


# ---- HeapTrim: the C heap's freed memory back to the system -------------------------------------
def _rss_anon_mib() -> float:
    for line in open("/proc/self/status"):
        if line.startswith("RssAnon:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def test_the_trim_returns_freed_memory_that_a_live_block_pins_in_the_heap():
    # the nodes' pattern: memory freed below a live allocation stays resident (glibc trims only the
    # top of a heap) until malloc_trim gives its whole pages back

    from neural_estimator.nodes.heap_trace import HeapTrim

    trim = HeapTrim(10.0)
    if not trim.available:
        pytest.skip("no glibc malloc_trim in this C library")
    size = 1000  # a variable: b"x" * 1000 would be folded into one constant object
    blocks = [b"x" * size for _ in range(64_000)]  # 61 MiB of written malloc'ed blocks (over pymalloc's 512)
    pins = blocks[63::64]  # one live block every 64 KiB: the freed runs cannot leave from the top
    del blocks
    freed = _rss_anon_mib()
    assert trim() is True
    # about 60 MiB go back; without the trim they stay (the soak's "growth" after a backlog drained)
    assert freed - _rss_anon_mib() > 40
    assert len(pins) == 1000
    report = trim.report()
    assert report["calls"] == 1 and report["released"] == 1 and report["period_s"] == 10.0
    assert report["max_ms"] >= report["mean_ms"] > 0


def test_the_trim_period_comes_from_the_environment_and_a_bad_one_is_named():
    from neural_estimator.nodes.heap_trace import DEFAULT_HEAP_TRIM_PERIOD, HEAP_TRIM_ENV, heap_trim_period

    assert heap_trim_period({}) == DEFAULT_HEAP_TRIM_PERIOD == heap_trim_period({HEAP_TRIM_ENV: " "})
    assert heap_trim_period({HEAP_TRIM_ENV: "0"}) == 0.0 and heap_trim_period({HEAP_TRIM_ENV: "2.5"}) == 2.5
    for bad in ("soon", "-1", "nan", "inf"):
        with pytest.raises(ValueError, match=f"{HEAP_TRIM_ENV} must be seconds between heap trims.*{bad}"):
            heap_trim_period({HEAP_TRIM_ENV: bad})


_THRESHOLD_PROBE = """
import ctypes, sys
from neural_estimator.nodes.heap_trace import pin_malloc_thresholds

libc = ctypes.CDLL("libc.so.6")
libc.malloc.restype, libc.malloc.argtypes, libc.free.argtypes = ctypes.c_void_p, [ctypes.c_size_t], [ctypes.c_void_p]
libc.free(libc.malloc(8 << 20))  # mapped on its own; freeing it raises glibc's mmap threshold to 8 MiB
pinned = sys.argv[1] == "pin" and pin_malloc_thresholds({})
block = libc.malloc(1 << 20)  # a 1 MiB temporary
heap = next(line.split()[0] for line in open("/proc/self/maps") if line.rstrip().endswith("[heap]"))
lo, hi = (int(a, 16) for a in heap.split("-"))
print(pinned, lo <= block < hi)
"""


def test_pinned_thresholds_map_a_large_temporary_on_its_own_whatever_was_freed_before():
    # glibc raises its mmap threshold when a mapped block is freed: afterwards a 1 MiB temporary
    # is carved out of the heap, where its hole outlives it (the EKF node's heap grew 2.2 MiB in
    # 200 s with nothing in use growing). Pinned at 128 KiB (what every node does), it is mapped
    # on its own and unmapped when freed. A fresh process each: the thresholds are process-wide.
    import subprocess
    import sys
    from pathlib import Path

    def run(mode: str) -> str:
        out = subprocess.run(
            [sys.executable, "-c", _THRESHOLD_PROBE, mode],
            capture_output=True,
            text=True,
            timeout=60,
            cwd=Path(__file__).resolve().parents[1],
        )
        assert out.returncode == 0, out.stderr
        return out.stdout.strip()

    assert run("pin") == "True False"  # pinned: mapped on its own, outside the heap
    assert run("default") == "False True"  # glibc's dynamic threshold: inside the heap


def test_glibc_variables_set_by_the_user_are_left_alone():
    from neural_estimator.nodes.heap_trace import pin_malloc_thresholds

    assert pin_malloc_thresholds({"MALLOC_MMAP_THRESHOLD_": "65536"}) is False
    assert pin_malloc_thresholds({"MALLOC_TRIM_THRESHOLD_": "0"}) is False
