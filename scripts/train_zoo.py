"""Train the model zoo shipped in neural_estimator/zoo/<scenario>-<method>/ (card.json + model.safetensors).

The paper's recipe (neural_estimator.models.training.TrainConfig defaults) with a smaller budget so
the whole zoo trains on a CPU: fewer windows per epoch and fewer epochs (the budget is recorded in
each card's recipe). Full-scale training is the same command with --full (GPU advised).

    python scripts/train_zoo.py --scenarios lorenz96 --methods gru,lstm,gpt2,filterformer,mamba,mamba2 \
        --epochs 20 --windows-per-epoch 2000
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

import torch

from neural_estimator.estimators import NEURAL_METHODS
from neural_estimator.models.training import TrainConfig, train
from neural_estimator.scenarios import BUILTIN_SCENARIOS, make_scenario

ZOO = Path(__file__).resolve().parents[1] / "neural_estimator" / "zoo"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenarios", default=",".join(BUILTIN_SCENARIOS))
    p.add_argument("--methods", default=",".join(NEURAL_METHODS))
    p.add_argument("--epochs", type=int, default=10)
    p.add_argument("--windows-per-epoch", type=int, default=2000)
    p.add_argument("--val-trajectories", type=int, default=400)
    p.add_argument("--eval-trajectories", type=int, default=400)
    p.add_argument("--threads", type=int, default=1, help="torch threads (1 is fastest on a shared 2-core machine)")
    p.add_argument("--full", action="store_true", help="the paper's full budget (500 epochs, 8000 validation trajectories)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--skip-existing", action="store_true")
    p.add_argument("--zoo", default=str(ZOO))
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    # method-major: every scenario gets the first method before any gets the second
    for method in a.methods.split(","):
        for scenario_name in a.scenarios.split(","):
            scenario = make_scenario(scenario_name)
            out = Path(a.zoo) / f"{scenario_name}-{method}"
            if a.skip_existing and (out / "card.json").exists():
                continue
            cfg = TrainConfig(device=a.device, keep_resume=False, eval_trajectories=a.eval_trajectories) if a.full else TrainConfig(
                epochs=a.epochs, windows_per_epoch=a.windows_per_epoch, val_trajectories=a.val_trajectories,
                eval_trajectories=a.eval_trajectories, device=a.device, keep_resume=False)
            tmp = out.with_name(out.name + ".partial")
            shutil.rmtree(tmp, ignore_errors=True)
            t0 = time.time()
            train(scenario, method, tmp, cfg, progress=False)
            shutil.rmtree(out, ignore_errors=True)
            tmp.rename(out)
            print(f"{scenario_name}-{method}: {time.time() - t0:.0f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
