"""The ``reproduce`` verb: the paper's experiments on Ray."""

from __future__ import annotations


from neural_estimator.cli.common import CliError


def add_reproduce(sub) -> None:
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
    p.add_argument(
        "--experiments",
        help="comma-separated, of accuracy, noise, data_ratio, runtime, mismatch (default: all five; mismatch, "
        "beyond the paper: the crossover of networks over filters told a wrong model, with its own methods)",
    )
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
    from neural_estimator.paper.reproduce.cli import run_from_args

    return run_from_args(args, CliError)
