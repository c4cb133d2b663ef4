"""Time of one training epoch of the hybrid (KalmanNet) at the paper's recipe, per scenario, on this
machine: one batch of 64 whole training trajectories (500 steps, 5 TBPTT chunks of 100: forward,
backward, AdamW) timed, times the batches of an epoch (4,000 / 64 = 63), plus the validation pass
(``--val-trajectories`` full-length trajectories, no gradient), measured on a slice and scaled.

    OMP_NUM_THREADS=1 python benchmarks/bench_hybrid_training.py
    OMP_NUM_THREADS=1 python benchmarks/bench_hybrid_training.py --scenarios lorenz96 --val-trajectories 1000

Prints figures; asserts nothing (a benchmark, not a test).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

from neural_estimator.data.simulate import simulate  # noqa: E402
from neural_estimator.models import build_model, count_parameters  # noqa: E402
from neural_estimator.paper.results import PAPER_SCENARIOS  # noqa: E402
from neural_estimator.scenarios import make_scenario  # noqa: E402
from neural_estimator.serving.normalization import Normalizer  # noqa: E402
from neural_estimator.methods.interface import previous_controls  # noqa: E402


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenarios", default=",".join(PAPER_SCENARIOS))
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--length", type=int, default=500)
    p.add_argument("--chunk", type=int, default=100)
    p.add_argument("--trajectories", type=int, default=4000)
    p.add_argument("--val-trajectories", type=int, default=1000)
    a = p.parse_args(argv)
    print(f"torch threads {torch.get_num_threads()}; batch {a.batch} x {a.length} steps in chunks of {a.chunk}")
    print("| scenario | parameters | one batch (s) | training epoch (min) | validation (min) | epoch total (min) |")
    print("|---|---|---|---|---|---|")
    for name in a.scenarios.split(","):
        scen = make_scenario(name)
        length = min(a.length, scen.longest_training_trajectory or a.length)
        data = simulate(scen, a.batch, length, seed=0)
        norm = Normalizer.from_data(scen, data)
        torch.manual_seed(0)
        model = build_model("kalmannet", scen)
        model.set_normalization(norm)
        opt = torch.optim.AdamW(model.parameters(), lr=2e-3)
        z, _ = norm.normalize_inputs(data.y, previous_controls(data.u))
        x = norm.normalize_states(data.x)
        z, x = torch.as_tensor(z, dtype=torch.float32), torch.as_tensor(x, dtype=torch.float32)
        t0 = time.perf_counter()
        state = model.init_state(a.batch)
        for c in range(0, length, a.chunk):
            xn, _, state = model.rollout(z[:, c : c + a.chunk], state)
            loss = (xn - x[:, c : c + a.chunk]).square().mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            state = tuple(s.detach() for s in state)
        batch_s = time.perf_counter() - t0
        with torch.no_grad():
            t0 = time.perf_counter()
            model.rollout(z, model.init_state(a.batch))
            val_s = (time.perf_counter() - t0) * a.val_trajectories / a.batch
        train_min = batch_s * math.ceil(a.trajectories / a.batch) / 60
        print(
            f"| {name} | {count_parameters(model):,} | {batch_s:.2f} | {train_min:.1f} | {val_s / 60:.1f} | "
            f"{train_min + val_s / 60:.1f} |",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
