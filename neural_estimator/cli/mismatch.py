"""The ``mismatch`` verb: RMSE against the model's relative error, and the crossover where a network
(or the hybrid) overtakes the best filter (:mod:`neural_estimator.evaluation.mismatch`)."""

from __future__ import annotations

import sys
from pathlib import Path

from neural_estimator.cli.common import CliError, preset_flag


def add_mismatch(sub) -> None:
    from neural_estimator.evaluation.mismatch import DEFAULT_VALUES, NOISE_VALUES

    p = sub.add_parser(
        "mismatch",
        help="RMSE of filters told a wrong constant (or Q/R) against a network; the crossover with its interval",
    )
    p.add_argument("--plugin", action="append", metavar="FILE", help="Python file registering user scenarios")
    p.add_argument("--scenario", help="the scenario (with --experiment: default all five)")
    p.add_argument("--set", action="append", metavar="NAME=VALUE", help="a true constant of the data (repeatable)")
    preset_flag(p)
    p.add_argument(
        "--parameter",
        metavar="NAME",
        help="the constant the model gets wrong (any real-valued constant of the scenario), or Q / R: the scale of "
        "the process / observation noise covariance the model is told",
    )
    p.add_argument(
        "--values",
        metavar="V,V,...",
        help="multipliers of the true value (1.0 = the exact model; relative error = V - 1); default "
        f"{','.join(map(str, DEFAULT_VALUES))}, for Q and R {','.join(map(str, NOISE_VALUES))}",
    )
    p.add_argument(
        "--experiment",
        action="store_true",
        help="every parameter the reproduce experiment declares for the scenario (all five without --scenario): "
        "ballistic k, bearings accel_noise_std, lorenz96 forcing, nlink total_length, quadrotor mass, and Q, R",
    )
    p.add_argument(
        "--methods",
        help="comma-separated; default ekf, ukf, the best of the six networks on these sets, and kalmannet where "
        "the zoo ships it",
    )
    p.add_argument("--trajectories", type=int, default=100, help="per evaluation set (default 100)")
    p.add_argument("--sets", type=int, default=2, help="evaluation sets (default 2)")
    p.add_argument("--horizon", type=int, help="steps (default: the scenario's)")
    p.add_argument("--seed", type=int, default=0, help="seed of the evaluation sets' streams")
    p.add_argument("--no-cache", action="store_true", help="neither read nor write the dataset and result caches")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument(
        "--out",
        default="mismatch-out",
        help="directory of SCENARIO-PARAMETER.json, .csv and .png (default mismatch-out)",
    )
    p.set_defaults(func=_cmd_mismatch)


def _plan(args) -> list[tuple[str, str, list[float] | None]]:
    """(scenario, parameter, values or None for the default) of each sweep the flags ask for."""
    from neural_estimator.evaluation.mismatch import EXPERIMENT

    if args.experiment:
        if args.parameter or args.values:
            raise CliError("--experiment declares its parameters and values: drop --parameter and --values")
        names = [args.scenario] if args.scenario else list(EXPERIMENT)
        missing = [s for s in names if s not in EXPERIMENT]
        if missing:
            raise CliError(f"--experiment declares no sweep for {missing[0]!r}; pass --parameter NAME")
        return [(s, prm, None) for s in names for prm in EXPERIMENT[s]]
    if not args.scenario or not args.parameter:
        raise CliError("pass --scenario S --parameter NAME (or --experiment)")
    values = None
    if args.values:
        try:
            values = [float(v) for v in args.values.split(",") if v.strip()]
        except ValueError:
            raise CliError(f"--values expects comma-separated numbers, got {args.values!r}") from None
    return [(args.scenario, args.parameter, values)]


def _cmd_mismatch(args) -> int:
    from neural_estimator.evaluation import mismatch as MM
    from neural_estimator.filters.baselines import check_evaluated_method
    from neural_estimator.scenarios import make_scenario, parse_assignments

    if args.trajectories < 2 or args.sets < 1:
        raise CliError(f"--trajectories must be >= 2 and --sets >= 1, got {args.trajectories} and {args.sets}")
    methods = [check_evaluated_method(m) for m in args.methods.split(",") if m.strip()] if args.methods else None
    out = Path(args.out)
    for name, parameter, values in _plan(args):
        scenario = make_scenario(name, preset=args.preset, **parse_assignments(args.set))
        MM.true_value(scenario, parameter)  # a bad name fails now, before any data are simulated
        if values is None:
            values = list(MM.default_values(parameter))
        MM.check_values(values)
        result = MM.mismatch(
            scenario,
            parameter,
            values,
            methods,
            trajectories=args.trajectories,
            sets=args.sets,
            horizon=args.horizon,
            seed=args.seed,
            cache_dir=False if args.no_cache else None,
            progress=not args.quiet,
        )
        print(MM.result_text(result), end="")
        stem = MM.write_result(result, out)
        print(f"wrote {stem}.json, .csv, .png", file=sys.stderr)
    return 0
