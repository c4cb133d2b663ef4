"""The ``neural-estimator`` command line: a thin front end over the library.

Verbs (``neural-estimator VERB --help`` for each):
    simulate   write a dataset (.npz) of a scenario
    metrics    the paper's table from a truth file and an estimate file (or one file, or an MCAP bag)
    evaluate   run methods on the three evaluation sets and print the paper's per-scenario table
    train      train a neural estimator with the paper's protocol
    live       a live ROS 2 run (simulator, estimators, evaluator) ending with the table and an MCAP bag
    replay     run an MCAP bag's observations through estimators offline
    recover    rewrite a damaged or unfinished bag into a valid .mcap
    scenarios  list the registered scenarios and their constants
    reproduce  the paper's experiments on Ray, with a report beside the paper's numbers
    dataset    recorded bags of a robot -> a dataset (.npz), through a spec of message fields
    ros2       the minimal ``ros2 run`` / ``ros2 pkg executables`` of pip environments

``train`` and ``evaluate`` take ``--data FILE.npz`` (a recorded dataset) instead of ``--scenario``.

Every command accepts ``--plugin FILE`` (repeatable) to import a Python file that registers user
scenarios. Errors in the input print one line naming the problem and exit with status 2.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, Callable

from neural_estimator.scenarios import (
    ScenarioError,
    load_plugins,
    make_scenario,
    parse_assignments,
    preset_names,
    scenario_names,
)

EXIT_BAD_INPUT = 2


class CliError(Exception):
    """A command-line usage problem (message shown to the user, exit status 2)."""


class OneLineParser(argparse.ArgumentParser):
    """argparse whose usage errors are one line (no usage block) and suggest the closest verb or flag
    to a mistyped one ("did you mean"), with exit status 2. Sub-parsers inherit the class."""

    _argv: list[str] = []

    def parse_args(self, args=None, namespace=None):  # noqa: D102 - argparse's
        self._argv = list(sys.argv[1:] if args is None else args)
        return super().parse_args(args, namespace)

    def _flags(self) -> list[str]:
        """The option strings of this parser, or of the verb named on the command line."""
        parser = self
        for action in self._actions:
            if isinstance(action, argparse._SubParsersAction):
                verb = next((a for a in self._argv if a in action.choices), None)
                if verb is not None:
                    parser = action.choices[verb]
        return [o for a in parser._actions for o in a.option_strings if o.startswith("--")]

    def error(self, message: str):  # noqa: D102 - argparse's
        import re

        from neural_estimator.options import did_you_mean

        m = re.match(r"unrecognized arguments: (.*)", message)
        if m:
            flags = [w.split("=", 1)[0] for w in m.group(1).split() if w.startswith("-")]
            if flags:
                message = f"unrecognized option {flags[0]}{did_you_mean(flags[0], self._flags())}"
                if len(flags) > 1:
                    message += f" (and {', '.join(flags[1:])})"
        m = re.search(r"invalid choice: '([^']*)' \(choose from (.*)\)", message)
        if m:
            choices = re.findall(r"'([^']*)'", m.group(2))
            message = message.replace(f"'{m.group(1)}'", f"'{m.group(1)}'{did_you_mean(m.group(1), choices)}", 1)
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def scenario_from_args(args: argparse.Namespace):
    """The scenario named by ``--scenario`` with ``--set`` overrides and ``--noise-scale``."""
    overrides: dict[str, Any] = parse_assignments(getattr(args, "set", None))
    if getattr(args, "noise_scale", None) is not None:
        overrides["noise_scale"] = args.noise_scale
    return make_scenario(args.scenario, preset=getattr(args, "preset", None), **overrides)


def _preset_flag(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--preset",
        metavar="NAME",
        help="named set of the scenario's constants, applied before --set (built-ins: v4, the default; "
        "v3, the constants before the spread calibration; see docs/scenarios.md)",
    )


def _common(p: argparse.ArgumentParser, scenario: bool = True, data: bool = False) -> None:
    p.add_argument("--plugin", action="append", metavar="FILE", help="Python file registering user scenarios")
    if scenario:
        p.add_argument(
            "--scenario",
            required=not data,
            help=f"one of: {', '.join(scenario_names())} (or a plugin's)" + ("; or --data" if data else ""),
        )
        p.add_argument("--set", action="append", metavar="NAME=VALUE", help="override a scenario constant (repeatable)")
        _preset_flag(p)
        p.add_argument("--noise-scale", type=float, help="multiply the observation-noise std (filters are told)")


# ---- simulate ---------------------------------------------------------------------------------
def _add_simulate(sub) -> None:
    p = sub.add_parser("simulate", help="write a dataset (.npz) of a scenario")
    _common(p)
    p.add_argument("--trajectories", type=int, default=100)
    p.add_argument("--horizon", type=int, help="steps per trajectory (default: the scenario's)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True, help="output .npz")
    p.set_defaults(func=_cmd_simulate)


def _cmd_simulate(args) -> int:
    from neural_estimator.data import save_trajectories, simulate

    scenario = scenario_from_args(args)
    data = simulate(scenario, args.trajectories, args.horizon, args.seed)
    path = save_trajectories(args.out, data)
    print(
        f"wrote {path}: {data.n} trajectories x {data.horizon} steps of {scenario.name} "
        f"(x {data.x.shape[2]}, y {data.y.shape[2]}, u {data.u.shape[2]}), seed {args.seed}"
    )
    return 0


# ---- scenarios ----------------------------------------------------------------------------------
def _add_scenarios(sub) -> None:
    p = sub.add_parser("scenarios", help="list the registered scenarios and their constants")
    _common(p, scenario=False)
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=_cmd_scenarios)


def _cmd_scenarios(args) -> int:
    descs = [make_scenario(n).describe() for n in scenario_names()]
    if args.json:
        print(json.dumps(descs, indent=2))
        return 0

    def names(ns, us):
        if len(ns) > 8:
            return f"{ns[0]} .. {ns[-1]} ({len(ns)})" + (f" [{us[0]}]" if us[0] else "")
        return ", ".join(f"{n} [{u}]" if u else n for n, u in zip(ns, us))

    for d in descs:
        print(f"{d['scenario']}: x = [{names(d['state_names'], d['state_units'])}]")
        print(
            f"  y = [{names(d['obs_names'], d['obs_units'])}]"
            + (f", u = [{names(d['control_names'], d['control_units'])}]" if d["control_names"] else "")
            + f", dt = {d['dt']} s"
            + (f"; preset {d['preset']} (presets: {', '.join(preset_names(d['scenario']))})" if "preset" in d else "")
        )
        print("  " + ", ".join(f"{k}={v}" for k, v in d["config"].items() if not isinstance(v, list) or len(v) <= 4))
    return 0


# ---- metrics ------------------------------------------------------------------------------------
def _add_metrics(sub) -> None:
    p = sub.add_parser("metrics", help="the paper's table from a truth file and estimate files (or an MCAP bag)")
    p.add_argument("--plugin", action="append", metavar="FILE", help="Python file registering user scenarios")
    p.add_argument(
        "files",
        nargs="+",
        metavar="FILE",
        help="an estimate .npz (x and x_hat), or a truth .npz followed by estimate .npz files, or a bag "
        "(.mcap file or rosbag2 directory)",
    )
    _bag_scenario_flags(p)
    p.add_argument(
        "--spec",
        metavar="SPEC.yaml",
        help="a bag of a live run on recorded-data models (section 'Your own robot'): the ground truth is "
        "the spec's state fields, each estimates/<method> stream is scored",
    )
    p.add_argument("--length", type=int, default=200, help="with --spec: steps per scored trajectory (default 200)")
    _warmup_flag(p)
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


def _warmup_flag(p: argparse.ArgumentParser) -> None:
    """``--warmup N``: leading timesteps of every trajectory that are not scored (metrics verbs)."""
    from neural_estimator.metrics import EVALUATION_WARMUP

    p.add_argument(
        "--warmup",
        type=int,
        default=EVALUATION_WARMUP,
        metavar="N",
        help=f"leading timesteps of every trajectory not scored, for every method alike (default "
        f"{EVALUATION_WARMUP}: this project's choice; the paper states its {EVALUATION_WARMUP}-step warm-up for "
        "the training loss only; 0 scores every step)",
    )
    p.add_argument(
        "--every-step",
        dest="warmup",
        action="store_const",
        const=0,
        help="score every step of every trajectory (the same as --warmup 0)",
    )


def _bag_scenario_flags(p: argparse.ArgumentParser) -> None:
    """Flags of the verbs that read a bag: its namespace, and the scenario of a bag without one."""
    p.add_argument("--namespace", default="/", help="namespace of the recorded streams")
    p.add_argument(
        "--scenario",
        help="scenario of a bag without a /scenario message (e.g. one recorded from your "
        "own nodes); overrides the bag's",
    )
    p.add_argument(
        "--set", action="append", metavar="NAME=VALUE", help="scenario constant, with --scenario (repeatable)"
    )
    _preset_flag(p)


def _bag_description(args: argparse.Namespace) -> dict[str, Any] | None:
    """The description named by ``--scenario``/``--set``, or None (use the bag's own)."""
    if getattr(args, "scenario", None):
        return make_scenario(args.scenario, preset=args.preset, **parse_assignments(args.set)).describe()
    if getattr(args, "set", None) or getattr(args, "preset", None):
        flag = "--set" if getattr(args, "set", None) else "--preset"
        raise CliError(f"{flag} needs --scenario (the bag's own scenario message carries its constants)")
    return None


def _is_bag(path: str) -> bool:
    return path.endswith(".mcap") or Path(path).is_dir()


def _estimates_from_files(files: list[str], args: argparse.Namespace | None = None):
    """(truth Trajectories, {method: (x_hat, P_hat or None)}, angle_states) from npz files or a bag."""
    from neural_estimator.data.io import load_truth_and_estimates

    if len(files) == 1 and _is_bag(files[0]):
        from neural_estimator.bags import load_bag_dataset

        return load_bag_dataset(
            files[0],
            namespace=getattr(args, "namespace", "/") or "/",
            description=_bag_description(args) if args is not None else None,
        )
    if any(_is_bag(f) for f in files):
        raise CliError("a bag is scored on its own: pass one .mcap file or rosbag2 directory")
    return load_truth_and_estimates(files)


def _cmd_metrics(args) -> int:
    if args.spec:
        return _print_spec_metrics(args)
    return _print_metrics(args.files, args, as_json=args.json, out=args.out)


def _print_spec_metrics(args) -> int:
    """The metrics of a recorded live run of recorded-data models, scored through a spec."""
    from neural_estimator import metrics as M
    from neural_estimator.robot import SpecError
    from neural_estimator.robot.score import score_recording

    if len(args.files) != 1 or not _is_bag(args.files[0]):
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
    from neural_estimator import departures as D
    from neural_estimator import metrics as M
    from neural_estimator.expected_failures import mark_rows, notes

    truth, estimates, angles = _estimates_from_files(files, args)
    warmup = getattr(args, "warmup", M.EVALUATION_WARMUP)
    if not 0 <= warmup < truth.horizon:
        raise CliError(
            f"--warmup {warmup} leaves no step of {truth.horizon}-step trajectories to score: pass a smaller "
            "--warmup (0 scores every step)"
        )
    reports = {m: M.compute_metrics(truth.x, xh, angles, P_hat=P, warmup=warmup) for m, (xh, P) in estimates.items()}
    note = ""
    if "bag" in truth.meta:
        from neural_estimator.bags.dataset import left_out_note

        note = left_out_note(truth.meta["bag"])
        if note:  # a partly scorable bag: say what the table does not cover
            print(f"neural-estimator: note: {note}", file=sys.stderr)
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
        print(mark_rows(table, scenario_name, starts), end="")
        used = {x for v in rows.values() for x in v} | ({D.OUTLIERS} if cells else set())
        for line in notes(scenario_name, list(reports), starts) + D.legend_text(used) + [D.scored_steps(warmup)]:
            print(line)
    if out:
        _write_table(out, reports)
    return 0


def _write_table(path: str, reports) -> None:
    from neural_estimator import metrics as M

    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    if out.suffix == ".csv":
        out.write_text(M.format_reports(reports, fmt="csv"))
    elif out.suffix == ".json":
        out.write_text(json.dumps(M.to_json(reports), indent=1, allow_nan=False))
    else:
        out.write_text(M.format_reports(reports, fmt="markdown"))
    print(f"wrote {out}")


# ---- evaluate -----------------------------------------------------------------------------------
_DEFAULT_METHODS = "ekf,ukf,enkf,pf"


def _add_evaluate(sub) -> None:
    p = sub.add_parser("evaluate", help="run methods on the evaluation sets; print the paper's table")
    _common(p, data=True)
    p.add_argument(
        "--data",
        metavar="FILE.npz",
        help="a recorded dataset (neural-estimator dataset) instead of --scenario: its trajectories are the "
        "one evaluation set; neural methods need --checkpoint",
    )
    p.add_argument(
        "--estimate",
        action="append",
        metavar="NAME=FILE.npz",
        help="with --data: a recorded estimate file (neural-estimator dataset writes one per spec estimate) "
        "scored as one more row",
    )
    p.add_argument(
        "--methods",
        default=_DEFAULT_METHODS,
        help="comma-separated (ekf ukf enkf pf gru lstm gpt2 "
        "filterformer mamba mamba2); with --data: default the --checkpoint methods",
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
    _warmup_flag(p)
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
        help="directory for table.md, table.csv, results.json (rewritten after every run) and rmse_over_time.png",
    )
    p.set_defaults(func=_cmd_evaluate)


def _parse_checkpoints(items: list[str] | None) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for item in items or ():
        method, sep, paths = item.partition("=")
        if not sep or not paths:
            raise CliError(f"--checkpoint expects METHOD=DIR[,DIR...], got {item!r}")
        out.setdefault(method.strip().lower(), []).extend(p for p in paths.split(",") if p)
    return out


def _parse_options(items: list[str] | None) -> dict[str, dict[str, Any]]:
    """{method: {name: text}}: the values stay text, parsed by the method against each option's type
    (:mod:`neural_estimator.options`)."""
    out: dict[str, dict[str, Any]] = {}
    for item in items or ():
        key, sep, value = item.partition("=")
        method, dot, name = key.partition(".")
        if not sep or not dot or not name:
            raise CliError(f"--option expects METHOD.NAME=VALUE, got {item!r}")
        out.setdefault(method.strip().lower(), {})[name.strip()] = value.strip()
    return out


def _scenario_or_data(args: argparse.Namespace):
    """(scenario, None) from --scenario, or (DataScenario, [the recorded trajectories]) from --data."""
    if getattr(args, "data", None) is None:
        if getattr(args, "scenario", None) is None:
            raise CliError("pass --scenario NAME, or --data FILE.npz for recorded data")
        return scenario_from_args(args), None
    if getattr(args, "scenario", None) is not None or getattr(args, "set", None) or getattr(args, "preset", None):
        raise CliError("--data brings its own interface: drop --scenario, --set and --preset")
    from neural_estimator.data import load_trajectories
    from neural_estimator.robot import DataScenario

    data, _ = load_trajectories(args.data)
    if data.meta.get("scenario") != "data":
        raise CliError(
            f"{args.data}: not a recorded dataset (scenario {data.meta.get('scenario')!r}); "
            "make one with neural-estimator dataset, or pass --scenario"
        )
    try:
        scenario = DataScenario(data.meta)
    except ScenarioError as exc:
        raise CliError(f"{args.data}: {exc}") from None
    return scenario, [data]


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
    from neural_estimator.estimators import CLASSICAL_METHODS, check_method
    from neural_estimator import departures as D
    from neural_estimator.evaluation import departure_legend, evaluate, results_json, results_table
    from neural_estimator.expected_failures import mark_rows, notes

    scenario, datasets = _scenario_or_data(args)
    methods = [check_method(m) for m in args.methods.split(",") if m.strip()]
    checkpoints = _parse_checkpoints(args.checkpoint)
    for m in checkpoints:
        check_method(m)
    recorded = {}
    if datasets is not None:
        if args.methods == _DEFAULT_METHODS:  # not given: the methods of the checkpoints
            methods = list(checkpoints)
        for m in methods:
            if m in CLASSICAL_METHODS:
                raise CliError(
                    f"{m}: recorded data have no model for a classical filter; compare the robot's own "
                    "filter with --estimate NAME=FILE"
                )
            if m not in checkpoints:
                raise CliError(f"{m}: recorded data have no shipped model: pass --checkpoint {m}=DIR")
        recorded = _recorded_estimates(args.estimate, datasets[0])
    elif args.estimate:
        raise CliError("--estimate needs --data")
    if not methods and not recorded:
        raise CliError(
            "--methods is empty"
            if datasets is None
            else "nothing to evaluate: pass --checkpoint METHOD=DIR or --estimate NAME=FILE"
        )
    options = _parse_options(args.option)
    if args.threads is not None:
        if args.threads < 1:
            raise CliError(f"--threads must be >= 1, got {args.threads}")
        for m in methods:
            if m in CLASSICAL_METHODS:
                options.setdefault(m, {}).setdefault("threads", args.threads)
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
    out = Path(args.out) if args.out else None
    expected_runs = {m: info["sets"] * max(1, len(checkpoints.get(m) or ())) for m in methods}
    expected_runs.update({name: 1 for name in recorded})

    def write_partial(results) -> None:  # after every run: an interrupted evaluate leaves its finished runs
        if out is not None:
            _write_evaluation(out, scenario, results, info, expected_runs, plot=False)

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
    )
    if recorded:
        from neural_estimator.evaluation import recorded_result

        for name, x_hat in recorded.items():
            results[name] = recorded_result(scenario, datasets[0], x_hat, name, warmup=args.warmup)
    if args.json:
        print(json.dumps(results_json(scenario, results, complete=True, **info), indent=1, allow_nan=False))
    else:
        if datasets is not None:
            print(
                f"recorded data {args.data}: {info['trajectories']} trajectories x {info['horizon']} steps"
                + _scored(args.warmup)
            )
        else:
            print(
                f"{scenario.name}: {args.sets} sets x {args.trajectories} trajectories x {info['horizon']} steps"
                f"{_scored(args.warmup)}, "
                f"filters start from the {_START_WORDS[args.init]} (median ± IQR over runs)"
            )
        starts = {m: r.init for m, r in results.items()}
        print(mark_rows(results_table(results, fmt="text", marked=True), scenario.name, starts), end="")
        for line in notes(scenario.name, list(results), starts):
            print(line)
        for line in departure_legend(results):
            print(line)
        print(D.scored_steps(args.warmup))
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
    if out is not None:
        _write_evaluation(out, scenario, results, info, expected_runs, plot=True)
        print(f"wrote {out}/table.md, table.csv, results.json, rmse_over_time.png", file=sys.stderr)
    return 0


