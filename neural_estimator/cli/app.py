"""The ``neural-estimator`` command line: the parser of every verb and :func:`main`."""

from __future__ import annotations

import argparse
import sys
from typing import Callable

from neural_estimator.scenarios import (
    ScenarioError,
    load_plugins,
)
from neural_estimator.cli.reproduce import add_reproduce
from neural_estimator.cli.streams import add_live, add_recover, add_replay, cmd_live
from neural_estimator.cli.train import add_train
from neural_estimator.cli.data import add_dataset, add_scenarios, add_simulate
from neural_estimator.cli.evaluate import add_evaluate, add_metrics
from neural_estimator.cli.headline import add_headline
from neural_estimator.cli.mismatch import add_mismatch
from neural_estimator.cli.common import CliError
from neural_estimator.core.arguments import EXIT_BAD_INPUT, OneLineParser


_VERBS: list[Callable] = [
    add_simulate,
    add_metrics,
    add_evaluate,
    add_train,
    add_replay,
    add_recover,
    add_live,
    add_scenarios,
    add_reproduce,
    add_dataset,
    add_headline,
    add_mismatch,
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
    from neural_estimator.core.runtime import cooperative_threads, tune_allocator

    tune_allocator()  # batched numpy work is up to 2x faster (see neural_estimator/core/runtime.py)
    cooperative_threads()  # --threads 2 never slower than one on a busy machine (before torch loads)
    if argv[:1] == ["ros2"]:  # the minimal `ros2 run` of pip environments (neural_estimator/cli/ros2_shim.py)
        from neural_estimator.cli.ros2_shim import main as ros2_main

        return ros2_main(argv[1:])
    if argv[:1] == ["live"]:  # its own parser (neural_estimator.nodes.launch); argparse.REMAINDER drops --help
        return cmd_live(argparse.Namespace(rest=argv[1:]))
    # Plugins must be imported before parsing so their scenario names show up in --help.
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--plugin", action="append")
    known, _ = pre.parse_known_args(argv)
    from neural_estimator.data import DataError
    from neural_estimator.methods.registry import EstimatorError

    from neural_estimator.core.atomic import WriteError

    handled: tuple[type[BaseException], ...] = (CliError, ScenarioError, DataError, EstimatorError, WriteError)
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
