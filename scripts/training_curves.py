"""The full-recipe training curves in zoo_training/: validation loss per epoch, learning-rate halvings, plateau.

For every (scenario, method) in STATE (default zoo_training/, finished or in progress) this reads the
per-epoch history (the card's when finished, else resume/state.json's) and

- plots the validation loss (log scale) against the epoch, one panel per pair, with the best epoch
  marked and a tick at each learning-rate reduction (``--out``, a PNG);
- prints one line per pair: epochs, CPU hours, best validation loss and its epoch, learning-rate
  reductions, and the plateau figure

      flat = (min of the last ``--window`` epochs' validation losses) / (min of all earlier ones) - 1

  (negative: the last epochs still found a lower loss, by that fraction; about 0: flat), which is
  the evidence for calling a run converged short of the paper's 30-epoch early stopping.

    python scripts/training_curves.py --out docs/results/training_curves.png > docs/results/training_curves.txt
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
STATE = ROOT / "zoo_training"


def history(work: Path) -> tuple[list[dict], str]:
    """(per-epoch records, "finished: <why>" or "in progress") of one pair's directory."""
    card = work / "card.json"
    if card.is_file():
        t = json.loads(card.read_text())["training"]
        if t["stopped"] != "in progress":
            return t["history"], f"finished: {t['stopped']}"
    state = work / "resume" / "state.json"
    if state.is_file():
        return json.loads(state.read_text())["run"]["history"], "in progress"
    return [], "not started"


def reductions(hist: list[dict]) -> list[int]:
    """Epochs whose learning rate is lower than the epoch before's."""
    return [b["epoch"] for a, b in zip(hist, hist[1:]) if b["lr"] < a["lr"]]


def flatness(val: list[float], window: int) -> float:
    """min(last ``window``) / min(the rest) - 1; NaN when there are not more than ``window`` epochs."""
    if len(val) <= window:
        return math.nan
    return min(val[-window:]) / min(val[:-window]) - 1


def summary(name: str, hist: list[dict], why: str, window: int) -> str:
    val = [h["val_loss"] for h in hist]
    best = min(range(len(val)), key=val.__getitem__)
    hours = sum(h["seconds"] for h in hist) / 3600
    flat = flatness(val, window)
    flat_text = "–" if math.isnan(flat) else f"{100 * flat:+.1f} %"
    return (
        f"{name:<28} {len(hist):>4} epochs {hours:5.2f} h  best val {val[best]:.4g} at epoch {hist[best]['epoch']:>3}"
        f"  lr reductions {len(reductions(hist)):>2} (lr {hist[-1]['lr']:.3g})"
        f"  flat over last {window}: {flat_text}  [{why}]"
    )


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--state", default=str(STATE))
    p.add_argument("--out", default=None, help="PNG of the curves (none: the summary only)")
    p.add_argument("--window", type=int, default=10, help="epochs of the plateau figure")
    a = p.parse_args(argv)
    runs = []
    root = Path(a.state)
    # <pair>/ and one level below (zoo_training/normalised/<pair>/: runs of the earlier loss units)
    for work in sorted([*root.glob("*-*"), *root.glob("*/*-*")], key=lambda w: (len(w.parts), str(w))):
        hist, why = history(work)
        if hist:
            name = str(work.relative_to(root))
            runs.append((name, hist, why))
            print(summary(name, hist, why, a.window))
    if not runs:
        print(f"no training histories under {a.state}", file=sys.stderr)
        return 1
    if a.out:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        cols = min(3, len(runs))
        rows = math.ceil(len(runs) / cols)
        fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.2 * rows), squeeze=False)
        for ax, (name, hist, why) in zip(axes.flat, runs):
            ep = [h["epoch"] for h in hist]
            val = [h["val_loss"] for h in hist]
            ax.semilogy(ep, val, lw=1.2, label="validation")
            best = min(range(len(val)), key=val.__getitem__)
            ax.plot(ep[best], val[best], "o", ms=4, color="C3", label=f"best {val[best]:.3g}")
            for e in reductions(hist):
                ax.axvline(e, color="0.8", lw=0.6, zorder=0)
            ax.set_title(f"{name} ({'finished' if why.startswith('finished') else 'in progress'})", fontsize=9)
            ax.set_xlabel("epoch (20,000 windows)", fontsize=8)
            ax.tick_params(labelsize=7)
            ax.legend(fontsize=7)
        for ax in list(axes.flat)[len(runs) :]:
            ax.axis("off")
        fig.suptitle("Full-recipe training: validation loss (grey lines: learning rate halved)", fontsize=10)
        fig.tight_layout()
        out = Path(a.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(out, dpi=110)
        print(f"wrote {out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