def _print_consistency(results, dx: int) -> None:
    """The consistency table of the methods that report a covariance (docs/uncertainty.md)."""
    from neural_estimator.consistency import COVERAGE_BAND, NEES_BAND
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


def _write_evaluation(
    out: Path, scenario, results, info: dict[str, Any], expected_runs: dict[str, int], plot: bool
) -> None:
    """table.md, table.csv and results.json of the runs so far ("complete" says whether all are in)."""
    from neural_estimator.evaluation import results_json, results_table

    done = {m: r for m, r in results.items() if r.reports}
    complete = all(len(results[m].reports) == n for m, n in expected_runs.items())
    out.mkdir(parents=True, exist_ok=True)
    from neural_estimator import departures as D
    from neural_estimator.evaluation import departure_marks

    _, _, used = departure_marks(done)
    legend = [f"- {line}" for line in D.legend(used, [r.context for r in done.values()])]
    (out / "table.md").write_text(
        results_table(done, fmt="markdown", marked=True)
        + "".join(f"\n{line}" for line in legend)
        + f"\n\n{D.scored_steps(info.get('warmup', 0))}\n"
    )
    (out / "table.csv").write_text(results_table(done, fmt="csv"))
    from neural_estimator.evaluation import consistency_table

    consistency = consistency_table(done, scenario.dx)
    if consistency:
        (out / "consistency.md").write_text(consistency)
    payload = results_json(scenario, done, complete=complete, **info)
    tmp = out / "results.json.tmp"
    tmp.write_text(json.dumps(payload, indent=1, allow_nan=False))
    tmp.replace(out / "results.json")
    if plot:
        from neural_estimator.plots import plot_rmse_over_time

        plot_rmse_over_time(
            {m: [rep.rmse_t for rep in r.reports] for m, r in done.items()},
            out / "rmse_over_time.png",
            title=scenario.name,
            dt=scenario.dt,
            first_step=info.get("warmup", 0),
        )


