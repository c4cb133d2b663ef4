"""CPU cost of the paper's classical protocol, from one-thread CPU time per trajectory-step.

    .venv/bin/python benchmarks/bench_protocol.py                      # all five scenarios, ~1 min
    .venv/bin/python benchmarks/bench_protocol.py --scenarios nlink --pf-paths numpy,compiled

For each (scenario, filter) the filter runs ``--batch`` trajectories (the PF ``--pf-batch``) for
``--steps`` steps on ONE thread after a short warm-up (the compiled kernels' first call), and the
process CPU time (``time.process_time``) per trajectory-step is kept, the fastest of ``--repeats``.
CPU time, not wall time: on a shared machine another process's load stretches wall time but
hardly the CPU time a computation needs. The protocol (3 sets x 8,000 trajectories x the
scenario's horizon) then costs ``24,000 T t`` CPU-seconds, and the wall-time estimate divides the
sum by ``--cores`` (2): the protocol's runs are independent (Ray tasks in ``reproduce``, or the
filters' worker threads), so they spread over the cores. ``--pf-paths numpy,compiled`` times the
PF's numpy reference path beside the compiled kernels in the same run.
"""

from __future__ import annotations

import argparse
import os
import sys

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import platform  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from neural_estimator.data.simulate import simulate  # noqa: E402
from neural_estimator.methods.registry import make_estimator  # noqa: E402
from neural_estimator.scenarios import BUILTIN_SCENARIOS, make_scenario  # noqa: E402

SETS, TRAJECTORIES = 3, 8000


def cpu_per_step(method: str, scenario, y: np.ndarray, u: np.ndarray, repeats: int, **options) -> float:
    """Fastest process CPU seconds per trajectory-step of ``method.run`` over (y, u), one thread."""
    est = make_estimator(method, scenario, seed=0, threads=1, **options)
    est.run(y[:, :2], u[:, :2])  # warm-up: compiled kernels, allocator
    best = float("inf")
    for _ in range(repeats):
        t0 = time.process_time()
        est.run(y, u)
        best = min(best, time.process_time() - t0)
    return best / (y.shape[0] * y.shape[1])


def fmt_duration(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.1f} min"
    return f"{seconds / 3600:.2f} h"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--scenarios", default=",".join(BUILTIN_SCENARIOS))
    p.add_argument("--methods", default="ekf,ukf,enkf,pf")
    p.add_argument("--pf-paths", default="compiled", help="comma-separated: compiled, numpy")
    p.add_argument("--batch", type=int, default=1000, help="trajectories for the EKF, UKF and EnKF (1000)")
    p.add_argument("--pf-batch", type=int, default=64, help="trajectories for the PF (64)")
    p.add_argument("--steps", type=int, default=20, help="time steps timed (20)")
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--cores", type=int, default=2, help="cores the protocol's runs spread over (2)")
    a = p.parse_args(argv)

    scenarios = a.scenarios.split(",")
    columns = []
    for m in a.methods.split(","):
        columns += [(m, path) for path in a.pf_paths.split(",")] if m == "pf" else [(m, None)]
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print("# Classical protocol cost (CPU time per trajectory-step, one thread)\n")
    print(
        f"`python benchmarks/bench_protocol.py {' '.join(argv if argv is not None else sys.argv[1:])}`; "
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, load average {load:.1f} at start\n"
    )
    head = [f"{m} ({path})" if path else m for m, path in columns]
    print("| scenario | T | " + " | ".join(head) + " |")
    print("|---|---:|" + "---:|" * len(columns))
    totals = dict.fromkeys(head, 0.0)
    for name in scenarios:
        s = make_scenario(name)
        T = s.horizon
        big = simulate(s, a.batch, a.steps, seed=1)
        cells = []
        for (m, path), label in zip(columns, head):
            n = a.pf_batch if m == "pf" else a.batch
            opts = {"compiled": path == "compiled"} if m == "pf" else {}
            t = cpu_per_step(m, s, big.y[:n], big.u[:n], a.repeats, **opts)
            cpu = SETS * TRAJECTORIES * T * t
            totals[label] += cpu
            unit = f"{t * 1e6 / 1024:.3f} µs/particle" if m == "pf" else f"{t * 1e6:.2f} µs"
            cells.append(f"{unit}, {fmt_duration(cpu)} CPU")
        print(f"| {name} | {T} | " + " | ".join(cells) + " |", flush=True)
    print("| **CPU total** | | " + " | ".join(fmt_duration(v) for v in totals.values()) + " |")
    print(f"| **wall on {a.cores} cores** | | " + " | ".join(fmt_duration(v / a.cores) for v in totals.values()) + " |")
    chosen = [label for (m, path), label in zip(columns, head) if path in (None, "compiled")]
    wall = sum(totals[c] for c in chosen) / a.cores
    print(
        f"\nThe protocol with {', '.join(chosen)}: {fmt_duration(wall)} on {a.cores} cores "
        f"(load average {os.getloadavg()[0]:.1f} at the end)."
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
