"""Print a table of the shipped models: RMSE (NRMSE) on evaluation set 0, as measured at
the end of training and recorded in each card, "(converged)" where the card says training converged,
"(ctx N)" for a variant validated and served with its context bounded to N steps, "†" where the card
scored the steps after its warm-up (cards made since the warm-up rule record
``metrics.set.warmup``; older ones scored every step), and the training budgets.

    python scripts/zoo_table.py
"""

import json
from pathlib import Path

from neural_estimator.methods.registry import NEURAL_METHODS
from neural_estimator.paper import PAPER_SCENARIOS

ZOO = Path(__file__).resolve().parents[1] / "neural_estimator" / "serving" / "zoo"


def main() -> None:
    print("| model | " + " | ".join(PAPER_SCENARIOS) + " |")
    print("|---|" + "---:|" * len(PAPER_SCENARIOS))
    for m in NEURAL_METHODS:
        cells = []
        for s in PAPER_SCENARIOS:
            card = ZOO / f"{s}-{m}" / "card.json"
            if not card.exists():
                cells.append("–")
                continue
            c = json.loads(card.read_text())
            met = c["metrics"]
            mark = " (converged)" if c["training"].get("converged") else ""  # cards say so since the retraining
            scored = "†" if met["set"].get("warmup") else ""
            ctx = c["training"]["recipe"].get("val_context")
            mark += f" (ctx {ctx})" if ctx else ""  # validated and served with a bounded context
            cells.append(f"{met['rmse']:.4g}{scored} ({met['nrmse']:.3f}){mark}")
        print(f"| {m} | " + " | ".join(cells) + " |")
    budgets: dict[tuple, set[tuple[str, str]]] = {}  # budget -> the (scenario, method) models that had it
    for card in (p for p in ZOO.glob("*-*/card.json") if "." not in p.parent.name):
        c = json.loads(card.read_text())
        r, m = c["training"]["recipe"], c["metrics"]["set"]
        key = (
            c["training"].get("epochs_run", r["epochs"]),
            c["data"]["windows_per_epoch"],
            r["val_trajectories"],
            m["trajectories"],
        )
        budgets.setdefault(key, set()).add((c["scenario"]["scenario"], c["method"]))
    for (ep, w, v, n), models in sorted(budgets.items(), reverse=True):
        print(
            f"\n{_names(models)}: {ep} epochs x {w} windows, {v} validation trajectories, "
            f"metrics on {n} trajectories of evaluation set 0.",
            end="",
        )
    print("\n\n† the card's warm-up steps (metrics.set.warmup, 10) left out; the others scored over every step.")


def _names(models: set[tuple[str, str]]) -> str:
    """A scenario's name where all its models are in ``models``, else each model as scenario-method."""
    out = []
    for s in PAPER_SCENARIOS:
        mine = [m for m in NEURAL_METHODS if (s, m) in models]
        if len(mine) == len(NEURAL_METHODS):
            out.append(s)
        elif mine:
            out += [f"{s}-{m}" for m in mine]
    return ", ".join(out)


if __name__ == "__main__":
    main()
