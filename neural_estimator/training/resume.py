"""The resume state of a training run: everything needed to continue bit-for-bit (model, AdamW,
scheduler, RNG states, epoch, best, history), safetensors for tensors and JSON for the rest."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import torch

from neural_estimator.serving.card import json_ready
from neural_estimator.serving.checkpoint import savable
from neural_estimator.training.recipe import TrainingError

RESUME_DIR = "resume"
RESUME_FORMAT = "neural_estimator.resume"
# Settings that may change when a run is resumed (budget and runtime); everything else must match.
RESUMABLE_CHANGES = (
    "epochs",
    "patience",
    "device",
    "resume",
    "keep_resume",
    "cache_dir",
    "eval_trajectories",
    "val_batch_size",
)


def save_resume(
    directory: Path,
    identity: dict[str, Any],
    run: dict[str, Any],
    model: torch.nn.Module,
    optimizer: torch.optim.Optimizer,
    scheduler: Any,
    rng: np.random.Generator,
) -> None:
    """Write the state after an epoch: written to ``directory.tmp`` and then swapped in."""
    from safetensors.torch import save_file, save_model

    tmp = directory.with_name(directory.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    save_model(savable(model), str(tmp / "model.safetensors"), force_contiguous=True)
    opt = optimizer.state_dict()
    tensors, extra = {}, {}
    for pid, slots in opt["state"].items():
        for key, value in slots.items():
            if torch.is_tensor(value):
                tensors[f"{pid}.{key}"] = value.detach().cpu().contiguous()
            else:
                extra.setdefault(str(pid), {})[key] = value
    save_file(tensors, str(tmp / "optimizer.safetensors"))
    rng_tensors = {"torch_cpu": torch.get_rng_state()}
    if torch.cuda.is_available():
        for i, s in enumerate(torch.cuda.get_rng_state_all()):
            rng_tensors[f"torch_cuda_{i}"] = s
    save_file(rng_tensors, str(tmp / "rng.safetensors"))
    state = {
        "format": RESUME_FORMAT,
        **identity,
        "run": run,
        "optimizer": {"param_groups": opt["param_groups"], "state_extra": extra},
        "scheduler": scheduler.state_dict(),
        "numpy_rng": rng.bit_generator.state,
    }
    # allow_nan: the scheduler's "best" starts at inf; Python's json reads the Infinity token back
    (tmp / "state.json").write_text(json.dumps(state, indent=1, allow_nan=True) + "\n")
    old = directory.with_name(directory.name + ".old")
    shutil.rmtree(old, ignore_errors=True)
    if directory.exists():
        os.replace(directory, old)
    os.replace(tmp, directory)
    shutil.rmtree(old, ignore_errors=True)


def load_resume(
    directory: Path,
    identity: dict[str, Any],
    model: torch.nn.Module,
    optimizer: torch.optim.Optimizer,
    scheduler: Any,
    rng: np.random.Generator,
) -> dict[str, Any]:
    """Restore the state :func:`save_resume` wrote (in place); returns the run record."""
    from safetensors.torch import load_file, load_model

    try:
        state = json.loads((directory / "state.json").read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise TrainingError(f"{directory / 'state.json'} is corrupt ({exc}); start without --resume") from None
    if state.get("format") != RESUME_FORMAT:
        raise TrainingError(f"{directory / 'state.json'} is not a training resume state")
    _check_same_run(directory, state, identity)
    try:
        device = str(next(model.parameters()).device)
        load_model(model, str(directory / "model.safetensors"), strict=True, device=device)
        flat = load_file(str(directory / "optimizer.safetensors"))
        rng_tensors = load_file(str(directory / "rng.safetensors"))
    except Exception as exc:  # safetensors' own error types for missing or malformed files
        raise TrainingError(f"{directory}: cannot read the resume state ({exc}); start without --resume") from None
    opt_state: dict[int, dict[str, Any]] = {}
    for name, tensor in flat.items():
        pid, _, key = name.partition(".")
        opt_state.setdefault(int(pid), {})[key] = tensor
    for pid, slots in state["optimizer"]["state_extra"].items():
        opt_state.setdefault(int(pid), {}).update(slots)
    groups = state["optimizer"]["param_groups"]
    for g in groups:
        if "betas" in g:
            g["betas"] = tuple(g["betas"])
    optimizer.load_state_dict({"state": opt_state, "param_groups": groups})
    scheduler.load_state_dict(state["scheduler"])
    rng.bit_generator.state = state["numpy_rng"]
    torch.set_rng_state(rng_tensors["torch_cpu"])
    if torch.cuda.is_available():
        keys = [f"torch_cuda_{i}" for i in range(torch.cuda.device_count())]
        cuda = [rng_tensors[k] for k in keys if k in rng_tensors]
        if cuda:
            torch.cuda.set_rng_state_all(cuda)
    return state["run"]


def _without_preset(desc: Any) -> Any:
    return {k: v for k, v in desc.items() if k != "preset"} if isinstance(desc, dict) else desc


def _check_same_run(directory: Path, state: dict[str, Any], identity: dict[str, Any]) -> None:
    """Refuse to resume a state written by another scenario, architecture or recipe."""
    # The preset label is derived from the constants (Scenario.describe); states written before
    # presets existed lack it, and the constants themselves are compared.
    if _without_preset(state.get("scenario")) != _without_preset(identity["scenario"]):
        raise TrainingError(
            f"{directory} was written for scenario {state.get('scenario', {}).get('scenario')!r} "
            f"with other constants or dimensions; start without --resume or use another --out"
        )
    if state.get("arch") != identity["arch"]:
        raise TrainingError(f"{directory} was written for {state.get('arch')!r}, not {identity['arch']!r}")
    old, new = state.get("config", {}), json_ready(identity["config"])
    diffs = [
        f"{k}={old.get(k)!r} (resume state) vs {new.get(k)!r} (now)"
        for k in sorted(set(old) | set(new))
        if k not in RESUMABLE_CHANGES and old.get(k) != new.get(k)
    ]
    if diffs:
        raise TrainingError(
            f"{directory} was written with other settings: {'; '.join(diffs)}. Resume with the same "
            f"settings (only {', '.join(RESUMABLE_CHANGES)} may change) or start without --resume"
        )