# ---- train --------------------------------------------------------------------------------------
_TRAIN_FLAG_HELP = {
    "data_ratio": "data-to-parameter ratio: 20 (paper's default), 10, 5 or 1",
    "data_seed": "seed of the training/validation/evaluation sets",
    "init_seed": "seed of the initial weights, dropout and window draws",
    "trajectories": "training trajectories (default: from --data-ratio; 20:1 -> 4000 x 500 steps)",
    "windows_per_epoch": "windows per epoch (default: the set's timesteps once)",
    "epochs": "maximum epochs (paper: 500)",
    "patience": "early-stopping patience in epochs (paper: 30)",
    "eval_trajectories": "metrics of the best model on that many evaluation trajectories, in the card "
    "(default 200, a few seconds to minutes; 0: none)",
    "val_trajectories": "validation trajectories, run in full after every epoch (default: half the training "
    "trajectories, at most the paper's 8000; 20:1 -> 2000)",
}
_TRAIN_FLAG_HELP["loss_units"] = (
    "units the loss weighs the state components in: state (the states' own units, as RMSE counts them; "
    "default) or normalised (each at unit variance; cards without the field); the paper does "
    "not say which"
)
_TRAIN_FLAG_HELP["val_context"] = (
    "> 0: validate (and so choose the checkpoint) with the context bounded to this many steps: "
    "--val-context-copies copies restarted at staggered steps (gru, lstm, mamba, mamba2), the attention "
    "window (gpt2, filterformer); not the paper's recipe; the model then serves bounded by default "
    "(default: 0, the paper's validation)"
)
_TRAIN_FLAG_HELP["val_context_copies"] = "copies for --val-context (K times the validation compute; default: 4)"
_TRAIN_DEFAULTS = {
    "eval_trajectories": 200,
    "val_trajectories": None,
}  # the CLI's, where they differ from TrainConfig's


