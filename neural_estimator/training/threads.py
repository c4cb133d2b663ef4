"""The thread count of a training, chosen by measuring it while the machine's load changes.

A training step with T > 1 threads finishes only when every OpenMP worker has been scheduled. On
an otherwise idle 2-core machine two threads train 1.2-1.5x faster than one; with another job on
the second core they train at 0.29-0.89x of one, whatever OpenMP's wait policy
(``benchmarks/bench_threads.py``, docs/performance.md). No fixed setting is right for both, and a
long training sees both. :class:`ThreadGovernor` measures instead: at the start and then every
``period`` seconds it times ``probe_steps`` training steps at each candidate count (1 and the
maximum asked for; the first step after a change is not timed), and trains at the count whose
median step was shortest until the next probe. A count whose timed step takes more than
``ABORT_FACTOR`` times the best median so far is dropped after that one step, so on a busy
machine a probe costs two steps at the slow count, not ``probe_steps + 1``.

The decision depends on the load, so a run with ``max_threads > 1`` is not bit-reproducible
across machines or runs (torch's CPU reductions depend on the thread count); ``max_threads = 1``
never changes the count and is.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from typing import Any


ABORT_FACTOR = 1.5  # a probed count whose step takes this much longer than the best so far is dropped at once


class ThreadGovernor:
    """Probe, choose, hold, re-probe; call :meth:`before_step` and :meth:`after_step` around each step.

    Args:
        max_threads: the most threads to use (1: the governor never changes anything).
        probe_steps: timed steps per candidate count in a probe.
        period: seconds between the end of one probe and the start of the next.
        set_threads: applies a count (default ``torch.set_num_threads``).
        clock: monotonic seconds (default ``time.perf_counter``).
    """

    def __init__(
        self,
        max_threads: int,
        probe_steps: int = 8,
        period: float = 300.0,
        set_threads: Callable[[int], None] | None = None,
        clock: Callable[[], float] = time.perf_counter,
    ) -> None:
        if max_threads < 1:
            raise ValueError(f"max_threads must be >= 1, got {max_threads}")
        if probe_steps < 1 or period <= 0:
            raise ValueError(f"probe_steps must be >= 1 and period > 0, got {probe_steps} and {period}")
        if set_threads is None:
            import torch

            set_threads = torch.set_num_threads
        self.candidates = sorted({1, int(max_threads)})
        self.probe_steps, self.period = int(probe_steps), float(period)
        self._set, self._clock = set_threads, clock
        self.current = self.candidates[-1]
        self._set(self.current)
        self.decisions: list[dict[str, Any]] = []  # {"at": seconds since start, "ms": {count: median}, "chose": n}
        self._t0 = clock()
        self._queue: list[int] = []  # counts still to probe in this probe
        self._times: dict[int, list[float]] = {}
        self._skip = 0  # untimed steps left at the count just set
        self._started: float | None = None
        self._next_probe = self._t0  # probe at the first step
        self.probing = False

    def before_step(self) -> None:
        """Set the count for the coming step (starting a probe when one is due)."""
        if len(self.candidates) == 1:
            return
        if not self.probing and self._clock() >= self._next_probe:
            self.probing, self._queue, self._times = True, list(self.candidates), {}
            self._switch(self._queue[0])
        self._started = self._clock()

    def after_step(self) -> None:
        """Record the step's time; end the probe when every count has its samples."""
        if len(self.candidates) == 1 or self._started is None:
            return
        elapsed, self._started = self._clock() - self._started, None
        if not self.probing:
            return
        if self._skip:
            self._skip -= 1
            return
        samples = self._times.setdefault(self.current, [])
        samples.append(elapsed)
        done = {n: statistics.median(t) for n, t in self._times.items() if n != self.current}
        clearly_slower = bool(done) and elapsed > ABORT_FACTOR * min(done.values())
        if len(samples) < self.probe_steps and not clearly_slower:
            return
        if clearly_slower:  # no need for more samples of a count that loses by that much
            self._queue = self._queue[:1]
        self._queue.pop(0)
        if self._queue:
            self._switch(self._queue[0])
            return
        medians = {n: statistics.median(t) for n, t in self._times.items()}
        best = min(medians, key=lambda n: (medians[n], n))  # a tie goes to fewer threads
        self._switch(best, skip=0)
        self.probing = False
        self._next_probe = self._clock() + self.period
        self.decisions.append(
            {
                "at": round(self._clock() - self._t0, 1),
                "ms": {str(n): round(1e3 * m, 2) for n, m in medians.items()},
                "chose": best,
            }
        )

    def _switch(self, n: int, skip: int = 1) -> None:
        if n != self.current:
            self._set(n)
            self.current = n
        self._skip = skip

    def summary(self) -> str:
        """One line: how many probes chose each count, and the last probe's medians."""
        if not self.decisions:
            return f"{self.current} thread(s)"
        chosen = {n: sum(d["chose"] == n for d in self.decisions) for n in self.candidates}
        last = self.decisions[-1]["ms"]
        return (
            f"threads chosen by measurement: {', '.join(f'{n} in {k} probe(s)' for n, k in chosen.items())}; "
            f"last probe, median ms a step: {', '.join(f'{n}: {m}' for n, m in last.items())}"
        )
