"""The verbs over message streams: ``live`` (a ROS 2 run), ``replay`` (a bag through estimators,
offline) and ``recover`` (a damaged bag -> a valid .mcap)."""

from __future__ import annotations

import argparse
from pathlib import Path

from neural_estimator.cli.evaluate import _print_metrics
from neural_estimator.cli.common import (
    CliError,
    bag_description,
    bag_scenario_flags,
    check_out,
    model_assignments,
    model_set_flag,
    parse_checkpoints,
    parse_options,
    warmup_flag,
)


def add_live(sub) -> None:
    p = sub.add_parser(
        "live",
        add_help=False,  # dispatched before parsing, see main()
        help="live ROS 2 run: simulator -> estimators -> evaluator, ends with the table and the MCAP bag",
    )
    p.add_argument("rest", nargs=argparse.REMAINDER)
    p.set_defaults(func=cmd_live)


def cmd_live(args) -> int:
    from neural_estimator.nodes.launch import main as launch_main

    return launch_main(args.rest)


def add_replay(sub) -> None:
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
    bag_scenario_flags(p)
    model_set_flag(p)
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
    p.add_argument(
        "--force",
        action="store_true",
        help="run even when --scenario/--preset/--set name other constants than the bag's data were made with",
    )
    p.add_argument("--metrics", action="store_true", help="print the metrics table of the output bag")
    warmup_flag(p)
    p.set_defaults(func=_cmd_replay)


def _cmd_replay(args) -> int:
    from neural_estimator.methods import table
    from neural_estimator.methods.registry import check_method
    from neural_estimator.evaluation.replay import replay

    methods = [check_method(m) for m in args.methods.split(",") if m.strip()]
    ckpts = {m: paths[-1] for m, paths in parse_checkpoints(args.checkpoint).items()}
    options = parse_options(args.option)
    starts = {}
    if args.init != "prior":
        for m in methods:
            if table.has(m, takes_init=True):
                options.setdefault(m, {}).setdefault("init", args.init)
                starts[m] = options[m]["init"]
    if args.threads < 0:
        raise CliError(f"--threads must be >= 0 (0 = torch's default), got {args.threads}")
    check_out(args.out, args.overwrite)
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
        description=bag_description(args),
        order=args.order,
        threads=args.threads,
        force=args.force,
        model_set=model_assignments(args.model_set),
    )
    if args.model_set:
        print(f"model-based methods told a wrong model on purpose (--model-set): {', '.join(args.model_set)}")
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


def add_recover(sub) -> None:
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
    check_out(args.out, args.overwrite)
    res = recover_bag(args.bag, args.out, overwrite=args.overwrite)
    lost = f"; the input had lost: {res.damage}" if res.damage is not None else "; the input was intact"
    note = f"; {res.lost_note()}" if res.lost else ""
    print(f"wrote {res.path}: {res.messages} messages on {res.topics} topics{lost}{note}")
    return 0
