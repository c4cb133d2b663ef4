"""Real-time scheduling of a node process: SCHED_FIFO at the priority the environment names.

On a machine whose cores other work shares (a training, the rest of a robot's stack), a node that
is woken by a message still waits for the scheduler to give it a core, and at 1 kHz those waits
are the end-to-end delay: the EKF + GRU + Mamba chain behind one simulator had p99 18-79 ms beside
two trainings (load 5) where an idle machine gives 3-5 ms. Under SCHED_FIFO a woken node runs at
once, ahead of every normal process: the same chain, same load, p99 0.7-1.1 ms
(``benchmarks/bench_pipeline.py --realtime-priority 10``, docs/performance.md).

``NEURAL_ESTIMATOR_REALTIME_PRIORITY=N`` (1-99; unset, empty or 0: off) puts a node's process on
SCHED_FIFO at priority N before ``rclpy.init``, so the middleware's threads, created later,
inherit it. It needs the right to (root, CAP_SYS_NICE, or an ``rtprio`` limit of at least N in
``/etc/security/limits.conf``); refused, the node says so in one line and runs at normal
priority. The kernel's real-time throttling (``/proc/sys/kernel/sched_rt_runtime_us``, 95 % of
each second by default) keeps a runaway real-time thread from locking the machine. This module
imports no rclpy.
"""

from __future__ import annotations

import os
from collections.abc import Mapping

REALTIME_ENV = "NEURAL_ESTIMATOR_REALTIME_PRIORITY"
MAX_PRIORITY = 99  # SCHED_FIFO's range on Linux is 1-99
_RANGE = f"{REALTIME_ENV} must be an integer from 1 to {MAX_PRIORITY} (0: off)"


class RealtimeError(ValueError):
    """The environment names no valid priority: one line naming the variable and the value."""


def requested_priority(environ: Mapping[str, str] | None = None) -> int:
    """The priority ``NEURAL_ESTIMATOR_REALTIME_PRIORITY`` asks for; 0 when unset, empty or 0."""
    env = os.environ if environ is None else environ
    raw = env.get(REALTIME_ENV, "").strip()
    if not raw:
        return 0
    try:
        value = int(raw)
    except ValueError:
        raise RealtimeError(
            f"{REALTIME_ENV} must be an integer from 1 to {MAX_PRIORITY} (0: off), got {raw!r}"
        ) from None
    if not 0 <= value <= MAX_PRIORITY:
        raise RealtimeError(f"{_RANGE}, got {value}")
    return value


def apply_realtime_priority(priority: int) -> tuple[bool, str]:
    """Put the calling process's thread on SCHED_FIFO at ``priority`` (threads it creates later
    inherit it); returns (applied, one line saying what happened)."""
    if priority <= 0:
        return False, "normal scheduling"
    if not hasattr(os, "sched_setscheduler"):
        return (
            False,
            f"{REALTIME_ENV}={priority}: real-time scheduling is not available on this system; normal priority",
        )
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except PermissionError:
        return False, (
            f"{REALTIME_ENV}={priority}: SCHED_FIFO refused (needs root, CAP_SYS_NICE or an rtprio limit "
            f">= {priority}, see `ulimit -r`); running at normal priority"
        )
    except OSError as exc:
        return False, f"{REALTIME_ENV}={priority}: SCHED_FIFO refused ({exc.strerror}); running at normal priority"
    return True, f"real-time scheduling: SCHED_FIFO priority {priority} ({REALTIME_ENV})"
