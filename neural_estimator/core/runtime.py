"""Process-wide settings that make the batched numpy code fast; called by the entry points.

numpy allocates a fresh array for every intermediate result. The filters' and simulators'
intermediates are 0.1 to 10 MiB (a block of sigma points, members or particles), and glibc's
malloc, with its default dynamic thresholds, hands such blocks back to the operating system when
they are freed (the heap's top is trimmed once more than twice the largest recently freed block is
free) and takes them back at the next call, page by page. Measured with and without the two
settings below: simulating 8,000 Lorenz 96 trajectories x 200 steps 9.0 s -> 3.9 s; the PF and
EnKF on Lorenz 96 7-8 % faster; Lorenz 96 f alone on 40 streams x 81 sigma points 102 -> 28 us per
stream (docs/performance.md).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

# mallopt parameters (glibc's malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3

MMAP_THRESHOLD = 64 * 2**20  # blocks below this come from the heap (and are reused), not from mmap
TRIM_THRESHOLD = 256 * 2**20  # free memory at the heap's top kept for reuse, not returned to the OS

_tuned: bool | None = None


def tune_allocator() -> bool:
    """Keep freed memory for reuse instead of returning it to the OS (glibc only; idempotent).

    The cost: a process keeps up to ``TRIM_THRESHOLD`` of freed heap in its resident set, and
    blocks below ``MMAP_THRESHOLD`` are served from the heap. Returns True when the settings took
    effect, False where they do not apply (not Linux/glibc) or were refused.
    """
    global _tuned
    if _tuned is not None:
        return _tuned
    _tuned = False
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # musl and others: no mallopt
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    _tuned = bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD))
    return _tuned


WAIT_POLICY = {"OMP_WAIT_POLICY": "PASSIVE", "KMP_BLOCKTIME": "0"}  # libgomp (torch's Linux wheels), Intel OpenMP


def cooperative_threads() -> bool:
    """Make OpenMP worker threads sleep instead of spin while they wait (unless the environment says
    otherwise): on a machine whose other cores are busy, a spinning worker takes a core from the
    process that holds the lock it waits for, and two threads ran one training 5-7x slower than one
    (benchmarks/bench_threads.py). OpenMP reads these variables once, when torch loads it, so this
    must run before ``import torch``; returns False (and changes nothing) when torch is already loaded.
    """
    import os

    if "torch" in sys.modules:
        return False
    for name, value in WAIT_POLICY.items():
        os.environ.setdefault(name, value)
    return True
