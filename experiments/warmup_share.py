"""How much of a model's RMSE comes from the warm-up steps its training loss ignores.

    .venv/bin/python experiments/warmup_share.py                                   # Lorenz 96, shipped models
    .venv/bin/python experiments/warmup_share.py --checkpoint mamba2=zoo_training/lorenz96-mamba2
    .venv/bin/python experiments/warmup_share.py --scenario nlink --segments 0,10,100,200,300,400,500

The paper's loss skips the first 10 timesteps of every window ("warm-up"), and so do the package's
metrics (neural_estimator.metrics, "Effective trajectory length"; `--warmup 0` counts every
step). For each method this
prints the RMSE over all steps (plain, before the outlier rule), over the first ``--warmup`` steps
and over the rest, on evaluation set 0 (``--trajectories`` of them), so the part of the aggregate
that the training never optimised is visible. Output of the default run (the shipped models):
experiments/results/warmup_share.txt. With ``--segments`` it prints the RMSE over each segment of the
horizon instead, which shows whether a model trained on length-100 windows stays as good beyond
step 100 (experiments/results/horizon_segments.txt).
"""

from __future__ import annotations

import argparse

import numpy as np

from neural_estimator.data import evaluation_sets
from neural_estimator.methods.registry import make_estimator
from neural_estimator.scenarios import make_scenario


def step_mse(x: np.ndarray, x_hat: np.ndarray, angle_states=()) -> np.ndarray:
    """(T,) squared error per step, pooled over trajectories and components (angles wrapped to (-pi, pi])."""
    e = np.asarray(x_hat, dtype=np.float64) - x
    for i in angle_states:
        e[..., i] = np.pi - np.mod(np.pi - e[..., i], 2 * np.pi)
    return (e**2).mean(axis=(0, 2))


def split_rmse(x: np.ndarray, x_hat: np.ndarray, warmup: int, angle_states=()) -> tuple[float, float, float]:
    """RMSE over all steps, over t < warmup and over t >= warmup (errors pooled over trajectories)."""
    e2 = step_mse(x, x_hat, angle_states)
    return float(np.sqrt(e2.mean())), float(np.sqrt(e2[:warmup].mean())), float(np.sqrt(e2[warmup:].mean()))


def segment_rmse(x: np.ndarray, x_hat: np.ndarray, bounds: list[int], angle_states=()) -> list[float]:
    """RMSE over each segment [bounds[i], bounds[i+1]) of the horizon (errors pooled over trajectories)."""
    e2 = step_mse(x, x_hat, angle_states)
    return [float(np.sqrt(e2[a:b].mean())) for a, b in zip(bounds, bounds[1:])]


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenario", default="lorenz96")
    p.add_argument("--methods", default="ukf,gru,lstm,gpt2,filterformer,mamba,mamba2")
    p.add_argument("--checkpoint", action="append", default=[], help="METHOD=DIR (repeatable): add that model")
    p.add_argument("--trajectories", type=int, default=200)
    p.add_argument("--warmup", type=int, default=10, help="the paper's loss warm-up")
    p.add_argument(
        "--segments",
        default=None,
        help="comma-separated step bounds, e.g. 0,10,100,200,300,400,500: RMSE per horizon segment instead "
        "(does a model trained on length-100 windows stay as good beyond step 100?)",
    )
    args = p.parse_args(argv)
    scenario = make_scenario(args.scenario)
    data = evaluation_sets(scenario, seed=0, trajectories=args.trajectories, sets=1, cache_dir=False)[0]
    runs = [(m, m, None) for m in args.methods.split(",")]
    for spec in args.checkpoint:
        method, _, path = spec.partition("=")
        runs.append((f"{method} ({path})", method, path))
    bounds = [int(b) for b in args.segments.split(",")] if args.segments else None
    if bounds is not None and (bounds != sorted(set(bounds)) or bounds[0] < 0 or bounds[-1] > data.horizon):
        p.error(f"--segments must increase within 0..{data.horizon}, got {args.segments}")
    if bounds is None:
        print(f"{args.scenario}, {args.trajectories} trajectories x {data.horizon} steps, warm-up {args.warmup}")
        print(f"{'method':<44} {'all steps':>10} {'t < warm-up':>12} {'t >= warm-up':>13}")
    else:
        print(f"{args.scenario}, {args.trajectories} trajectories x {data.horizon} steps, RMSE per segment of steps")
        print(f"{'method':<44} " + " ".join(f"{f'{a}-{b}':>9}" for a, b in zip(bounds, bounds[1:])))
    for label, method, path in runs:
        est = make_estimator(method, scenario, **({"checkpoint": path} if path else {}))
        x_hat = np.asarray(est.run(data.y, data.u).x)
        if bounds is None:
            a, b, c = split_rmse(data.x, x_hat, args.warmup, scenario.angle_states)
            print(f"{label:<44} {a:>10.4f} {b:>12.3f} {c:>13.4f}", flush=True)
        else:
            segs = segment_rmse(data.x, x_hat, bounds, scenario.angle_states)
            print(f"{label:<44} " + " ".join(f"{v:>9.4f}" for v in segs), flush=True)


if __name__ == "__main__":
    main()
