"""How much of a model's RMSE comes from the warm-up steps its training loss ignores.

    .venv/bin/python benchmarks/warmup_share.py                                   # Lorenz 96, shipped models
    .venv/bin/python benchmarks/warmup_share.py --checkpoint mamba2=zoo_training/lorenz96-mamba2

The paper's loss skips the first 10 timesteps of every window ("warm-up"); its RMSE, and ours
(neural_estimator.metrics: every timestep counts), covers the whole horizon. For each method this
prints the RMSE over all steps (plain, before the outlier rule), over the first ``--warmup`` steps
and over the rest, on evaluation set 0 (``--trajectories`` of them), so the part of the aggregate
that the training never optimised is visible. Output of the default run (the shipped models):
benchmarks/results/warmup_share.txt.
"""

from __future__ import annotations

import argparse

import numpy as np

from neural_estimator.data import evaluation_sets
from neural_estimator.estimators import make_estimator
from neural_estimator.scenarios import make_scenario


def split_rmse(x: np.ndarray, x_hat: np.ndarray, warmup: int) -> tuple[float, float, float]:
    """RMSE over all steps, over t < warmup and over t >= warmup (errors pooled over trajectories)."""
    e2 = ((x_hat - x) ** 2).mean(axis=(0, 2))  # (T,)
    return float(np.sqrt(e2.mean())), float(np.sqrt(e2[:warmup].mean())), float(np.sqrt(e2[warmup:].mean()))


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenario", default="lorenz96")
    p.add_argument("--methods", default="ukf,gru,lstm,gpt2,filterformer,mamba,mamba2")
    p.add_argument("--checkpoint", action="append", default=[], help="METHOD=DIR (repeatable): add that model")
    p.add_argument("--trajectories", type=int, default=200)
    p.add_argument("--warmup", type=int, default=10, help="the paper's loss warm-up")
    args = p.parse_args(argv)
    scenario = make_scenario(args.scenario)
    data = evaluation_sets(scenario, seed=0, trajectories=args.trajectories, sets=1, cache_dir=False)[0]
    runs = [(m, m, None) for m in args.methods.split(",")]
    for spec in args.checkpoint:
        method, _, path = spec.partition("=")
        runs.append((f"{method} ({path})", method, path))
    print(f"{args.scenario}, {args.trajectories} trajectories x {data.horizon} steps, warm-up {args.warmup}")
    print(f"{'method':<44} {'all steps':>10} {'t < warm-up':>12} {'t >= warm-up':>13}")
    for label, method, path in runs:
        est = make_estimator(method, scenario, **({"checkpoint": path} if path else {}))
        out = est.run(data.y, data.u)
        a, b, c = split_rmse(data.x, np.asarray(out.x), args.warmup)
        print(f"{label:<44} {a:>10.4f} {b:>12.3f} {c:>13.4f}", flush=True)


if __name__ == "__main__":
    main()