def _add_train(sub) -> None:
    import dataclasses

    from neural_estimator.data.recipe import TrainConfig  # no torch: the flags cost nothing to list

    p = sub.add_parser("train", help="train a neural estimator with the paper's protocol")
    _common(p, data=True)
    p.add_argument(
        "--data",
        metavar="FILE.npz",
        help="train on a recorded dataset (neural-estimator dataset) instead of simulating --scenario",
    )
    p.add_argument(
        "--val-data",
        metavar="FILE.npz",
        help="with --data: the validation set (default: the last --val-fraction of --data's trajectories)",
    )
    p.add_argument(
        "--val-fraction",
        type=float,
        default=0.2,
        help="with --data and no --val-data: share of the "
        "trajectories held out for validation, split by trajectory (default 0.2)",
    )
    p.add_argument("--model", required=True, help="gru, lstm, gpt2, filterformer, mamba or mamba2")
    p.add_argument("--out", required=True, help="output directory (model.safetensors + card.json)")
    p.add_argument("--model-set", action="append", metavar="NAME=VALUE", help="override an architecture hyperparameter")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    # Every TrainConfig field is a flag with the paper's default (one source of truth).
    for f in dataclasses.fields(TrainConfig):
        if f.name in ("model_overrides", "resume", "keep_resume"):
            continue
        default = _TRAIN_DEFAULTS.get(f.name, f.default)
        flag = "--" + f.name.replace("_", "-")
        kind = type(f.default) if f.default is not None else int
        if f.name == "cache_dir":
            kind = str
        p.add_argument(flag, type=kind, default=default, help=_TRAIN_FLAG_HELP.get(f.name, f"default: {default}"))
    p.add_argument("--resume", action="store_true", help="continue from OUT/resume if it exists")
    p.add_argument("--no-keep-resume", action="store_true", help="delete OUT/resume after the run")
    p.add_argument(
        "--threads",
        type=int,
        default=1,
        metavar="N",
        help="CPU threads for torch and the fused scan kernels (default 1: on this project's 2-core "
        "machine one process per core beats two threads in one; see docs/performance.md)",
    )
    p.set_defaults(func=_cmd_train)


