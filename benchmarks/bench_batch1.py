"""Classical filters at batch 1 (the live node's case) beside filterpy and DAPPER, on Lorenz 96.

    .venv/bin/python benchmarks/bench_batch1.py                      # EKF and EnKF, 10 and 40 variables
    .venv/bin/python benchmarks/bench_batch1.py --n-vars 40 --steps 300 --rounds 5

Per step, one trajectory (B = 1), the same simulated observations for every implementation:

- ours: ``Estimator.step`` in a loop (the node's call), p50 and p99 of the wall clock, and the mean;
- filterpy: :func:`neural_estimator.filters.reference.filterpy_ekf` / ``filterpy_enkf`` (N = our
  member count), total time / steps;
- DAPPER: ``ExtKF`` / ``EnKF('PertObs')`` through :func:`~neural_estimator.filters.reference.dapper_filter`,
  with its statistics switched off (``Stats.assess`` a no-op: DAPPER otherwise spends most of a step
  on its running statistics), total time / steps.

The peers get the scenario's own ``f`` and ``jac_f`` (as in the equality tests). Rounds alternate the
implementations; the best mean of the rounds is kept for each. Ratios are peer / ours (> 1: ours faster).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n-vars", type=int, nargs="+", default=[10, 40])
    ap.add_argument("--methods", nargs="+", default=["ekf", "enkf"])
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--rounds", type=int, default=3)
    a = ap.parse_args(argv)
    warnings.filterwarnings("ignore")
    import dapper.stats
    import dapper.tools.progressbar

    from neural_estimator.data import simulate
    from neural_estimator.registry import make_estimator
    from neural_estimator.filters import reference as ref
    from neural_estimator.scenarios import make_scenario

    dapper.stats.Stats.assess = lambda self, *args, **kw: None  # statistics off
    dapper.tools.progressbar.disable_progbar = True
    print(f"command: python benchmarks/bench_batch1.py {' '.join(argv if argv is not None else sys.argv[1:])}")
    print(f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f} at start; microseconds a step, B = 1\n")
    print("| method | n | ours p50 / p99 | ours mean | filterpy | DAPPER | filterpy / ours | DAPPER / ours |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for n in a.n_vars:
        scen = make_scenario("lorenz96", n_vars=n)
        d = simulate(scen, 1, a.steps, 0)
        y, u, x = d.y[0], d.u[0], d.x[0]
        for m in a.methods:
            est = make_estimator(m, scen, seed=0)
            members = int(getattr(getattr(est, "hp", None), "n_members", 50) or 50)
            best = {"ours": np.inf, "filterpy": np.inf, "dapper": np.inf}
            samples: list[float] = []
            for r in range(a.rounds + 1):  # round 0 warms up (numba compiles, caches fill)
                est.reset(1)
                t_all = time.perf_counter()
                for k in range(a.steps):
                    t0 = time.perf_counter()
                    est.step(y[k : k + 1])
                    if r:
                        samples.append(time.perf_counter() - t0)
                best["ours"] = min(best["ours"], (time.perf_counter() - t_all) / a.steps) if r else best["ours"]
                t0 = time.perf_counter()
                if m == "ekf":
                    ref.filterpy_ekf(scen, y, u)
                else:
                    ref.filterpy_enkf(scen, y, u, N=members, seed=r)
                if r:
                    best["filterpy"] = min(best["filterpy"], (time.perf_counter() - t0) / a.steps)
                t0 = time.perf_counter()
                if m == "ekf":
                    ref.dapper_filter(scen, x, y, "ExtKF", seed=r, infl=1.0)
                else:
                    ref.dapper_filter(scen, x, y, "EnKF", seed=r, upd_a="PertObs", N=members, infl=1.0)
                if r:
                    best["dapper"] = min(best["dapper"], (time.perf_counter() - t0) / a.steps)
            s = np.asarray(samples) * 1e6
            o, f, dp = best["ours"] * 1e6, best["filterpy"] * 1e6, best["dapper"] * 1e6
            print(
                f"| {m} | {n} | {np.percentile(s, 50):.0f} / {np.percentile(s, 99):.0f} | {o:.0f} | {f:.0f} | {dp:.0f} "
                f"| {f / o:.1f}x | {dp / o:.1f}x |",
                flush=True,
            )
    print(f"\nload average {os.getloadavg()[0]:.1f} at the end")
    return 0


if __name__ == "__main__":
    sys.exit(main())
