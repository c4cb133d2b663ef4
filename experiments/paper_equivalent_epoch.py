"""At which epoch of our own training did each shipped network reach the paper's figure?

    python experiments/paper_equivalent_epoch.py [--measured benchmarks/results/fidelity_measured]

Where our network is far more accurate than the paper's (Lorenz 96 GRU 0.071 against 0.127), the
scenario may be easier than the paper's, or the paper's network less trained than ours. Lorenz 96
separates the two: its operating point matches the paper's on both calibration distances (classical
rows within 4 %, spread of the true states 0.98x), so there the gap can only be the network.

Every epoch's validation loss is in the card's history (``training.history``). With the default
loss units (``state``) the loss is the mean squared error over the state components and the scored
steps of the validation trajectories, divided by a constant (the mean state variance), so an
epoch's RMSE is, to the extent that validation and evaluation sets agree,

    RMSE_k ~= RMSE_best * sqrt(val_loss_k / val_loss_best)

with RMSE_best our measured cell (fresh evaluation seeds, ``scripts/fidelity_table.py``) of the
shipped model (the best epoch). The script prints, per (scenario, method), our RMSE, the paper's,
the first epoch's equivalent RMSE and the first epoch whose equivalent reaches the paper's figure
("never": the paper's is better than any epoch of ours; 1: worse than our first epoch).
A reading from the training records, not a re-evaluation of early weights (those are not kept).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from neural_estimator.paper.reproduce.fidelity import load_measured, paper_table  # noqa: E402

ZOO = ROOT / "neural_estimator" / "serving" / "zoo"
NEURAL = ("gru", "lstm", "gpt2", "filterformer", "mamba", "mamba2")


def equivalent_rmse(history: list[dict], best_loss: float, best_rmse: float) -> list[float]:
    """Each epoch's RMSE read from its validation loss: best_rmse * sqrt(val_loss / best_loss)."""
    return [best_rmse * math.sqrt(h["val_loss"] / best_loss) for h in history]


def epoch_reaching(curve: list[float], target: float) -> str:
    """The first epoch (1-based) whose RMSE is at most ``target``, or "never"."""
    return next((str(k) for k, r in enumerate(curve, start=1) if r <= target), "never")


def rows(measured_dir: Path) -> list[str]:
    measured = load_measured(measured_dir)
    paper = paper_table("rmse")
    out = [
        "| scenario | method | ours | paper | ours / paper | epoch 1 (equivalent) | epochs "
        "| the paper's reached at epoch |"
    ]
    out.append("|---|---|---|---|---|---|---|---|")
    for scenario in sorted(measured.rmse):
        for method in NEURAL:
            ours = measured.rmse[scenario].get(method)
            theirs = paper.get(scenario, {}).get(method)
            card_path = ZOO / f"{scenario}-{method}" / "card.json"
            if ours is None or theirs is None or not math.isfinite(theirs) or not card_path.is_file():
                continue
            card = json.loads(card_path.read_text())
            if card.get("training", {}).get("recipe", {}).get("loss_units", "state") != "state":
                continue  # the reading needs the loss in the states' units
            history = card["training"]["history"]
            curve = equivalent_rmse(history, card["validation_loss"], ours)
            out.append(
                f"| {scenario} | {method} | {ours:.3g} | {theirs:.3g} | {ours / theirs:.2f} | {curve[0]:.3g} | "
                f"{len(history)} | {epoch_reaching(curve, theirs)} |"
            )
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--measured", default=str(ROOT / "benchmarks" / "results" / "fidelity_measured"))
    a = p.parse_args(argv)
    print("\n".join(rows(Path(a.measured))))
    return 0


if __name__ == "__main__":
    sys.exit(main())