def _cmd_train(args) -> int:
    import dataclasses

    from neural_estimator.estimators import NEURAL_METHODS, check_method
    from neural_estimator.data.recipe import TrainConfig, TrainingError
    from neural_estimator.models.training import train

    method = check_method(args.model)
    if method not in NEURAL_METHODS:
        raise CliError(f"--model must be a neural method ({', '.join(NEURAL_METHODS)}), got {args.model!r}")
    scenario, datasets = _scenario_or_data(args)
    data = None
    if datasets is not None:
        data = _train_val_split(args, scenario, datasets[0])
    elif args.val_data:
        raise CliError("--val-data needs --data")
    values = {f.name: getattr(args, f.name) for f in dataclasses.fields(TrainConfig) if hasattr(args, f.name)}
    values.update(
        model_overrides=_parse_model_overrides(args.model_set), resume=args.resume, keep_resume=not args.no_keep_resume
    )
    if args.threads < 1:
        raise CliError(f"--threads must be >= 1, got {args.threads}")
    import torch

    torch.set_num_threads(args.threads)
    if data is not None:
        values.update(trajectories=data[0].n, train_length=data[0].horizon, val_trajectories=data[1].n)
    if values["val_trajectories"] is None:  # scales with the training set: half of it, at most the paper's 8000
        from neural_estimator.data.protocol import VALIDATION_TRAJECTORIES, training_trajectories

        n_train = values["trajectories"] or training_trajectories(values["data_ratio"], length=values["train_length"])
        values["val_trajectories"] = max(1, min(VALIDATION_TRAJECTORIES, int(n_train) // 2))
    if not args.quiet:
        print(
            f"validation after every epoch: {values['val_trajectories']} trajectories x {values['train_length']} "
            f"steps (--val-trajectories); card metrics on {values['eval_trajectories']} evaluation trajectories "
            f"(--eval-trajectories); {args.threads} thread(s) (--threads)",
            flush=True,
        )
    try:
        config = TrainConfig(**values)
        path = train(scenario, method, args.out, config, progress=not args.quiet, data=data)
    except TrainingError as exc:
        raise CliError(str(exc)) from None
    print(f"wrote {path}")
    return 0


def _train_val_split(args: argparse.Namespace, scenario, train_data):
    """(training, validation) trajectories from --data and --val-data, or a split by trajectory."""
    if args.val_data:
        from neural_estimator.data import load_trajectories

        val, _ = load_trajectories(args.val_data)
        if val.meta.get("spec_sha256") != train_data.meta.get("spec_sha256"):
            raise CliError(f"{args.val_data} was made with another spec than {args.data}")
        return train_data, val
    if not 0 < args.val_fraction < 1:
        raise CliError(f"--val-fraction must be between 0 and 1, got {args.val_fraction}")
    n_val = int(round(train_data.n * args.val_fraction))
    if n_val < 1 or n_val >= train_data.n:
        raise CliError(
            f"{args.data}: {train_data.n} trajectories cannot be split into training and validation "
            f"(--val-fraction {args.val_fraction}); record more, or cut shorter ones (dataset --length)"
        )
    return train_data.subset(slice(0, train_data.n - n_val)), train_data.subset(slice(train_data.n - n_val, None))


def _parse_model_overrides(items: list[str] | None) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for name, value in parse_assignments(items).items():
        try:
            out[name] = json.loads(value)
        except json.JSONDecodeError:
            out[name] = value
    return out


# ---- live ---------------------------------------------------------------------------------------
def _add_live(sub) -> None:
    p = sub.add_parser(
        "live",
        add_help=False,  # dispatched before parsing, see main()
        help="live ROS 2 run: simulator -> estimators -> evaluator, ends with the table and the MCAP bag",
    )
    p.add_argument("rest", nargs=argparse.REMAINDER)
    p.set_defaults(func=_cmd_live)


def _cmd_live(args) -> int:
    from neural_estimator.nodes.launch import main as launch_main

    return launch_main(args.rest)


# ---- replay -------------------------------------------------------------------------------------
def _add_replay(sub) -> None:
    p = sub.add_parser("replay", help="run an MCAP bag's observations through estimators offline (no DDS)")
    p.add_argument("--plugin", action="append", metavar="FILE", help="Python file registering user scenarios")
    p.add_argument(
        "bag",
        help="input bag: .mcap file or rosbag2 directory (recorded by the evaluator, by "
        "`ros2 bag record`, or a sample bag from bags/)",
    )
    p.add_argument("--methods", required=True, help="comma-separated methods")
    p.add_argument("--out", required=True, help="output .mcap: the input's messages plus the estimates")
    p.add_argument("--checkpoint", action="append", metavar="METHOD=DIR", help="checkpoint of a neural method")
    p.add_argument("--option", action="append", metavar="METHOD.NAME=VALUE", help="filter hyperparameter")
    p.add_argument("--device", default="cpu")
    p.add_argument("--seed", type=int, default=0)
    _bag_scenario_flags(p)
    p.add_argument(
        "--threads",
        type=int,
        default=1,
        metavar="N",
        help="torch threads of neural methods (default 1: fastest for one-step updates; 0 = torch's default)",
    )
    p.add_argument(
        "--order",
        choices=("recorded", "identity"),
        default="recorded",
        help="process observations as recorded (default: exactly as a live estimator node) or sorted "
        "by (trajectory, step) for bags recorded out of order",
    )
    p.add_argument("--no-covariance", action="store_true", help="do not write covariance streams")
    p.add_argument(
        "--init",
        choices=("prior", "observation"),
        default="prior",
        help="how the classical filters start each trajectory: prior (default, the paper's start) or observation "
        "(the state the first observation determines where h is invertible; Lorenz 96: x0 = y0)",
    )
    p.add_argument("--overwrite", action="store_true")
    p.add_argument("--metrics", action="store_true", help="print the metrics table of the output bag")
    _warmup_flag(p)
    p.set_defaults(func=_cmd_replay)


def _cmd_replay(args) -> int:
    from neural_estimator.estimators import CLASSICAL_METHODS, check_method
    from neural_estimator.replay import replay

    methods = [check_method(m) for m in args.methods.split(",") if m.strip()]
    ckpts = {m: paths[-1] for m, paths in _parse_checkpoints(args.checkpoint).items()}
    options = _parse_options(args.option)
    starts = {}
    if args.init != "prior":
        for m in methods:
            if m in CLASSICAL_METHODS:
                options.setdefault(m, {}).setdefault("init", args.init)
                starts[m] = options[m]["init"]
    if args.threads < 0:
        raise CliError(f"--threads must be >= 0 (0 = torch's default), got {args.threads}")
    _check_out(args.out, args.overwrite)
    res = replay(
        args.bag,
        methods,
        args.out,
        ckpts,
        device=args.device,
        seed=args.seed,
        namespace=args.namespace,
        options=options,
        publish_covariance=not args.no_covariance,
        overwrite=args.overwrite,
        description=_bag_description(args),
        order=args.order,
        threads=args.threads,
    )
    print(
        f"wrote {res.path}: {res.observations} observations; "
        + ", ".join(
            f"{m} {res.estimates[m]} estimates ({res.per_step_us(m):.0f} us/step"
            + (f", {res.rejected[m]} rejected" if res.rejected.get(m) else "")
            + (f", {res.skipped[m]} duplicate, stale or unconfirmed skipped" if res.skipped.get(m) else "")
            + ")"
            for m in methods
        )
    )
    if args.metrics:
        return _print_metrics([str(res.path)], args, starts=starts)
    return 0


def _check_out(out: str, overwrite: bool) -> None:
    """An existing ``--out`` is replaced only with ``--overwrite`` (the flag's name in the message)."""
    if Path(out).exists() and not overwrite:
        raise CliError(f"{out}: file exists; pass --overwrite to replace it")


# ---- recover ------------------------------------------------------------------------------------
def _add_recover(sub) -> None:
    p = sub.add_parser(
        "recover", help="rewrite a damaged or unfinished bag (e.g. a killed recorder's) into a valid .mcap"
    )
    p.add_argument("bag", help="the damaged .mcap file (or rosbag2 directory)")
    p.add_argument("--out", required=True, help="the valid .mcap to write")
    p.add_argument("--overwrite", action="store_true")
    p.set_defaults(func=_cmd_recover)


def _cmd_recover(args) -> int:
    from neural_estimator.bags.recover import recover_bag

    if Path(args.out).exists() and Path(args.out).resolve() == Path(args.bag).resolve():
        raise CliError(f"{args.out}: recover writes a new file; it cannot overwrite its input (choose another --out)")
    _check_out(args.out, args.overwrite)
    res = recover_bag(args.bag, args.out, overwrite=args.overwrite)
    lost = f"; the input had lost: {res.damage}" if res.damage is not None else "; the input was intact"
    note = f"; {res.lost_note()}" if res.lost else ""
    print(f"wrote {res.path}: {res.messages} messages on {res.topics} topics{lost}{note}")
    return 0


# ---- reproduce ----------------------------------------------------------------------------------
def _add_reproduce(sub) -> None:
    p = sub.add_parser("reproduce", help="the paper's experiments on Ray; a report beside the paper's numbers")
    p.add_argument("--scale", required=True, choices=("smoke", "small", "paper"), help="sizes (docs/reproduce.md)")
    p.add_argument(
        "--plugin",
        action="append",
        metavar="FILE",
        help="Python file registering user scenarios (loaded by every Ray worker too)",
    )
    p.add_argument("--scenarios", help="comma-separated (default: the paper's five; plugin scenarios allowed)")
    p.add_argument("--methods", help="comma-separated (default: all ten)")
    p.add_argument("--out", default="reproduce-out", help="directory of report.md, figures/, reproduce.json")
    p.add_argument("--address", help="Ray cluster to join (default: a local Ray instance)")
    p.add_argument("--num-cpus", type=int, help="CPUs of the local Ray instance (default: usable cores, at most 4)")
    p.add_argument(
        "--cache-dir",
        help="job result cache (default: $NEURAL_ESTIMATOR_CACHE or ~/.cache/neural_estimator; "
        "on a cluster, a path every node sees)",
    )
    p.add_argument("--resume", action="store_true", help="continue the run in --out (finished jobs are read back)")
    p.add_argument(
        "--init",
        choices=("prior", "truth", "observation"),
        default="prior",
        help="classical filters of the accuracy and noise experiments start from the scenario prior "
        "(default, the paper's start; expected failures are marked), at each trajectory's true x0, or at the "
        "state the first observation determines where h is invertible",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_reproduce)


def _cmd_reproduce(args) -> int:
    try:
        import ray.util  # noqa: F401 - the optional dependency of this verb
    except ImportError:
        raise CliError("reproduce runs its jobs on Ray: pip install 'neural_estimator[reproduce]'") from None
    from neural_estimator.reproduce.cli import run_from_args

    return run_from_args(args, CliError)


# Verbs are added to this list as their modules land; each is (adder).
def _add_dataset(sub) -> None:
    p = sub.add_parser("dataset", help="recorded bags of a robot -> a dataset (.npz) through a spec of message fields")
    p.add_argument("bags", nargs="+", metavar="BAG", help=".mcap files or rosbag2 directories (any recorder)")
    p.add_argument(
        "--spec",
        required=True,
        metavar="SPEC.yaml",
        help="the observation, control and state as message "
        "fields on topics, the rate and the alignment (docs/robot.md)",
    )
    p.add_argument("--out", required=True, metavar="DATA.npz")
    p.add_argument(
        "--length",
        type=int,
        default=500,
        help="steps per trajectory: each segment of valid ticks is cut "
        "into trajectories of this length (default 500, the paper's)",
    )
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_dataset)


def _cmd_dataset(args) -> int:
    from neural_estimator.data.io import save_estimates, save_trajectories
    from neural_estimator.robot import SpecError, build_dataset, load_spec

    try:
        spec = load_spec(args.spec)
        data, estimates, summaries = build_dataset(args.bags, spec, args.length, progress=None if args.quiet else print)
    except SpecError as exc:
        raise CliError(str(exc)) from None
    out = save_trajectories(args.out, data)
    print(
        f"wrote {out}: {data.n} trajectories x {data.horizon} steps at {spec.rate:g} Hz "
        f"(dx={data.x.shape[2]}, dy={data.y.shape[2]}, du={data.u.shape[2]})"
    )
    for name, x_hat in estimates.items():
        path = save_estimates(out.with_name(f"{out.stem}.{name}.npz"), data, x_hat, name)
        print(f"wrote {path}: the recorded estimate {name!r} at the same ticks")
    return 0


_VERBS: list[Callable] = [
    _add_simulate,
    _add_metrics,
    _add_evaluate,
    _add_train,
    _add_replay,
    _add_recover,
    _add_live,
    _add_scenarios,
    _add_reproduce,
    _add_dataset,
]


def build_parser() -> argparse.ArgumentParser:
    """The parser of every verb (none imports torch to build its flags)."""
    parser = OneLineParser(
        prog="neural-estimator",
        description="Model-free neural estimators beside model-based nonlinear filters (paper reproduction).",
    )
    sub = parser.add_subparsers(dest="verb", required=True, metavar="VERB")
    for add in _VERBS:
        add(sub)
    return parser


def _one_line_warnings() -> None:
    """The package's own warnings (a truncated bag, ...) as ``neural-estimator: warning: ...``, one
    line without the Python-warnings prefix of a source path and line number."""
    import warnings

    default = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None):
        if category.__module__.startswith("neural_estimator"):
            print(f"neural-estimator: warning: {message}", file=file or sys.stderr)
        else:
            default(message, category, filename, lineno, file, line)

    warnings.showwarning = show


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    _one_line_warnings()
    from neural_estimator.runtime import cooperative_threads, tune_allocator

    tune_allocator()  # batched numpy work is up to 2x faster (see neural_estimator/runtime.py)
    cooperative_threads()  # --threads 2 never slower than one on a busy machine (before torch loads)
    if argv[:1] == ["ros2"]:  # the minimal `ros2 run` of pip environments (neural_estimator/ros2_shim.py)
        from neural_estimator.ros2_shim import main as ros2_main

        return ros2_main(argv[1:])
    if argv[:1] == ["live"]:  # its own parser (neural_estimator.nodes.launch); argparse.REMAINDER drops --help
        return _cmd_live(argparse.Namespace(rest=argv[1:]))
    # Plugins must be imported before parsing so their scenario names show up in --help.
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--plugin", action="append")
    known, _ = pre.parse_known_args(argv)
    from neural_estimator.data import DataError
    from neural_estimator.estimators import EstimatorError

    handled: tuple[type[BaseException], ...] = (CliError, ScenarioError, DataError, EstimatorError)
    try:
        from neural_estimator.bags.errors import BagError  # light: the bags package imports rosbags

        handled += (BagError,)
    except ImportError:  # bags not importable (optional dependency missing)
        pass
    try:
        load_plugins(known.plugin)
        args = build_parser().parse_args(argv)
        return int(args.func(args) or 0)
    except handled as exc:
        print(f"neural-estimator: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("neural-estimator: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
