"""Does it matter in which units the training loss weighs the state components? (``train --loss-units``)

The paper's metric is RMSE in the states' own units; it does not say in which units its loss is.
Ours defaults to normalised units (each component at unit variance). For each (scenario, model)
this trains the same recipe with ``--loss-units state`` (the states' own units) and compares the
RMSE on evaluation set 0 with the shipped model trained on normalised units, when that model had
the same recipe otherwise (same budget, data and seeds: the same window stream), so the loss units
are the only difference:

    python experiments/loss_units.py --pairs ballistic-mamba2,quadrotor-mamba2 --out runs/lossunits

Each training goes to OUT/<scenario>-<model>-state/ and is skipped when its card is already
there (so the script can be run again to extend the table). Defaults are the shipped 2 %-budget
recipe: 20 epochs x 2,000 windows, 400 validation and 400 evaluation trajectories, one thread.
Its output: experiments/results/loss_units.md.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from neural_estimator.cli import main as cli

ZOO = Path(__file__).resolve().parents[1] / "neural_estimator" / "serving" / "zoo"


def same_recipe(a: dict, b: dict) -> bool:
    """Two cards' recipes equal up to the loss units (a recipe without the field is normalised)."""
    ra, rb = dict(a["training"]["recipe"]), dict(b["training"]["recipe"])
    for r in (ra, rb):
        r.pop("loss_units", None)
    return ra == rb


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--pairs", required=True, help="comma-separated scenario-model, e.g. ballistic-mamba2")
    p.add_argument("--out", required=True, help="directory of the state-unit trainings")
    p.add_argument("--epochs", type=int, default=20)
    p.add_argument("--windows-per-epoch", type=int, default=2000)
    p.add_argument("--val-trajectories", type=int, default=400)
    p.add_argument("--eval-trajectories", type=int, default=400)
    p.add_argument("--zoo", default=str(ZOO), help="the normalised-unit models to compare with")
    a = p.parse_args(argv)
    rows = []
    for pair in [x for x in a.pairs.split(",") if x]:
        scenario, _, model = pair.rpartition("-")
        out = Path(a.out) / f"{pair}-state"
        if (
            not (out / "card.json").is_file()
            or json.loads((out / "card.json").read_text())["training"]["stopped"] == "in progress"
        ):
            t0 = time.time()
            args = ["train", "--scenario", scenario, "--model", model, "--out", str(out), "--loss-units", "state"]
            args += ["--epochs", str(a.epochs), "--windows-per-epoch", str(a.windows_per_epoch)]
            args += ["--val-trajectories", str(a.val_trajectories), "--eval-trajectories", str(a.eval_trajectories)]
            if cli([*args, "--threads", "1", "--quiet", "--resume"]) != 0:
                print(f"{pair}: training failed", file=sys.stderr)
                continue
            print(f"{pair}: trained in {time.time() - t0:.0f} s", file=sys.stderr)
        state = json.loads((out / "card.json").read_text())
        base_path = Path(a.zoo) / pair / "card.json"
        base = json.loads(base_path.read_text()) if base_path.is_file() else None
        comparable = base is not None and same_recipe(base, state)
        n = state["metrics"]["set"]["trajectories"]
        rows.append(
            f"| {pair} | {state['training']['recipe']['epochs']} x {state['data']['windows_per_epoch']} "
            f"| {base['metrics']['rmse']:.4g} | {state['metrics']['rmse']:.4g} | "
            f"{base['metrics']['rmse'] / state['metrics']['rmse']:.2f}x | {n} |"
            + ("" if comparable else " (shipped model had another recipe)")
            if base is not None
            else f"| {pair} | – | – | {state['metrics']['rmse']:.4g} | – | {n} |"
        )
    head = ["pair", "budget (epochs x windows)", "RMSE, normalised loss (shipped)", "RMSE, state-unit loss"]
    print("| " + " | ".join([*head, "ratio", "trajectories of set 0"]) + " |")
    print("|---|---|---:|---:|---:|---:|")
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
