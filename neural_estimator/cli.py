"""The ``neural-estimator`` command line: a thin front end over the library.

Verbs (``neural-estimator VERB --help`` for each):
    simulate   write a dataset (.npz) of a scenario
    metrics    the paper's table from a truth file and an estimate file (or one file, or an MCAP bag)
    evaluate   run methods on the three evaluation sets and print the paper's per-scenario table
    train      train a neural estimator with the paper's protocol
    replay     run an MCAP bag's observations through estimators offline
    scenarios  list the registered scenarios and their constants

Every command accepts ``--plugin FILE`` (repeatable) to import a Python file that registers user
scenarios. Errors in the input print one line naming the problem and exit with status 2.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
from pathlib import Path
from typing import Any, Callable

from neural_estimator.scenarios import ScenarioError, make_scenario, parse_assignments, scenario_names

EXIT_BAD_INPUT = 2


class CliError(Exception):
    """A command-line usage problem (message shown to the user, exit status 2)."""


def load_plugins(paths: list[str] | None) -> None:
    """Import user files that call ``register_scenario``."""
    for p in paths or ():
        path = Path(p)
        if not path.is_file():
            raise CliError(f"--plugin {p}: no such file")
        spec = importlib.util.spec_from_file_location(f"neural_estimator_plugin_{path.stem}", path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = module
        spec.loader.exec_module(module)


def scenario_from_args(args: argparse.Namespace):
    """The scenario named by ``--scenario`` with ``--set`` overrides and ``--noise-scale``."""
    overrides: dict[str, Any] = parse_assignments(getattr(args, "set", None))
    if getattr(args, "noise_scale", None) is not None:
        overrides["noise_scale"] = args.noise_scale
    return make_scenario(args.scenario, **overrides)


def _common(p: argparse.ArgumentParser, scenario: bool = True) -> None:
    p.add_argument("--plugin", action="append", metavar="FILE", help="Python file registering user scenarios")
    if scenario:
        p.add_argument("--scenario", required=True, help=f"one of: {', '.join(scenario_names())} (or a plugin's)")
        p.add_argument("--set", action="append", metavar="NAME=VALUE", help="override a scenario constant (repeatable)")
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
    print(f"wrote {path}: {data.n} trajectories x {data.horizon} steps of {scenario.name} "
          f"(x {data.x.shape[2]}, y {data.y.shape[2]}, u {data.u.shape[2]}), seed {args.seed}")
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
    for d in descs:
        print(f"{d['scenario']}: x = [{', '.join(f'{n} [{u}]' for n, u in zip(d['state_names'], d['state_units']))}]")
        print(f"  y = [{', '.join(f'{n} [{u}]' for n, u in zip(d['obs_names'], d['obs_units']))}]"
              + (f", u = [{', '.join(d['control_names'])}]" if d["control_names"] else ""))
        print("  " + ", ".join(f"{k}={v}" for k, v in d["config"].items() if not isinstance(v, list) or len(v) <= 4))
    return 0


# Verbs are added to this list as their modules land; each is (adder).
_VERBS: list[Callable] = [_add_simulate, _add_scenarios]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="neural-estimator",
        description="Model-free neural estimators beside model-based nonlinear filters (paper reproduction).",
    )
    sub = parser.add_subparsers(dest="verb", required=True, metavar="VERB")
    for add in _VERBS:
        add(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    # Plugins must be imported before parsing so their scenario names show up in --help.
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--plugin", action="append")
    known, _ = pre.parse_known_args(argv)
    from neural_estimator.data import DataError
    from neural_estimator.estimators import EstimatorError

    handled: tuple[type[BaseException], ...] = (CliError, ScenarioError, DataError, EstimatorError)
    try:
        from neural_estimator.bags import BagError

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
