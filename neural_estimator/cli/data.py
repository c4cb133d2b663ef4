"""The data verbs: ``simulate`` (a scenario's dataset), ``scenarios`` (the registered scenarios) and
``dataset`` (recorded robot bags -> a dataset)."""

from __future__ import annotations

import json

from neural_estimator.scenarios import (
    make_scenario,
    preset_names,
    scenario_names,
)
from neural_estimator.cli.common import CliError, scenario_flags, scenario_from_args


def add_simulate(sub) -> None:
    p = sub.add_parser("simulate", help="write a dataset (.npz) of a scenario")
    scenario_flags(p)
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


def add_scenarios(sub) -> None:
    p = sub.add_parser("scenarios", help="list the registered scenarios and their constants")
    scenario_flags(p, scenario=False)
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


# Verbs are added to this list as their modules land; each is (adder).
def add_dataset(sub) -> None:
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
    p.add_argument(
        "--plugin",
        action="append",
        metavar="FILE",
        help="Python file registering user scenarios (a spec's model: naming one of them)",
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
    if data.meta.get("ground_truth") is False:  # a spec with a model and no state
        print("no ground truth (the spec reads no state): train a hybrid on it with --supervision observations")
    elif data.labelled is not None:  # partial ground truth: say what training and scoring will use
        print(
            f"ground truth on {data.meta['labelled_steps']} of {data.x.shape[0] * data.x.shape[1]} steps "
            f"({data.meta['unlabelled_steps']} unlabelled: kept as inputs, never trained on or scored; "
            "the 'labelled' mask in the file)"
        )
    for name, x_hat in estimates.items():
        path = save_estimates(out.with_name(f"{out.stem}.{name}.npz"), data, x_hat, name)
        print(f"wrote {path}: the recorded estimate {name!r} at the same ticks")
    return 0
