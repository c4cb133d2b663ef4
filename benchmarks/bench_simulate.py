"""Cost of simulating the paper's evaluation sets: 8,000 trajectories of the default horizon.

Times :func:`neural_estimator.data.simulate.simulate` (initial states including Lorenz 96's
spin-up, controls, and the step loop with both noises) for each scenario at its default constants
and horizon (500 steps; the quadrotor 200), and one call of ``jac_f`` at the same batch (what an
EKF pays per step). Wall-clock seconds, best of ``--repeats``.

    python benchmarks/bench_simulate.py                              # all five, n = 8000
    python benchmarks/bench_simulate.py --scenarios nlink,lorenz96 --n 2000 --repeats 3

Prints a markdown table and the command that produced it.
"""

from __future__ import annotations

import argparse
import os
import platform
import shlex
import sys
import time

import numpy as np

from neural_estimator.data.simulate import simulate
from neural_estimator.core.runtime import tune_allocator
from neural_estimator.scenarios import BUILTIN_SCENARIOS, make_scenario


def best_time(fn, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - start)
    return best


def bench(name: str, n: int, repeats: int, seed: int) -> dict[str, float]:
    s = make_scenario(name)
    horizon = s.horizon
    sim_s = best_time(lambda: simulate(s, n, horizon, seed=seed), repeats)
    rng = np.random.default_rng(seed)
    m0, _ = s.prior()
    x = np.broadcast_to(m0, (n, s.dx)) + 0.01 * rng.standard_normal((n, s.dx))
    u = s.sample_controls(rng, n, 1)[:, 0]
    jac_s = best_time(lambda: s.jac_f(x, u), repeats)
    return {"dx": s.dx, "dy": s.dy, "du": s.du, "T": horizon, "sim_s": sim_s, "jac_ms": 1e3 * jac_s}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenarios", default=",".join(BUILTIN_SCENARIOS), help="comma-separated names")
    parser.add_argument("--n", type=int, default=8000, help="trajectories per scenario")
    parser.add_argument("--repeats", type=int, default=1, help="best of this many runs")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    tuned = tune_allocator()  # as the CLI does (neural_estimator/core/runtime.py)

    rows = []
    for name in args.scenarios.split(","):
        r = bench(name.strip(), args.n, args.repeats, args.seed)
        rows.append((name.strip(), r))
        print(f"# {name}: {r['sim_s']:.2f} s", file=sys.stderr, flush=True)

    print(
        f"Simulating N = {args.n} trajectories (best of {args.repeats}); "
        f"numpy {np.__version__}, {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
        f"allocator tuned: {tuned}\n"
    )
    print(
        "| scenario | dx | dy | du | T | simulate [s] | trajectory-steps / s | ms / step (batch N) "
        "| jac_f [ms] (batch N) |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for name, r in rows:
        steps = args.n * r["T"]
        print(
            f"| {name} | {r['dx']} | {r['dy']} | {r['du']} | {r['T']} | {r['sim_s']:.2f} | "
            f"{steps / r['sim_s']:,.0f} | {1e3 * r['sim_s'] / r['T']:.2f} | {r['jac_ms']:.1f} |"
        )
    words = [sys.argv[0], *(argv if argv is not None else sys.argv[1:])]
    print("\ncommand: python " + " ".join(shlex.quote(w) for w in words))


if __name__ == "__main__":
    main()
