"""The reliability diagram of every method, one figure per scenario (docs/uncertainty.md).

    python scripts/reliability_figures.py [--scenarios S,...] [--trajectories 100] [--pf-trajectories 50]
                                          [--seed 777] [--out docs/results/reliability]

For each scenario, `neural-estimator evaluate` runs the ten methods (the paper's filter settings,
started from the prior; the shipped neural models with their covariance heads) on fresh evaluation
seeds, one set, without the result cache (the reliability curve is recorded per run), and the median
coverage at each nominal level (`neural_estimator.metrics.consistency.RELIABILITY_LEVELS`) is drawn against
the level. Writes ``OUT/<scenario>.png`` and ``OUT/<scenario>.json`` (the curves). Neural models not
trained on the scenario's default constants are left out (see scripts/fidelity_table.py).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from neural_estimator.paper import PAPER_SCENARIOS

ROOT = Path(__file__).resolve().parents[1]


def curves_of(results: dict) -> dict[str, list[float]]:
    """{method: median coverage curve over its runs} for the methods that report a covariance."""
    out = {}
    for m, entry in results["methods"].items():
        runs = [r["coverage_curve"] for r in entry["runs"] if r.get("coverage_curve")]
        if runs:
            out[m] = [float(v) for v in np.median(np.asarray(runs, dtype=float), axis=0)]
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenarios", default=",".join(PAPER_SCENARIOS))
    p.add_argument("--trajectories", type=int, default=100)
    p.add_argument("--pf-trajectories", type=int, default=50)
    p.add_argument("--seed", type=int, default=777)
    p.add_argument("--out", default=str(ROOT / "docs" / "results" / "reliability"))
    a = p.parse_args(argv)

    from neural_estimator.cli import main as cli
    from neural_estimator.metrics.consistency import RELIABILITY_LEVELS
    from neural_estimator.metrics.plots import plot_reliability
    from neural_estimator.paper.reproduce.fidelity import shipped_on_defaults

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    for s in a.scenarios.split(","):
        neural, _ = shipped_on_defaults(s)
        curves: dict[str, list[float]] = {}
        runs = [(["ekf", "ukf", "enkf", *neural], a.trajectories), (["pf"], a.pf_trajectories)]
        for methods, n in runs:
            with tempfile.TemporaryDirectory() as tmp:
                args = ["evaluate", "--scenario", s, "--methods", ",".join(methods), "--trajectories", str(n)]
                args += ["--sets", "1", "--seed", str(a.seed), "--no-cache", "--quiet", "--out", tmp]
                print(f"{s}: {' '.join(args[4:6])}", flush=True)
                if cli(args) != 0:
                    return 1
                curves.update(curves_of(json.loads((Path(tmp) / "results.json").read_text())))
        info = {"scenario": s, "seed": a.seed, "trajectories": a.trajectories, "pf_trajectories": a.pf_trajectories}
        (out / f"{s}.json").write_text(
            json.dumps({**info, "levels": list(RELIABILITY_LEVELS), "curves": curves}, indent=1)
        )
        plot_reliability(curves, RELIABILITY_LEVELS, out / f"{s}.png", title=f"{s}: coverage against nominal level")
        print(f"wrote {out / s}.png", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
