"""Measure every cell of the paper's main table on fresh evaluation seeds and judge it against the paper.

    python scripts/fidelity_table.py measure [--scenarios S,...] [--trajectories 200] [--sets 3]
                                             [--pf-trajectories 100] [--seed 777] [--out DIR]
    python scripts/fidelity_table.py render [--out DIR]

`measure` runs `neural-estimator evaluate` per scenario on the default constants (preset v4; N-link
and bearings v5): the four classical filters (started from the prior, the live pipeline's start) and
every shipped neural model trained on those constants; a model trained on other constants is
recorded as pending. The PF
gets its own, smaller, run (it costs 100-300x the other filters). Each run writes
``DIR/<scenario>[-pf]/results.json`` and is cached, so an interrupted measurement resumes where it
stopped. `render` prints the fidelity section (`neural_estimator/paper/reproduce/fidelity.py`: the 49
cells within 1.5x, the spread of the states, the paper's seven findings) and writes
``DIR/fidelity.md``; docs/fidelity.md shows it (`<!-- generate: fidelity-measured -->`), the site's
front page shows the cells (`defaults-table`), and `python scripts/update_readme.py` then rewrites
the README's count of them (its `fidelity-summary` block).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from neural_estimator.paper import PAPER_SCENARIOS

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_OUT = ROOT / "benchmarks" / "results" / "fidelity_measured"


def measure(a: argparse.Namespace) -> int:
    from neural_estimator.cli import main as cli
    from neural_estimator.paper.reproduce.fidelity import shipped_on_defaults

    out = Path(a.out)
    for s in a.scenarios.split(","):
        neural, pending = shipped_on_defaults(s)
        (out / s).mkdir(parents=True, exist_ok=True)
        (out / s / "pending.json").write_text(json.dumps(pending, indent=1) + "\n")
        common = ["--scenario", s, "--sets", str(a.sets), "--seed", str(a.seed), "--quiet"]
        runs = [
            (out / s, ["--methods", ",".join(["ekf", "ukf", "enkf", *neural]), "--trajectories", str(a.trajectories)]),
            (out / f"{s}-pf", ["--methods", "pf", "--trajectories", str(a.pf_trajectories)]),
        ]
        for where, args in runs:
            print(f"{s}: evaluate {' '.join(args)}", flush=True)
            rc = cli(["evaluate", *common, *args, "--out", str(where)])
            if rc != 0:
                return rc
    return render(a)


def render(a: argparse.Namespace) -> int:
    from neural_estimator.paper.reproduce.fidelity import load_measured, section

    out = Path(a.out)
    got = load_measured(out)
    lines = section(got) + ["", "Measured:", ""] + [f"- {x}" for x in got.settings]
    text = "\n".join(lines) + "\n"
    (out / "fidelity.md").write_text(text)
    print(text)
    if Path(a.out).resolve() == DEFAULT_OUT.resolve():
        print("the README's count of these cells: python scripts/update_readme.py", file=sys.stderr)
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="verb", required=True)
    m = sub.add_parser("measure", help="run the evaluations, then render")
    m.add_argument("--scenarios", default=",".join(PAPER_SCENARIOS))
    m.add_argument("--trajectories", type=int, default=200)
    m.add_argument("--pf-trajectories", type=int, default=100)
    m.add_argument("--sets", type=int, default=3)
    m.add_argument("--seed", type=int, default=777, help="evaluation seed, disjoint from training and selection")
    r = sub.add_parser("render", help="the fidelity section from the measured results")
    for q in (m, r):
        q.add_argument("--out", default=str(DEFAULT_OUT))
    a = p.parse_args(argv)
    return measure(a) if a.verb == "measure" else render(a)


if __name__ == "__main__":
    sys.exit(main())
