"""Runs a kernel over a batch of independent streams, block by block, on worker threads.

It knows nothing of filtering: a kernel is any function of arrays whose axis 0 is the stream
(B, ...). The B streams are cut into blocks of ``block_size`` consecutive streams; the blocks of one
call run concurrently on ``threads`` threads (numpy releases the GIL in its array loops, LAPACK and
BLAS calls), and one block (B = 1, the live node's case) runs on the calling thread with no copies.

Random numbers never depend on the scheduling: a block's generator is keyed by (seed, step,
phase, block index) through a SeedSequence (:meth:`BlockScheduler.rng`), so the threads' order and
count change nothing, and a draw of shape (rows, ...) fills row after row, so stream b receives the
same numbers in a batch of any size B > b.

Kernel convention of :meth:`BlockScheduler.blockwise`: ``kernel(*block_arrays) -> (out_1, ..., out_j,
ok)`` with ok (b,) per-stream flags or None (all ok); the outputs are assembled to (B, ...).
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from neural_estimator.filters.seeding import KeyedSFC64

THREADS_ENV = "NEURAL_ESTIMATOR_THREADS"


class ThreadsError(ValueError):
    """A thread count that is not an integer >= 1; the message names where it came from."""


def check_threads(where: str, threads: int | str) -> int:
    """``threads`` as an int >= 1 (strings from the command line parse), else ThreadsError."""
    try:
        n = int(threads)
    except (TypeError, ValueError):
        n = 0
    if n < 1 or isinstance(threads, (bool, float)):
        raise ThreadsError(f"{where}: threads must be an integer >= 1, got {threads!r}")
    return n


def default_threads() -> int:
    """Worker threads for the blocks of streams: $NEURAL_ESTIMATOR_THREADS, else the usable cores."""
    env = os.environ.get(THREADS_ENV, "").strip()
    if env:
        return check_threads(f"${THREADS_ENV}", env)
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - platforms without sched_getaffinity
        return max(1, os.cpu_count() or 1)


_POOLS: dict[int, ThreadPoolExecutor] = {}
_POOLS_LOCK = threading.Lock()


def _pool(threads: int) -> ThreadPoolExecutor:
    """One shared pool per thread count (schedulers are built per chunk; their threads are not)."""
    with _POOLS_LOCK:
        pool = _POOLS.get(threads)
        if pool is None:
            pool = _POOLS[threads] = ThreadPoolExecutor(threads, thread_name_prefix="neural-estimator-filter")
        return pool


def _quiet(fn: Callable[[], Any]) -> Any:
    """``fn()`` with numpy's floating-point warnings off: diverging streams overflow by design and
    are flagged by the caller; the error state is per thread, so workers set their own."""
    with np.errstate(over="ignore", invalid="ignore", divide="ignore", under="ignore"):
        return fn()


def _ordered_map(pool: ThreadPoolExecutor, fn: Callable[[Any], Any], items: Sequence[Any], ahead: int) -> Iterator[Any]:
    """``map(fn, items)`` on ``pool`` in order, at most ``ahead`` items in flight (bounded memory)."""
    pending = []
    it = iter(items)
    for item in it:
        pending.append(pool.submit(_quiet, lambda item=item: fn(item)))
        if len(pending) >= ahead:
            break
    for item in it:
        yield pending.pop(0).result()
        pending.append(pool.submit(_quiet, lambda item=item: fn(item)))
    for fut in pending:
        yield fut.result()


class BlockScheduler:
    """The blocks of a batch of ``batch`` streams and the threads that run them.

    Args:
        batch: B, the number of streams.
        block_size: streams per block (the last block may be shorter).
        threads: worker threads (1: everything on the calling thread).
        seed: the seed of :meth:`rng`.
    """

    def __init__(self, batch: int, block_size: int, threads: int, seed: int) -> None:
        self.batch = int(batch)
        self.threads = int(threads)
        self.seed = int(seed)
        size = max(1, int(block_size))
        self.blocks = [slice(i, min(i + size, self.batch)) for i in range(0, self.batch, size)]
        self.keyed = KeyedSFC64(self.seed)

    def rng(self, step: int, phase: int, block: int) -> np.random.Generator:
        """The generator of one block's draws in one phase of one step, keyed by (seed, step, phase,
        block): ``Generator(SFC64(SeedSequence(seed, spawn_key=(step, phase, block))))``, in that
        very state, set up by :class:`~neural_estimator.filters.seeding.KeyedSFC64` (4 us instead
        of 40). The object is reused per (phase, block): valid until the next call for the same
        phase and block. SFC64: the fastest of numpy's generators for normal draws, a fifth faster
        than PCG64 here."""
        return self.keyed.generator((step, phase, block), (phase, block))

    def map(self, fn: Callable[[int], Any]) -> Iterator[Any]:
        """fn(i) for every block i, in order: on the calling thread for one block or one thread,
        else on the worker threads, at most two blocks per thread in flight (bounded memory)."""
        n = len(self.blocks)
        if n == 1 or self.threads == 1:
            return map(fn, range(n))
        return _ordered_map(_pool(self.threads), fn, range(n), ahead=2 * self.threads)

    def for_each(self, kernel: Callable[[int, slice], Any]) -> list:
        """[kernel(i, slice_i) for every block i]; for kernels that write their block in place."""
        return list(self.map(lambda i: kernel(i, self.blocks[i])))

    def draw(self, step: int, phase: int, draw: Callable[[np.random.Generator, int], np.ndarray]) -> np.ndarray:
        """(B, ...) draws assembled from ``draw(rng, rows)`` block by block (on the calling thread)."""
        parts = [draw(self.rng(step, phase, i), sl.stop - sl.start) for i, sl in enumerate(self.blocks)]
        return parts[0] if len(parts) == 1 else np.concatenate(parts, axis=0)

    def blockwise(
        self,
        kernel: Callable[..., tuple],
        *arrays: np.ndarray,
        rng_for: Callable[[int], np.random.Generator] | None = None,
    ) -> tuple:
        """Apply ``kernel(*block_arrays) -> (out_1, ..., out_j, ok)`` block by block of streams.

        Every array has the streams on axis 0; outputs are assembled to (B, ...) and ok flags to
        (B,) (None when every stream is ok). One block: the kernel's own outputs, no copies.
        With ``rng_for``, the kernel also gets the block's generator ``rng_for(i)`` as ``rng=``.
        """
        blocks = self.blocks
        if len(blocks) == 1:  # the whole batch is one block (B = 1 in the live node): a plain call
            return kernel(*arrays) if rng_for is None else kernel(*arrays, rng=rng_for(0))

        def one(i: int) -> tuple:
            views = (a[blocks[i]] for a in arrays)
            if rng_for is None:
                return kernel(*views)
            return kernel(*views, rng=rng_for(i))

        results = self.map(one)
        outs: list = []
        ok_full = None
        for sl, (*res, ok) in zip(blocks, results):
            if not outs:
                outs = [np.empty((self.batch,) + r.shape[1:], dtype=r.dtype) for r in res]
            for o, r in zip(outs, res):
                o[sl] = r
            if ok is not None and not ok.all():
                if ok_full is None:
                    ok_full = np.ones(self.batch, dtype=bool)
                ok_full[sl] = ok
        return (*outs, ok_full)
