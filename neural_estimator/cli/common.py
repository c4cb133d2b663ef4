"""What the verbs share: the one-line error, the scenario, preset, warm-up and bag flags, and
the parsing of METHOD=... values."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from neural_estimator.scenarios import (
    ScenarioError,
    make_scenario,
    parse_assignments,
    scenario_names,
)


class CliError(Exception):
    """A command-line usage problem (message shown to the user, exit status 2)."""


def scenario_from_args(args: argparse.Namespace):
    """The scenario named by ``--scenario`` with ``--set`` overrides and ``--noise-scale``."""
    overrides: dict[str, Any] = parse_assignments(getattr(args, "set", None))
    if getattr(args, "noise_scale", None) is not None:
        overrides["noise_scale"] = args.noise_scale
    return make_scenario(args.scenario, preset=getattr(args, "preset", None), **overrides)


def model_set_flag(p: argparse.ArgumentParser) -> None:
    """``--model-set NAME=VALUE``: the model the model-based methods are told (a wrong one, on purpose)."""
    p.add_argument(
        "--model-set",
        action="append",
        metavar="NAME=VALUE",
        help="a constant of the model the model-based methods (filters, baselines, hybrid) are given, on top "
        "of the data's --preset/--set; Q=S and R=S scale the process/observation noise covariance they are "
        "told; the data and the data-trained networks are untouched (repeatable)",
    )


def model_assignments(items: list[str] | None) -> dict[str, str]:
    """``--model-set`` items as {name: value}; a malformed one is a one-line CliError."""
    told: dict[str, str] = {}
    for item in items or ():
        name, sep, value = item.partition("=")
        if not sep or not name.strip() or not value.strip():
            raise CliError(f"--model-set expects NAME=VALUE, got {item!r}")
        told[name.strip()] = value.strip()
    return told


def model_scenario_from_args(args: argparse.Namespace, scenario):
    """The model scenario of ``--model-set`` (``scenario`` itself without one); bad names and values
    are the scenario's one-line errors."""
    from neural_estimator.scenarios.model import model_scenario

    items = getattr(args, "model_set", None)
    if not items:
        return scenario
    if scenario is None or getattr(args, "data", None) is not None:
        raise CliError("--model-set needs --scenario (recorded data have no model)")
    try:
        return model_scenario(scenario, model_assignments(items))
    except ScenarioError as exc:
        raise CliError(f"--model-set: {exc}") from None


def preset_flag(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--preset",
        metavar="NAME",
        help="named set of the scenario's constants, applied before --set (built-ins: the defaults are v4, "
        "for nlink and bearings v5; v3, v4 the earlier calibrations; see docs/scenarios.md)",
    )


def scenario_flags(p: argparse.ArgumentParser, scenario: bool = True, data: bool = False) -> None:
    p.add_argument("--plugin", action="append", metavar="FILE", help="Python file registering user scenarios")
    if scenario:
        p.add_argument(
            "--scenario",
            required=not data,
            help=f"one of: {', '.join(scenario_names())} (or a plugin's)" + ("; or --data" if data else ""),
        )
        p.add_argument("--set", action="append", metavar="NAME=VALUE", help="override a scenario constant (repeatable)")
        preset_flag(p)
        p.add_argument("--noise-scale", type=float, help="multiply the observation-noise std (filters are told)")


def warmup_flag(p: argparse.ArgumentParser) -> None:
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


def bag_scenario_flags(p: argparse.ArgumentParser) -> None:
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
    preset_flag(p)


def bag_description(args: argparse.Namespace) -> dict[str, Any] | None:
    """The description named by ``--scenario``/``--set``, or None (use the bag's own)."""
    if getattr(args, "scenario", None):
        return make_scenario(args.scenario, preset=args.preset, **parse_assignments(args.set)).describe()
    if getattr(args, "set", None) or getattr(args, "preset", None):
        flag = "--set" if getattr(args, "set", None) else "--preset"
        raise CliError(f"{flag} needs --scenario (the bag's own scenario message carries its constants)")
    return None


def is_bag(path: str) -> bool:
    return path.endswith(".mcap") or Path(path).is_dir()


def parse_checkpoints(items: list[str] | None) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for item in items or ():
        method, sep, paths = item.partition("=")
        if not sep or not paths:
            raise CliError(f"--checkpoint expects METHOD=DIR[,DIR...], got {item!r}")
        out.setdefault(method.strip().lower(), []).extend(p for p in paths.split(",") if p)
    return out


def parse_options(items: list[str] | None) -> dict[str, dict[str, Any]]:
    """{method: {name: text}}: the values stay text, parsed by the method against each option's type
    (:mod:`neural_estimator.core.options`)."""
    out: dict[str, dict[str, Any]] = {}
    for item in items or ():
        key, sep, value = item.partition("=")
        method, dot, name = key.partition(".")
        if not sep or not dot or not name:
            raise CliError(f"--option expects METHOD.NAME=VALUE, got {item!r}")
        out.setdefault(method.strip().lower(), {})[name.strip()] = value.strip()
    return out


def scenario_or_data(args: argparse.Namespace):
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


def check_out(out: str, overwrite: bool) -> None:
    """An existing ``--out`` is replaced only with ``--overwrite`` (the flag's name in the message)."""
    if Path(out).exists() and not overwrite:
        raise CliError(f"{out}: file exists; pass --overwrite to replace it")
