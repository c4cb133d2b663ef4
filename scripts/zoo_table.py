"""Print the README's table of the shipped models: RMSE (NRMSE) on evaluation set 0, as measured at
the end of training and recorded in each card, "(converged)" where the card says training converged,
and the training budgets.

    python scripts/zoo_table.py
"""

import json
from pathlib import Path

from neural_estimator.estimators import NEURAL_METHODS
from neural_estimator.scenarios import BUILTIN_SCENARIOS

ZOO = Path(__file__).resolve().parents[1] / "neural_estimator" / "zoo"


def main() -> None:
    print("| model | " + " | ".join(BUILTIN_SCENARIOS) + " |")
    print("|---|" + "---:|" * len(BUILTIN_SCENARIOS))
    for m in NEURAL_METHODS:
        cells = []
        for s in BUILTIN_SCENARIOS:
            card = ZOO / f"{s}-{m}" / "card.json"
            if not card.exists():
                cells.append("–")
                continue
            c = json.loads(card.read_text())
            met = c["metrics"]
            mark = " (converged)" if c["training"].get("converged") else ""  # cards say so since the retraining
            cells.append(f"{met['rmse']:.4g} ({met['nrmse']:.3f}){mark}")
        print(f"| {m} | " + " | ".join(cells) + " |")
    budgets: dict[tuple, set[str]] = {}  # budget -> the scenarios whose models had it
    for card in (p for p in ZOO.glob("*-*/card.json") if "." not in p.parent.name):
        c = json.loads(card.read_text())
        r, m = c["training"]["recipe"], c["metrics"]["set"]
        key = (r["epochs"], c["data"]["windows_per_epoch"], r["val_trajectories"], m["trajectories"])
        budgets.setdefault(key, set()).add(c["scenario"]["scenario"])
    for (ep, w, v, n), scenarios in sorted(budgets.items(), reverse=True):
        names = ", ".join(s for s in BUILTIN_SCENARIOS if s in scenarios)
        print(
            f"\n{names}: {ep} epochs x {w} windows, {v} validation trajectories, "
            f"metrics on {n} trajectories of evaluation set 0.",
            end="",
        )
    print()


if __name__ == "__main__":
    main()
