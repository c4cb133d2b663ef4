"""The ``headline`` verb: the README's first table, measured on one seed family."""

from __future__ import annotations

import sys
from pathlib import Path

from neural_estimator.cli.common import CliError


def add_headline(sub) -> None:
    p = sub.add_parser(
        "headline",
        help="per system: best filter, best network, their paired RMSE ratio with its 95%% interval, the verdict",
    )
    p.add_argument(
        "--family",
        required=True,
        choices=("development", "sealed"),
        help="the seed family of the evaluation sets: development (any time) or sealed (the README's, measured "
        "once at the end; nothing else reads it)",
    )
    p.add_argument("--scenarios", help="comma-separated (default: the paper's five)")
    p.add_argument("--methods", help="comma-separated (default: all ten; openloop is always added as a reference)")
    p.add_argument("--trajectories", type=int, default=200, help="per evaluation set (default 200)")
    p.add_argument("--sets", type=int, default=3, help="evaluation sets per system (default 3)")
    p.add_argument("--horizon", type=int, help="steps (default: each scenario's)")
    p.add_argument("--out", default="headline-out", help="directory of headline.md, headline.json, <scenario>/")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_headline)


def _cmd_headline(args) -> int:
    from neural_estimator.evaluation.headline import measure_headline
    from neural_estimator.evaluation.headline import HEADLINE_FAMILIES
    from neural_estimator.filters.baselines import check_evaluated_method
    from neural_estimator.methods import table
    from neural_estimator.paper import PAPER_SCENARIOS
    from neural_estimator.scenarios import scenario_names

    scenarios = [s.strip() for s in (args.scenarios or ",".join(PAPER_SCENARIOS)).split(",") if s.strip()]
    unknown = [s for s in scenarios if s not in scenario_names()]
    if unknown:
        raise CliError(f"unknown scenario {unknown[0]!r}; choose from {', '.join(scenario_names())}")
    default = ",".join(table.names(family=HEADLINE_FAMILIES))
    methods = [check_evaluated_method(m) for m in (args.methods or default).split(",") if m.strip()]
    if args.trajectories < 2 or args.sets < 1:
        raise CliError(f"--trajectories must be >= 2 and --sets >= 1, got {args.trajectories} and {args.sets}")
    by_scenario: dict = {}
    headline = measure_headline(
        args.family,
        scenarios,
        methods,
        trajectories=args.trajectories,
        sets=args.sets,
        horizon=args.horizon,
        out=Path(args.out),
        progress=not args.quiet,
        note=lambda line: print(line, file=sys.stderr),
        results_out=by_scenario,
    )
    from neural_estimator.evaluation.headline import render_headline

    print(render_headline(headline), end="")
    print(f"wrote {args.out}/headline.md, headline.json and one folder per system", file=sys.stderr)
    _findings(args, by_scenario)
    return 0


def _findings(args, by_scenario: dict) -> None:
    """The paper's seven findings judged on the same measurement's paired intervals
    (:mod:`neural_estimator.paper.reproduce.intervals`), written as findings.md and findings.json
    when every method they compare was measured."""
    import json

    from neural_estimator import metrics as M
    from neural_estimator.paper.reproduce.intervals import covers, judge, render

    if not covers(by_scenario):
        print(
            "the paper's findings: not judged (they need the five systems and the methods they compare)",
            file=sys.stderr,
        )
        return
    judged = judge(by_scenario)
    out = Path(args.out)
    text = render(judged)
    (out / "findings.md").write_text(text)
    (out / "findings.json").write_text(json.dumps(M.to_json(judged), indent=1, allow_nan=False))
    print("\nThe paper's findings on the same measurement's paired intervals:\n\n" + text, end="")
    print(f"wrote {args.out}/findings.md and findings.json", file=sys.stderr)
