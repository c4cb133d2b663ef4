"""The ``reproduce`` verb's arguments -> :func:`neural_estimator.paper.reproduce.run.reproduce`."""

from __future__ import annotations

from pathlib import Path

from neural_estimator.data.protocol import default_cache_dir
from neural_estimator.paper.reproduce.jobs import EXPERIMENTS
from neural_estimator.paper.reproduce.run import reproduce
from neural_estimator.paper.reproduce.settings import ReproduceError, Settings
from neural_estimator.paper.reproduce.scales import get_scale
from neural_estimator.paper.results import PAPER_SCENARIOS


def _names(text: str | None, default, check, flag: str) -> list[str]:
    names = [n.strip().lower() for n in (text.split(",") if text is not None else default) if n.strip()]
    if not names:
        raise ReproduceError(f"{flag} is empty")
    return [check(n) for n in dict.fromkeys(names)]


def run_from_args(args, usage_error: type[Exception]) -> int:
    from neural_estimator.methods import table
    from neural_estimator.methods.registry import check_method

    try:
        if args.num_cpus is not None and args.num_cpus < 1:
            raise ReproduceError(f"--num-cpus must be >= 1, got {args.num_cpus}")
        settings = Settings(
            scale=get_scale(args.scale),
            scenarios=_names(args.scenarios, PAPER_SCENARIOS, _known_scenario, "--scenarios"),
            methods=_names(args.methods, list(table.paper_names()), check_method, "--methods"),  # the paper's ten
            gpu=_cuda(),
            cache_dir=str(args.cache_dir or default_cache_dir()),
            address=args.address,
            num_cpus=args.num_cpus,
            plugins=tuple(str(Path(p).resolve()) for p in (args.plugin or ())),
            init=args.init,
            experiments=tuple(
                e for e in EXPERIMENTS if e in _names(args.experiments, EXPERIMENTS, _known_experiment, "--experiments")
            ),
        )
        summary = reproduce(settings, args.out, resume=args.resume, progress=not args.quiet)
    except ReproduceError as exc:
        raise usage_error(str(exc)) from None
    print(
        f"{summary['jobs']} jobs: {summary['computed']} computed, {summary['cached']} cached, "
        f"{summary['failed']} failed "
        f"in {summary['wall_s']:.1f} s; wrote {summary['report']}"
    )
    return 1 if summary["failed"] else 0


def _cuda() -> bool:
    import torch

    return bool(torch.cuda.is_available())


def _known_experiment(name: str) -> str:
    if name not in EXPERIMENTS:
        raise ReproduceError(f"--experiments: unknown experiment {name!r}; choose from {', '.join(EXPERIMENTS)}")
    return name


def _known_scenario(name: str) -> str:
    """A registered scenario: built-in, or a plugin's loaded with ``--plugin`` (the workers load it too)."""
    from neural_estimator.scenarios import scenario_class

    scenario_class(name)  # an unknown name: the registry's error, listing the valid ones
    return name
