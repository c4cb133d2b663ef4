"""The paper's seven findings judged on paired 95 % intervals (neural_estimator/paper/reproduce/intervals.py).

    .venv/bin/python experiments/findings_intervals.py                       # 2 sets x 100 trajectories, seed 777
    .venv/bin/python experiments/findings_intervals.py --trajectories 50 --sets 1

Runs the methods each finding compares on its scenarios (the development family: seed 777 by
default; the sealed family is the headline's alone), each pair on the same trajectories, and prints
each finding's ratio, its interval and the judgement on the interval. Uses evaluate's result cache,
so a rerun only computes what is missing. Output: experiments/results/findings_intervals.md.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from neural_estimator import metrics as M
from neural_estimator.evaluation import evaluate
from neural_estimator.paper.reproduce.intervals import NEEDED, judge, render
from neural_estimator.scenarios import make_scenario

OUT = Path(__file__).resolve().parent / "results" / "findings_intervals.md"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--trajectories", type=int, default=100)
    p.add_argument("--sets", type=int, default=2)
    p.add_argument("--seed", type=int, default=777, help="a development-family seed")
    p.add_argument("--out", type=Path, default=OUT)
    a = p.parse_args()
    by_scenario = {}
    for s, methods in NEEDED.items():
        by_scenario[s] = evaluate(
            make_scenario(s), list(methods), trajectories=a.trajectories, sets=a.sets, seed=a.seed, progress=False
        )
        print(f"{s}: done", flush=True)
    judged = judge(by_scenario)
    command = (
        f"python experiments/findings_intervals.py --trajectories {a.trajectories} --sets {a.sets} --seed {a.seed}"
    )
    text = (
        f"# The paper's findings on paired intervals\n\n`{command}` (development family; {a.sets} sets x "
        f"{a.trajectories} trajectories per system, steps {M.EVALUATION_WARMUP}.. scored, filters from the prior, "
        "the shipped networks, one instance each)\n\n" + render(judged)
    )
    a.out.write_text(text)
    a.out.with_suffix(".json").write_text(json.dumps(M.to_json(judged), indent=1, allow_nan=False))
    print(text)


if __name__ == "__main__":
    main()
