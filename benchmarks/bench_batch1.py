"""Classical filters at batch 1 (the live node's case) beside filterpy and DAPPER, on Lorenz 96.

    .venv/bin/python benchmarks/bench_batch1.py                      # EKF and EnKF, 10 and 40 variables
    .venv/bin/python benchmarks/bench_batch1.py --n-vars 40 --steps 300 --rounds 5
    .venv/bin/python benchmarks/bench_batch1.py --methods enkf --batch 1000   # + the batched EnKF

Per step, one trajectory (B = 1), the same simulated observations for every implementation:

- ours: ``Estimator.step`` in a loop (the node's call), p50 and p99 of the wall clock, and the mean;
- filterpy: :func:`neural_estimator.filters.reference.filterpy_ekf` / ``filterpy_enkf`` (N = our
  member count), total time / steps;
- DAPPER: ``ExtKF`` / ``EnKF('PertObs')`` through :func:`~neural_estimator.filters.reference.dapper_filter`,
  with its statistics switched off (``Stats.assess`` a no-op: DAPPER otherwise spends most of a step
  on its running statistics), total time / steps.

The peers get the scenario's own ``f`` and ``jac_f`` (as in the equality tests). Rounds alternate the
implementations; the best mean of the rounds is kept for each. Ratios are peer / ours (> 1: ours faster).

For the EnKF the table also shows "ours before": the batched numpy path (``compiled_max_batch = 0``)
with numpy's plain keyed generators (``Generator(SFC64(SeedSequence(seed, spawn_key=key)))`` built
per block and phase), i.e. the step as it was before the compiled single-stream kernels and the
fast seeding; it runs in the same rounds. ``--batch B`` adds the batched EnKF's throughput
(trajectory-steps per second, B streams, ``--batch-steps`` steps) now and before, in interleaved
rounds: the batched path keeps numpy's arithmetic, only its generators are set up faster.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import warnings
from contextlib import contextmanager
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
    ap.add_argument("--batch", type=int, default=0, help="also time the batched EnKF at this B (0: no)")
    ap.add_argument("--batch-steps", type=int, default=20)
    a = ap.parse_args(argv)
    warnings.filterwarnings("ignore")
    import dapper.stats
    import dapper.tools.progressbar

    from neural_estimator.data import simulate
    from neural_estimator.methods.registry import make_estimator
    from neural_estimator.filters import reference as ref
    from neural_estimator.scenarios import make_scenario

    dapper.stats.Stats.assess = lambda self, *args, **kw: None  # statistics off
    dapper.tools.progressbar.disable_progbar = True
    print(f"command: python benchmarks/bench_batch1.py {' '.join(argv if argv is not None else sys.argv[1:])}")
    print(f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f} at start; microseconds a step, B = 1\n")
    print(
        "| method | n | ours p50 / p99 | ours mean | ours before | filterpy | DAPPER "
        "| before / ours | filterpy / ours | DAPPER / ours |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for n in a.n_vars:
        scen = make_scenario("lorenz96", n_vars=n)
        d = simulate(scen, 1, a.steps, 0)
        y, u, x = d.y[0], d.u[0], d.x[0]
        for m in a.methods:
            est = make_estimator(m, scen, seed=0)
            members = int(getattr(getattr(est, "hp", None), "n_members", 50) or 50)
            best = {"ours": np.inf, "before": np.inf, "filterpy": np.inf, "dapper": np.inf}
            samples: list[float] = []
            old = make_estimator(m, scen, seed=0) if m == "enkf" else None
            for r in range(a.rounds + 1):  # round 0 warms up (numba compiles, caches fill)
                if old is not None:
                    old.compiled_max_batch = 0
                    with plain_generators():
                        old.reset(1)
                        t0 = time.perf_counter()
                        for k in range(a.steps):
                            old.step(y[k : k + 1])
                        if r:
                            best["before"] = min(best["before"], (time.perf_counter() - t0) / a.steps)
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
            o, b, f, dp = (best[key] * 1e6 for key in ("ours", "before", "filterpy", "dapper"))
            before = (f"{b:.0f}", f"{b / o:.1f}x") if np.isfinite(b) else ("-", "-")
            print(
                f"| {m} | {n} | {np.percentile(s, 50):.0f} / {np.percentile(s, 99):.0f} | {o:.0f} | {before[0]} "
                f"| {f:.0f} | {dp:.0f} | {before[1]} | {f / o:.1f}x | {dp / o:.1f}x |",
                flush=True,
            )
    if a.batch:
        batched_throughput(a, make_scenario, simulate, make_estimator)
    print(f"\nload average {os.getloadavg()[0]:.1f} at the end")
    return 0


@contextmanager
def plain_generators():
    """The keyed generators built the plain way (numpy's SeedSequence per block and phase), as before
    :class:`~neural_estimator.filters.seeding.KeyedSFC64`: the same numbers, about 40 us each."""
    from neural_estimator.filters.scheduler import BlockScheduler

    fast = BlockScheduler.rng

    def plain(self, step: int, phase: int, block: int) -> np.random.Generator:
        return np.random.Generator(np.random.SFC64(np.random.SeedSequence(self.seed, spawn_key=(step, phase, block))))

    BlockScheduler.rng = plain
    try:
        yield
    finally:
        BlockScheduler.rng = fast


def batched_throughput(a, make_scenario, simulate, make_estimator) -> None:
    """The batched EnKF, now and before, on ``--batch`` streams: trajectory-steps per second (best of
    the interleaved rounds), and the two agree bit for bit (the same numbers, the same arithmetic)."""
    print(f"\nbatched EnKF, B = {a.batch}, {a.batch_steps} steps, trajectory-steps per second (best of {a.rounds})\n")
    print("| n | now | before | now / before |")
    print("|---:|---:|---:|---:|")
    for n in a.n_vars:
        scen = make_scenario("lorenz96", n_vars=n)
        Y = simulate(scen, a.batch, a.batch_steps, 1).y
        best = {"now": 0.0, "before": 0.0}
        out = {}
        for r in range(a.rounds + 1):
            for which in ("now", "before") if r % 2 else ("before", "now"):  # alternate who goes first
                est = make_estimator("enkf", scen, seed=0)
                t0 = time.perf_counter()
                if which == "before":
                    with plain_generators():
                        out[which] = est.run(Y).x
                else:
                    out[which] = est.run(Y).x
                if r:
                    best[which] = max(best[which], a.batch * a.batch_steps / (time.perf_counter() - t0))
        same = "bit-equal" if np.array_equal(out["now"], out["before"]) else "DIFFERENT"
        print(
            f"| {n} | {best['now']:.0f} | {best['before']:.0f} | {best['now'] / best['before']:.2f}x ({same}) |",
            flush=True,
        )


if __name__ == "__main__":
    sys.exit(main())
