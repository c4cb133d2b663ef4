"""The ``train`` verb: a neural estimator with the paper's protocol."""

from __future__ import annotations

import argparse
import json
from typing import Any

from neural_estimator.scenarios import (
    parse_assignments,
)
from neural_estimator.cli.common import (
    CliError,
    model_assignments,
    model_scenario_from_args,
    model_set_flag,
    scenario_flags,
    scenario_or_data,
)


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


_TRAIN_FLAG_HELP["supervision"] = (
    "what the loss reads: states (the paper's; default) or observations (a hybrid, kalmannet, trained through "
    "the system's h on the next observation alone: no state label read; docs/training.md)"
)


_TRAIN_FLAG_HELP["init_from"] = (
    "a checkpoint directory whose weights start the training instead of a fresh initialisation "
    "(fine-tuning: same architecture and configuration; a fresh optimiser at --lr; recorded in the card "
    "as training.init_from)"
)


_TRAIN_FLAG_HELP["val_context_copies"] = "copies for --val-context (K times the validation compute; default: 4)"


_TRAIN_DEFAULTS = {
    "eval_trajectories": 200,
    "val_trajectories": None,
}  # the CLI's, where they differ from TrainConfig's


def add_train(sub) -> None:
    import dataclasses

    from neural_estimator.training.recipe import TrainConfig  # no torch: the flags cost nothing to list

    p = sub.add_parser("train", help="train a neural estimator with the paper's protocol")
    scenario_flags(p, data=True)
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
    p.add_argument(
        "--model", required=True, help="gru, lstm, gpt2, filterformer, mamba, mamba2 or kalmannet (the hybrid)"
    )
    p.add_argument("--out", required=True, help="output directory (model.safetensors + card.json)")
    p.add_argument(
        "--arch-set",
        action="append",
        metavar="NAME=VALUE",
        help="override an architecture hyperparameter (a field of the model's config, e.g. prior_gain=0)",
    )
    model_set_flag(p)  # a hybrid trained with a model other than the data's (the team's wrong model)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    # Every TrainConfig field is a flag with the paper's default (one source of truth).
    for f in dataclasses.fields(TrainConfig):
        if f.name in ("model_overrides", "model_set", "resume", "keep_resume"):
            continue
        default = _TRAIN_DEFAULTS.get(f.name, f.default)
        flag = "--" + f.name.replace("_", "-")
        kind = type(f.default) if f.default is not None else int
        if f.name in ("cache_dir", "init_from"):
            kind = str
        p.add_argument(flag, type=kind, default=default, help=_TRAIN_FLAG_HELP.get(f.name, f"default: {default}"))
    p.add_argument("--resume", action="store_true", help="continue from OUT/resume if it exists")
    p.add_argument("--no-keep-resume", action="store_true", help="delete OUT/resume after the run")
    p.add_argument(
        "--threads",
        type=int,
        default=1,
        metavar="N",
        help="CPU threads for torch and the fused scan kernels: at most N, the count actually used measured "
        "every few minutes (one thread when the other cores are busy; --fixed-threads to use N always). "
        "Default 1: bit-reproducible, and on a 2-core machine one process per core beats two threads in one; "
        "see docs/performance.md",
    )
    p.add_argument(
        "--fixed-threads",
        action="store_true",
        help="always use --threads N threads, even when measurement says fewer would be faster",
    )
    p.set_defaults(func=_cmd_train)


def _cmd_train(args) -> int:
    import dataclasses

    from neural_estimator.methods import table
    from neural_estimator.methods.registry import check_method
    from neural_estimator.training.recipe import TrainConfig, TrainingError
    from neural_estimator.training.loop import train

    method = check_method(args.model)
    if not table.has(method, trainable=True):
        trainable = ", ".join(table.names(trainable=True))
        raise CliError(f"--model must be a trainable method ({trainable}), got {args.model!r}")
    scenario, datasets = scenario_or_data(args)
    data = None
    if datasets is not None:
        data = _train_val_split(args, scenario, datasets[0])
    elif args.val_data:
        raise CliError("--val-data needs --data")
    values = {f.name: getattr(args, f.name) for f in dataclasses.fields(TrainConfig) if hasattr(args, f.name)}
    values.update(
        model_overrides=_parse_model_overrides(args.arch_set),
        model_set=_checked_model_set(args, scenario, method),
        resume=args.resume,
        keep_resume=not args.no_keep_resume,
    )
    if args.threads < 1:
        raise CliError(f"--threads must be >= 1, got {args.threads}")
    import torch

    torch.set_num_threads(args.threads)
    governor = None
    if args.threads > 1 and not args.fixed_threads:
        from neural_estimator.training.threads import ThreadGovernor

        governor = ThreadGovernor(args.threads)
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
            f"(--eval-trajectories); {args.threads} thread(s) (--threads"
            f"{', the count measured every few minutes' if governor else ''})",
            flush=True,
        )
    try:
        config = TrainConfig(**values)
        path = train(scenario, method, args.out, config, progress=not args.quiet, data=data, threads=governor)
    except TrainingError as exc:
        raise CliError(str(exc)) from None
    except ValueError as exc:  # a model that cannot be built for this system (a hybrid on recorded data)
        if table.has(method, family="hybrid"):
            raise CliError(str(exc)) from None
        raise
    if governor is not None and not args.quiet:
        print(governor.summary())
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


def _checked_model_set(args: argparse.Namespace, scenario, method: str) -> dict[str, str]:
    """``--model-set`` as {name: value}, checked as evaluate checks it (one-line errors); an
    architecture hyperparameter given there is pointed to ``--arch-set``. Whether the method reads
    a model at all is the recipe's check (training.loop)."""
    from neural_estimator.models import ARCHITECTURES

    told = model_assignments(args.model_set)
    if not told:
        return {}
    hyper = set(ARCHITECTURES[method][0].__dataclass_fields__) & set(told)
    if hyper:
        name = sorted(hyper)[0]
        raise CliError(f"--model-set {name}: an architecture hyperparameter; give it as --arch-set {name}=VALUE")
    model_scenario_from_args(args, scenario)  # unknown constants, bad values, recorded data: one line
    return told


def _parse_model_overrides(items: list[str] | None) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for name, value in parse_assignments(items).items():
        try:
            out[name] = json.loads(value)
        except json.JSONDecodeError:
            out[name] = value
    return out
