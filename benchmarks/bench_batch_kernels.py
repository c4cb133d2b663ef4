"""Does batching pay? The EKF and the EnKF on Lorenz 96, time per trajectory at B = 1 and at a large
batch, on the compiled kernels (filters/kernels/ekf.py, filters/kernels/enkf.py) and on the
batched numpy path (``compiled_max_batch = 0``), in one process, rounds interleaved.

A batch should never cost more per trajectory than one stream does. The figures are the process's
CPU seconds per trajectory (on a shared machine the wall clock also counts the waits for a core) of
``--steps`` steps (``Estimator.run``), best of ``--rounds`` rounds; the large batch runs once per
round, B = 1 runs ``--single`` trajectories one at a time. The compiled and batched results of the
large batch are compared (largest absolute difference printed).

Run: python benchmarks/bench_batch_kernels.py [--n-vars 40] [--batch 1000] [--threads 1]
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from neural_estimator.data import simulate
from neural_estimator.filters.ekf import ExtendedKalmanFilter
from neural_estimator.filters.enkf import EnsembleKalmanFilter
from neural_estimator.scenarios import make_scenario

FILTERS = {"ekf": ExtendedKalmanFilter, "enkf": EnsembleKalmanFilter}


def per_trajectory(method: str, scenario, Y: np.ndarray, compiled: bool, threads: int) -> tuple[float, np.ndarray]:
    """Seconds per trajectory of ``run`` over Y (B, T, dy), and the estimates."""
    est = FILTERS[method](scenario, threads=threads, **({"seed": 0} if method == "enkf" else {}))
    if not compiled:
        est.compiled_max_batch = 0
    t0 = time.process_time()
    out = est.run(Y)
    return (time.process_time() - t0) / Y.shape[0], out.x


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n-vars", type=int, default=40)
    ap.add_argument("--batch", type=int, default=1000)
    ap.add_argument("--single", type=int, default=8, help="trajectories run one at a time for B = 1")
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args()
    scenario = make_scenario("lorenz96", n_vars=a.n_vars)
    Y = simulate(scenario, a.batch, a.steps, seed=3).y
    for method in FILTERS:  # compile (or load) the kernels outside the timing
        per_trajectory(method, scenario, Y[:2], True, a.threads)
    best: dict[tuple[str, str, str], float] = {}
    diff = {}
    for _ in range(a.rounds):
        for method in FILTERS:
            for path, compiled in (("compiled", True), ("batched numpy", False)):
                one = np.mean(
                    [per_trajectory(method, scenario, Y[i : i + 1], compiled, a.threads)[0] for i in range(a.single)]
                )
                many, x = per_trajectory(method, scenario, Y, compiled, a.threads)
                for key, t in (((method, path, "1"), one), ((method, path, str(a.batch)), many)):
                    best[key] = min(best.get(key, np.inf), t)
                diff.setdefault(method, {})[path] = x
    print(
        f"Lorenz 96 n = {a.n_vars}, {a.steps} steps, {a.threads} thread(s), best of {a.rounds} rounds, "
        f"load average {os.getloadavg()[0]:.2f}"
    )
    print(f"| filter | path | CPU ms / trajectory at B = 1 | at B = {a.batch} | B = {a.batch} vs B = 1 |")
    print("|---|---|---:|---:|---:|")
    for (method, path, batch), t in best.items():
        if batch != "1":
            continue
        big = best[(method, path, str(a.batch))]
        print(f"| {method} | {path} | {t * 1e3:.3f} | {big * 1e3:.3f} | {t / big:.2f}x faster |")
    for method, paths in diff.items():
        d = np.nanmax(np.abs(paths["compiled"] - paths["batched numpy"]))
        print(f"{method}: compiled and batched estimates at B = {a.batch} differ by at most {d:.1e}")


if __name__ == "__main__":
    main()
