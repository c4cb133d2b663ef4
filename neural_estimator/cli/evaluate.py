"""The scoring verbs: ``metrics`` (the paper's table of given estimates) and ``evaluate`` (methods
on the evaluation sets)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from neural_estimator.cli.common import (
    CliError,
    bag_description,
    bag_scenario_flags,
    is_bag,
    parse_checkpoints,
    model_scenario_from_args,
    model_set_flag,
    parse_options,
    scenario_flags,
    scenario_or_data,
    warmup_flag,
)
from neural_estimator.methods import table


def _partial_line(reports) -> str:
    """How many steps were scored and how many had no ground truth, "" when every step had."""
    from neural_estimator.metrics.labelled import scored_line

    return scored_line(reports)


def add_metrics(sub) -> None:
    p = sub.add_parser("metrics", help="the paper's table from a truth file and estimate files (or an MCAP bag)")
    p.add_argument("--plugin", action="append", metavar="FILE", help="Python file registering user scenarios")
    p.add_argument(
        "files",
        nargs="+",
        metavar="FILE",
        help="an estimate .npz (x and x_hat), or a truth .npz followed by estimate .npz files, or a bag "
        "(.mcap file or rosbag2 directory)",
    )
    bag_scenario_flags(p)
    p.add_argument(
        "--spec",
        metavar="SPEC.yaml",
        help="a bag of a live run on recorded-data models (section 'Your own robot'): the ground truth is "
        "the spec's state fields, each estimates/<method> stream is scored",
    )
    p.add_argument("--length", type=int, default=200, help="with --spec: steps per scored trajectory (default 200)")
    warmup_flag(p)
    p.add_argument(
        "--start",
        action="append",
        metavar="METHOD=MODE",
        help="how a recorded filter started (prior, truth, observation; default prior): marks the departures "
        "from the paper's start and the expected failures by the start (repeatable)",
    )
    p.add_argument(
        "--json", action="store_true", help="print JSON (RMSE-over-time curves, outlier and diverged indices)"
    )
    p.add_argument("--out", help="also write the table: .csv, .md or .json by extension")
    p.set_defaults(func=_cmd_metrics)


def _estimates_from_files(files: list[str], args: argparse.Namespace | None = None):
    """(truth Trajectories, {method: (x_hat, P_hat or None)}, angle_states) from npz files or a bag."""
    from neural_estimator.data.io import load_truth_and_estimates

    if len(files) == 1 and is_bag(files[0]):
        from neural_estimator.bags import load_bag_dataset

        return load_bag_dataset(
            files[0],
            namespace=getattr(args, "namespace", "/") or "/",
            description=bag_description(args) if args is not None else None,
        )
    if any(is_bag(f) for f in files):
        raise CliError("a bag is scored on its own: pass one .mcap file or rosbag2 directory")
    return load_truth_and_estimates(files)


def _scored_files(files: list[str], args: argparse.Namespace, warmup: int):
    """(run, {method: MetricReport}, {method: TrajectoryErrors}) of npz files or a bag; ``run`` has
    the ``n``, ``horizon`` and ``meta`` of what was scored. A bag is scored in bounded memory
    (:func:`~neural_estimator.evaluation.bag_scoring.score_bag`); npz files are held as arrays and scored
    block by block."""
    from neural_estimator.metrics.streaming import score_in_blocks

    def check(horizon: int) -> None:
        if not 0 <= warmup < horizon:
            raise CliError(
                f"--warmup {warmup} leaves no step of {horizon}-step trajectories to score: pass a smaller "
                "--warmup (0 scores every step)"
            )

    if len(files) == 1 and is_bag(files[0]):
        from neural_estimator.evaluation.bag_scoring import score_bag

        run = score_bag(
            files[0],
            namespace=getattr(args, "namespace", "/") or "/",
            description=bag_description(args),
            warmup=warmup,
            check_horizon=check,
        )
        return run, run.reports, run.errors
    truth, estimates, angles = _estimates_from_files(files, args)
    check(truth.horizon)
    if getattr(truth, "labelled", None) is not None:  # partial ground truth: the labelled steps only
        from neural_estimator import metrics as M

        reports = {
            m: M.compute_labelled_metrics(truth.x, xh, angles, truth.labelled, P_hat=P, warmup=warmup)
            for m, (xh, P) in estimates.items()
        }
        errors = {
            m: M.trajectory_errors(truth.x, xh, angles, reports[m].outlier_idx, warmup, truth.labelled)
            for m, (xh, _) in estimates.items()
        }
        return truth, reports, errors
    scored = {m: score_in_blocks(truth.x, xh, angles, P_hat=P, warmup=warmup) for m, (xh, P) in estimates.items()}
    return truth, {m: r for m, (r, _) in scored.items()}, {m: e for m, (_, e) in scored.items()}


def _cmd_metrics(args) -> int:
    if args.spec:
        return _print_spec_metrics(args)
    return _print_metrics(args.files, args, as_json=args.json, out=args.out)


def _print_spec_metrics(args) -> int:
    """The metrics of a recorded live run of recorded-data models, scored through a spec."""
    from neural_estimator import metrics as M
    from neural_estimator.robot import SpecError
    from neural_estimator.robot.score import score_recording

    if len(args.files) != 1 or not is_bag(args.files[0]):
        raise CliError("--spec scores one bag (a .mcap file or rosbag2 directory)")
    try:
        reports, truth = score_recording(
            args.files[0], args.spec, args.length, namespace=args.namespace or "/", warmup=args.warmup
        )
    except SpecError as exc:
        raise CliError(str(exc)) from None
    if args.json:
        print(json.dumps(M.to_json({"scenario": "data", "methods": reports}), indent=1, allow_nan=False))
    else:
        print(f"recorded run {args.files[0]}: {truth.n} trajectories x {truth.horizon} steps (spec {args.spec})")
        partial = _partial_line(reports.values())
        if partial:
            print(partial)
        print(M.format_reports(reports, fmt="text"), end="")
    if args.out:
        _write_table(args.out, reports)
    return 0


def _print_metrics(
    files: list[str],
    args: argparse.Namespace,
    as_json: bool = False,
    out: str | None = None,
    starts: dict[str, str] | None = None,
) -> int:
    """The metrics table of ``files`` (the ``metrics`` verb, and ``replay --metrics`` on its output);
    ``starts``: {method: start mode} of the filters that made the estimates (default: the prior)."""
    from neural_estimator.paper import departures as D
    from neural_estimator import metrics as M
    from neural_estimator.paper.expected_failures import mark_rows, notes

    warmup = getattr(args, "warmup", M.EVALUATION_WARMUP)
    truth, reports, errors = _scored_files(files, args, warmup)
    note = ""
    if "bag" in truth.meta:
        from neural_estimator.bags.dataset import left_out_note, outside_note

        note = left_out_note(truth.meta["bag"])
        if note:  # a partly scorable bag: say what the table does not cover
            print(f"neural-estimator: note: {note}", file=sys.stderr)
        aside = outside_note(truth.meta["bag"])
        if aside:  # the table is right without them, but nothing is ignored without a word
            print(f"neural-estimator: note: {aside}", file=sys.stderr)
    if as_json:
        print(
            json.dumps(
                M.to_json(
                    {"scenario": truth.meta.get("scenario"), "methods": reports, **({"left_out": note} if note else {})}
                ),
                indent=1,
                allow_nan=False,
            )
        )
    else:
        starts = dict(starts or {})
        if "bag" in truth.meta and not starts:  # the evaluator records how the filters started
            from neural_estimator.evaluation.bag_report import recorded_starts

            starts = recorded_starts(files[0])
        for item in getattr(args, "start", None) or ():
            method, sep, mode = item.partition("=")
            if not sep or mode not in ("prior", "truth", "observation"):
                raise CliError(f"--start expects METHOD=prior|truth|observation, got {item!r}")
            starts[method.strip()] = mode
        scenario_name = str(truth.meta.get("scenario", "?"))
        rows = {m: D.row_marks(m, init=starts.get(m, "prior")) for m in reports}
        cells = {m: {"rmse": D.OUTLIERS} for m, r in reports.items() if D.rests_on_outliers(r.rmse, r.full_rmse)}
        named = D.marked_names(reports, rows)
        table = M.format_reports(
            {named[m]: r for m, r in reports.items()}, fmt="text", marks={named[m]: c for m, c in cells.items()}
        )
        print(f"{scenario_name}: {truth.n} trajectories x {truth.horizon} steps{_scored(warmup)}")
        if _partial_line(reports.values()):
            print(_partial_line(reports.values()))
        print(mark_rows(table, scenario_name, starts), end="")
        used = {x for v in rows.values() for x in v} | ({D.OUTLIERS} if cells else set())
        for line in notes(scenario_name, list(reports), starts) + D.legend_text(used) + [D.scored_steps(warmup)]:
            print(line)
        _print_given_decision(truth, reports, warmup, errors)
    if out:
        _write_table(out, reports)
    return 0


def _print_given_decision(truth, reports, warmup: int, errors) -> None:
    """The per-component table of given estimates, with the paired ratios (the ``metrics`` verb)."""
    from neural_estimator.evaluation.decision import estimates_decision

    text = estimates_decision(truth, None, (), reports, warmup, errors=errors)
    if text:
        print("per component (own units) and against the best filter:")
        print(text, end="")


def _write_table(path: str, reports) -> None:
    from neural_estimator import metrics as M
    from neural_estimator.core.atomic import write_text_atomically

    out = Path(path)
    if out.suffix == ".csv":
        text = M.format_reports(reports, fmt="csv")
    elif out.suffix == ".json":
        text = json.dumps(M.to_json(reports), indent=1, allow_nan=False)
    else:
        text = M.format_reports(reports, fmt="markdown")
    write_text_atomically(out, text)  # a full disk or read-only directory: one line, no empty file
    print(f"wrote {out}")


DEFAULT_METHODS = ",".join(table.names(family="classical"))


def add_evaluate(sub) -> None:
    p = sub.add_parser("evaluate", help="run methods on the evaluation sets; print the paper's table")
    scenario_flags(p, data=True)
    p.add_argument(
        "--data",
        metavar="FILE.npz",
        help="a recorded dataset (neural-estimator dataset) instead of --scenario: its trajectories are the "
        "one evaluation set; neural methods need --checkpoint",
    )
    model_set_flag(p)
    p.add_argument(
        "--estimate",
        action="append",
        metavar="NAME=FILE.npz",
        help="with --data: a recorded estimate file (neural-estimator dataset writes one per spec estimate) "
        "scored as one more row",
    )
    p.add_argument(
        "--methods",
        default=DEFAULT_METHODS,
        help=f"comma-separated ({' '.join(table.names())}, and the reference rows "
        f"{' and '.join(table.names(family='baseline'))}, never ranked); with --data: default the --checkpoint methods",
    )
    p.add_argument("--trajectories", type=int, default=8000, help="per evaluation set (paper: 8000)")
    p.add_argument("--horizon", type=int, help="steps (default: the scenario's; paper: 500, quadrotor 200)")
    p.add_argument("--sets", type=int, default=3, help="independent evaluation sets (paper: 3)")
    p.add_argument("--seed", type=int, default=0, help="seed of the evaluation sets' streams")
    p.add_argument(
        "--checkpoint",
        action="append",
        metavar="METHOD=DIR[,DIR...]",
        help="checkpoints of a neural method (each one instance); default: the shipped model",
    )
    p.add_argument(
        "--option",
        action="append",
        metavar="METHOD.NAME=VALUE",
        help="filter hyperparameter, e.g. pf.n_particles=2048 (repeatable)",
    )
    p.add_argument(
        "--threads",
        type=int,
        metavar="N",
        help="threads of the classical filters (default: $NEURAL_ESTIMATOR_THREADS, else the usable cores)",
    )
    p.add_argument(
        "--init",
        choices=("prior", "truth", "observation"),
        default="prior",
        help="how the classical filters start: from the scenario prior (default, the paper's start), at each "
        "trajectory's true x0, or at the state the first observation determines where h is invertible "
        "(Lorenz 96: x0 = y0); mean only, P0 and the PF's init_std unchanged",
    )
    warmup_flag(p)
    p.add_argument("--device", default="cpu")
    p.add_argument(
        "--no-cache",
        action="store_true",
        help="no disk cache at all: evaluation sets and run results are neither read nor written (no resume)",
    )
    p.add_argument(
        "--recompute",
        action="store_true",
        help="compute every run again even if its result is cached (and overwrite the cached result)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--json", action="store_true", help="print JSON instead of the table")
    p.add_argument(
        "--out",
        help="directory for table.md, table.csv, consistency.md, results.json (rewritten after every run) and "
        "rmse_over_time.png",
    )
    p.set_defaults(func=_cmd_evaluate)


def _recorded_estimates(items: list[str] | None, truth) -> dict[str, Any]:
    from neural_estimator.data.io import load_estimates

    out = {}
    for item in items or ():
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            raise CliError(f"--estimate expects NAME=FILE.npz, got {item!r}")
        out[name.strip()], _, _ = load_estimates(path, truth)
    return out


def _cmd_evaluate(args) -> int:
    from neural_estimator.evaluation import evaluate, recorded_result, results_json, write_evaluation

    scenario, datasets, methods, checkpoints, recorded, options, info = _evaluation_request(args)
    model = model_scenario_from_args(args, scenario)
    from neural_estimator.scenarios.model import model_set_of

    info["model_set"] = model_set_of(model)  # recorded beside the preset (results.json, table.csv)
    out = Path(args.out) if args.out else None
    expected_runs = {m: info["sets"] * max(1, len(checkpoints.get(m) or ())) for m in methods}
    expected_runs.update({name: 1 for name in recorded})

    def write_partial(results) -> None:  # after every run: an interrupted evaluate leaves its finished runs
        if out is not None:
            write_evaluation(out, scenario, results, info, expected_runs, plot=False)

    results = evaluate(
        scenario,
        methods,
        trajectories=args.trajectories,
        horizon=args.horizon,
        seed=args.seed,
        sets=args.sets,
        checkpoints=checkpoints,
        options=options,
        device=args.device,
        cache_dir=False if args.no_cache else None,
        progress=not args.quiet,
        recompute=args.recompute,
        on_result=write_partial,
        init=args.init,
        datasets=datasets,
        warmup=args.warmup,
        model_scenario=model,
    )
    if recorded:
        for name, x_hat in recorded.items():
            results[name] = recorded_result(scenario, datasets[0], x_hat, name, warmup=args.warmup)
    if args.json:
        print(json.dumps(results_json(scenario, results, complete=True, **info), indent=1, allow_nan=False))
    else:
        _print_evaluation(args, scenario, results, info, recorded_data=datasets is not None)
    if out is not None:
        write_evaluation(out, scenario, results, info, expected_runs, plot=True)
        print(
            f"wrote {out}/table.md, table.csv, decision.md, consistency.md, results.json, rmse_over_time.png",
            file=sys.stderr,
        )
    return 0


def _evaluation_request(args):
    """(scenario, recorded datasets or None, methods, checkpoints, recorded estimates, options, info)
    of the evaluate flags, each checked: a one-line CliError otherwise."""
    from neural_estimator.evaluation import recorded_data_methods
    from neural_estimator.filters.baselines import check_evaluated_method
    from neural_estimator.methods.registry import check_method

    scenario, datasets = scenario_or_data(args)
    methods = [check_evaluated_method(m) for m in args.methods.split(",") if m.strip()]
    checkpoints = parse_checkpoints(args.checkpoint)
    for m in checkpoints:
        check_method(m)
    recorded = {}
    if datasets is not None:
        if args.methods == DEFAULT_METHODS:  # not given: the methods of the checkpoints
            methods = list(checkpoints)
        try:
            methods = recorded_data_methods(methods, checkpoints, getattr(scenario, "system", None) is not None)
        except ValueError as exc:
            raise CliError(str(exc)) from None
        if datasets[0].labelled is not None and not datasets[0].labelled.any():
            raise CliError(f"{args.data}: no state labels (its spec reads no ground truth): nothing to score against")
        recorded = _recorded_estimates(args.estimate, datasets[0])
    elif args.estimate:
        raise CliError("--estimate needs --data")
    if not methods and not recorded:
        raise CliError(
            "--methods is empty"
            if datasets is None
            else "nothing to evaluate: pass --checkpoint METHOD=DIR or --estimate NAME=FILE"
        )
    options = parse_options(args.option)
    if args.threads is not None:
        if args.threads < 1:
            raise CliError(f"--threads must be >= 1, got {args.threads}")
        for m in methods:
            if table.has(m, family="classical"):
                options.setdefault(m, {}).setdefault("threads", args.threads)
    if scenario is not None:  # a misspelt filter option fails now, not after the data are simulated
        from neural_estimator.methods.registry import make_estimator

        from neural_estimator.filters.baselines import is_baseline, make_baseline

        for m in methods:
            if table.has(m, family="classical"):
                make_estimator(m, model_scenario_from_args(args, scenario), **options.get(m, {}))
            elif is_baseline(m):  # obsonly where h determines nothing fails now, in one line
                make_baseline(m, model_scenario_from_args(args, scenario), **options.get(m, {}))
    if datasets is not None:
        info = dict(
            trajectories=datasets[0].n,
            horizon=datasets[0].horizon,
            sets=1,
            seed=None,
            init="recorded",
            data=str(args.data),
            warmup=args.warmup,
        )
    else:
        info = dict(
            trajectories=args.trajectories,
            horizon=args.horizon or scenario.horizon,
            sets=args.sets,
            seed=args.seed,
            init=args.init,
            warmup=args.warmup,
        )
    if datasets is None:
        from neural_estimator.evaluation.families import check_unsealed

        try:
            check_unsealed(args.seed)
        except ValueError as exc:
            raise CliError(str(exc)) from None
    if args.horizon is not None and args.horizon < 1:
        raise CliError(f"--horizon must be >= 1 step, got {args.horizon}")
    if not 0 <= args.warmup < info["horizon"]:
        raise CliError(
            f"--horizon {info['horizon']} leaves no step to score after --warmup {args.warmup}: pass a --horizon "
            f"above {args.warmup}, or a smaller --warmup (0 scores every step)"
            if args.horizon is not None
            else f"--warmup {args.warmup} leaves no step of {info['horizon']}-step trajectories to score: pass a "
            "smaller --warmup (0 scores every step)"
        )
    return scenario, datasets, methods, checkpoints, recorded, options, info


def _print_evaluation(args, scenario, results, info: dict[str, Any], recorded_data: bool) -> None:
    """The table of ``results`` with its heading, notes, marks legend, scored steps and speeds."""
    from neural_estimator.paper import departures as D
    from neural_estimator.evaluation import departure_legend, results_table
    from neural_estimator.paper.expected_failures import mark_rows, notes

    if recorded_data:
        print(
            f"recorded data {args.data}: {info['trajectories']} trajectories x {info['horizon']} steps"
            + _scored(args.warmup)
        )
        partial = _partial_line(r for res in results.values() for r in res.reports)
        if partial:
            print(partial)
    else:
        print(
            f"{scenario.name}: {args.sets} sets x {args.trajectories} trajectories x {info['horizon']} steps"
            f"{_scored(args.warmup)}, "
            f"filters start from the {_START_WORDS[args.init]} (median ± IQR over runs)"
        )
    if info.get("model_set"):
        told = ", ".join(f"{k}={v}" for k, v in info["model_set"].items())
        print(
            f"model-based methods told a wrong model on purpose (--model-set): {told}; data and networks: the true one"
        )
    starts = {m: r.init for m, r in results.items()}
    print(mark_rows(results_table(results, fmt="text", marked=True), scenario.name, starts), end="")
    for line in notes(scenario.name, list(results), starts):
        print(line)
    for line in departure_legend(results):
        print(line)
    print(D.scored_steps(args.warmup))
    _print_decision(scenario, results)
    _print_consistency(results, scenario.dx)
    print(
        "speed: "
        + ", ".join(
            f"{m} {r.throughput:,.0f} traj-steps/s"
            if r.seconds
            else f"{m} recorded" + (f" ({r.cached} cached runs)" if r.cached else "")
            for m, r in results.items()
        )
    )


def _print_decision(scenario, results) -> None:
    """Per-component RMSE, the paired ratio to the best filter with its interval, the verdict."""
    from neural_estimator.evaluation.decision import decision_notes, decision_table

    table = decision_table(scenario, results, fmt="text")
    if table:
        print("per component (own units, median over runs) and against the best filter:")
        print(table, end="")
        for line in decision_notes(scenario, results):
            print(line)


def _print_consistency(results, dx: int) -> None:
    """The consistency table of the methods that report a covariance (docs/uncertainty.md)."""
    from neural_estimator.metrics.consistency import COVERAGE_BAND, NEES_BAND
    from neural_estimator.evaluation import consistency_table

    table = consistency_table(results, dx, fmt="text")
    if table:
        print(
            f"consistency of the reported covariances (consistent: 95% coverage in {list(COVERAGE_BAND)} "
            f"and mean NEES/dx in {list(NEES_BAND)}; a wide covariance is as wrong as a narrow one):"
        )
        print(table, end="")


_START_WORDS = {
    "prior": "prior",
    "truth": "true x0",
    "observation": "first observation where it determines state components, else the prior",
}


def _scored(warmup: int) -> str:
    """' (steps 10.. scored)' for a table's heading; nothing when every step is."""
    return f" (steps {warmup}.. scored)" if warmup else ""
