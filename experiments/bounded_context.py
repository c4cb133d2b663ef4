"""Is an SSM's loss of accuracy beyond its training windows a matter of context length?

    .venv/bin/python experiments/bounded_context.py --scenario nlink --model zoo_training/normalised/nlink-mamba2
    .venv/bin/python experiments/bounded_context.py --scenario nlink \
        --model zoo_training/normalised/nlink-mamba2 \
        --weights zoo_training/normalised/nlink-mamba2/resume/model.safetensors   # its last epoch

The paper trains on length-100 windows and evaluates over 500 steps. A model whose recurrent state
drifts once it has run longer than any window it was trained on (the N-link Mamba-2 trained on the paper's
recipe, see docs/training.md) is accurate inside 100 steps of context and not beyond. This diagnostic runs one
model two ways on evaluation set 0 and prints the RMSE per segment of the horizon:

* ``continuous``: over the whole trajectory from step 0, as every evaluation does (the paper's way);
* ``bounded L/K``: K copies of the model, copy k restarted from a zero state at steps
  k L / K + j L; the estimate at step t is that of the copy whose context (steps since its restart)
  is the longest, so every estimate after step L sees between L - L / K and L steps, never more
  than the training windows' L. Before step L the copy started at 0 is used, as in ``continuous``.
  K times the compute. (A bounded context is what the paper's GPT-2 has by construction: its
  attention window is 256 steps.)

The same bounding is the neural estimators' ``context`` option (``--option mamba2.context=100`` on
evaluate / replay, ``options:=['context=100']`` on the estimator node; off by default, see
:mod:`neural_estimator.serving.context`); this script runs it on any weights, e.g. a run's last epoch.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch
from safetensors.torch import load_file

from neural_estimator.core.angles import wrap_components
from neural_estimator.data import evaluation_sets
from neural_estimator.methods.interface import previous_controls
from neural_estimator.metrics import rmse_over_time
from neural_estimator.serving.checkpoint import load_checkpoint
from neural_estimator.serving.context import bounded_forward
from neural_estimator.scenarios import make_scenario


def segment_rmse(x: np.ndarray, x_hat: np.ndarray, bounds: list[int], angle_states=()) -> list[float]:
    """RMSE over each segment [bounds[i], bounds[i+1]) of the horizon, from the RMSE-time curve."""
    e2 = rmse_over_time(wrap_components(np.asarray(x_hat, dtype=np.float64) - x, angle_states)) ** 2  # (T,)
    return [float(np.sqrt(e2[a:b].mean())) for a, b in zip(bounds, bounds[1:])]


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenario", default="nlink")
    p.add_argument("--model", required=True, help="checkpoint directory (card.json + model.safetensors)")
    p.add_argument("--weights", default=None, help="other weights of the same model (e.g. resume/model.safetensors)")
    p.add_argument("--trajectories", type=int, default=200)
    p.add_argument("--length", type=int, default=100, help="L, the training window")
    p.add_argument("--copies", default="2,10", help="comma-separated K values")
    p.add_argument("--segments", default="10,100,200,300,400,500")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    scenario = make_scenario(args.scenario)
    model, norm, _ = load_checkpoint(args.model)
    if args.weights:
        model.load_state_dict(load_file(args.weights))
    model.eval()
    data = evaluation_sets(scenario, seed=0, trajectories=args.trajectories, sets=1, cache_dir=False)[0]
    bounds = [int(b) for b in args.segments.split(",")]
    if bounds != sorted(set(bounds)) or bounds[0] < 0 or bounds[-1] > data.horizon:
        p.error(f"--segments must increase within 0..{data.horizon}, got {args.segments}")
    z, _ = norm.normalize_inputs(data.y, previous_controls(data.u))
    z = torch.as_tensor(z, dtype=torch.float32)
    print(f"{args.scenario}, {args.model}{' with ' + args.weights if args.weights else ''}")
    print(f"{args.trajectories} trajectories of evaluation set 0 x {data.horizon} steps, RMSE per segment of steps")
    segs = [f"{a}-{b}" for a, b in zip(bounds, bounds[1:])]
    print(f"{'inference':<16} " + " ".join(f"{s:>9}" for s in segs) + f" {f'{bounds[0]}-{bounds[-1]}':>9}")
    with torch.no_grad():
        runs = [("continuous", model(z))]
        runs += [
            (f"bounded {args.length}/{k}", bounded_forward(model, z, args.length, k))
            for k in map(int, args.copies.split(","))
        ]
        for label, y in runs:
            x_hat = norm.denormalize_states(y.numpy())
            vals = segment_rmse(data.x, x_hat, bounds, scenario.angle_states)
            total = segment_rmse(data.x, x_hat, [bounds[0], bounds[-1]], scenario.angle_states)[0]
            print(f"{label:<16} " + " ".join(f"{v:>9.4f}" for v in vals) + f" {total:>9.4f}", flush=True)


if __name__ == "__main__":
    main()
