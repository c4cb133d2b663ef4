"""Checkpoints: safetensors weights plus a JSON card. Loading can never run code.

A checkpoint is a directory holding exactly

    model.safetensors   the weights (safetensors: a JSON header and raw tensor bytes, no pickle)
    card.json           everything needed to rebuild and judge the model:
                          method, architecture name and full config, parameter count,
                          scenario description with every constant (``Scenario.describe()``),
                          normalisation statistics, data seed/index/ratio and set sizes, init seed,
                          training recipe and history, final validation loss, metrics on an
                          evaluation set (when measured), software versions, creation date,
                          and the sha256 of model.safetensors

The model is rebuilt from the card (``ModelCls(ConfigCls(**config))``) and the weights are read with
safetensors only: no ``torch.load``, no pickle. Trained defaults ship at
``neural_estimator/zoo/<scenario>-<method>/``.

Loading for a scenario checks that the checkpoint belongs to it: same scenario name, same
dimensions, same state/observation/control names and angles, same constants. Two constants may
differ, because they describe an evaluation rather than the system: ``noise_scale`` (the paper's
robustness study evaluates at observation-noise levels beyond training) and ``horizon``.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import hashlib
import json
import math
import os
import platform
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from neural_estimator import __version__
from neural_estimator.estimator import EstimatorError, check_method
from neural_estimator.models import ARCHITECTURES, build_model, count_parameters
from neural_estimator.models.neural import NeuralEstimator, resolve_device
from neural_estimator.models.normalization import NormalizationError, Normalizer
from neural_estimator.scenarios import Scenario

CARD_FORMAT = "neural_estimator.checkpoint"
CARD_VERSION = 1
WEIGHTS_FILE = "model.safetensors"
CARD_FILE = "card.json"
ZOO_DIR = Path(__file__).resolve().parents[1] / "zoo"
EVALUATION_CONSTANTS = ("noise_scale", "horizon")  # may differ between training and use


# ---- architectures ----------------------------------------------------------------------------------
def architecture_of(model: nn.Module) -> tuple[str, dict[str, Any]]:
    """(architecture name, full config as a dict) of a model built by :mod:`neural_estimator.models`."""
    for name, (_, model_cls) in ARCHITECTURES.items():
        if type(model) is model_cls:
            return name, dataclasses.asdict(model.cfg)
    raise EstimatorError(f"{type(model).__name__} is not one of the registered architectures")


def build_from_config(name: str, config: dict[str, Any]) -> nn.Module:
    """Rebuild an (untrained) model from a card's architecture name and full config dict
    (:func:`~neural_estimator.models.build_model`, its errors as EstimatorError naming the card's values)."""
    config = dict(config)
    try:
        return build_model(name, config.pop("d_in"), config.pop("d_out"), **config)
    except KeyError as exc:
        raise EstimatorError(f"cannot build {name!r} from the card's config: {str(exc).strip(chr(39))}") from None
    except (TypeError, ValueError, AssertionError) as exc:
        raise EstimatorError(f"cannot build {name} from its config {config}: {exc}") from None


# ---- JSON that never holds inf/NaN tokens ---------------------------------------------------------
def json_ready(obj: Any) -> Any:
    """A copy of ``obj`` with numpy types as Python ones, inf as "inf"/"-inf" and NaN as null."""
    if isinstance(obj, dict):
        return {str(k): json_ready(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_ready(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_ready(obj.tolist())
    if isinstance(obj, np.generic):
        return json_ready(obj.item())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None if math.isnan(obj) else ("inf" if obj > 0 else "-inf")
    return obj


def write_json(path: Path, obj: Any) -> None:
    """Write JSON atomically (a temporary file renamed over the target)."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(json_ready(obj), indent=2, allow_nan=False) + "\n")
    os.replace(tmp, path)


def read_json(path: Path, what: str = "file") -> dict[str, Any]:
    """Read a JSON object; a missing or malformed file raises EstimatorError naming it."""
    if not path.is_file():
        raise EstimatorError(f"{path}: {what} is missing")
    try:
        obj = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise EstimatorError(f"{path}: {what} is corrupt (not valid JSON: {exc})") from None
    if not isinstance(obj, dict):
        raise EstimatorError(f"{path}: {what} is corrupt (expected a JSON object)")
    return obj


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def software_versions() -> dict[str, str]:
    import safetensors

    return {
        "neural_estimator": __version__,
        "torch": torch.__version__,
        "numpy": np.__version__,
        "safetensors": safetensors.__version__,
        "python": platform.python_version(),
    }


# ---- save ---------------------------------------------------------------------------------------
def save_checkpoint(directory: str | Path, model: nn.Module, normalizer: Normalizer, card: dict[str, Any]) -> Path:
    """Write ``model.safetensors`` and ``card.json`` into ``directory``.

    Args:
        directory: the checkpoint directory (created if needed).
        model: a model of :mod:`neural_estimator.models`.
        normalizer: its training-set statistics.
        card: provenance to record; must hold ``scenario`` (``Scenario.describe()``). Usually also
            ``data``, ``init_seed``, ``training``, ``validation_loss`` and ``metrics``. The entries
            this function computes (method, architecture, normalization, weights, software,
            created) replace any given ones, except ``created``.

    Returns:
        The directory.
    """
    from safetensors.torch import save_model

    directory = Path(directory)
    if "scenario" not in card or "scenario" not in card["scenario"]:
        raise EstimatorError("a checkpoint card needs the scenario description (Scenario.describe())")
    name, config = architecture_of(model)
    directory.mkdir(parents=True, exist_ok=True)
    weights = directory / WEIGHTS_FILE
    tmp = directory / (WEIGHTS_FILE + ".tmp")
    save_model(model, str(tmp), metadata={"format": CARD_FORMAT, "method": name}, force_contiguous=True)
    os.replace(tmp, weights)
    full = {
        "format": CARD_FORMAT,
        "format_version": CARD_VERSION,
        "method": name,
        "scenario": card["scenario"],
        "architecture": {"name": name, "config": config, "parameters": count_parameters(model)},
        "normalization": normalizer.to_dict(),
    }
    for key, value in card.items():
        if key not in full:
            full[key] = value
    full["weights"] = {"file": WEIGHTS_FILE, "sha256": sha256_file(weights), "tensors": len(model.state_dict())}
    full["software"] = software_versions()
    full.setdefault("created", _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"))
    write_json(directory / CARD_FILE, full)
    return directory


# ---- load ---------------------------------------------------------------------------------------
def checkpoint_paths(checkpoint: str | Path) -> tuple[Path, Path]:
    """(directory, card path) of a checkpoint given as its directory or its ``card.json``."""
    p = Path(checkpoint)
    if p.suffix == ".json" or p.is_file():
        return p.parent, p
    return p, p / CARD_FILE


def default_checkpoint(scenario_name: str, method: str) -> Path:
    """Where the shipped model of (scenario, method) lives."""
    return ZOO_DIR / f"{scenario_name}-{method}"


def read_card(checkpoint: str | Path) -> tuple[Path, dict[str, Any]]:
    """(directory, card) of a checkpoint; a missing or corrupt card raises EstimatorError."""
    directory, card_path = checkpoint_paths(checkpoint)
    if not directory.exists():
        raise EstimatorError(f"checkpoint {directory} does not exist")
    card = read_json(card_path, "checkpoint card")
    if card.get("format") != CARD_FORMAT:
        raise EstimatorError(f"{card_path}: not a neural_estimator checkpoint card (format {card.get('format')!r})")
    if int(card.get("format_version", 0)) > CARD_VERSION:
        raise EstimatorError(
            f"{card_path}: card format version {card.get('format_version')} is newer than this "
            f"neural_estimator reads ({CARD_VERSION}); upgrade the package"
        )
    for key in ("method", "scenario", "architecture", "normalization", "weights"):
        if key not in card:
            raise EstimatorError(f"{card_path}: checkpoint card is corrupt (no {key!r} entry)")
    return directory, card


def load_checkpoint(
    checkpoint: str | Path, device: str | torch.device = "cpu"
) -> tuple[nn.Module, Normalizer, dict[str, Any]]:
    """(model in eval mode on ``device``, normalizer, card) of a checkpoint directory or card.

    Raises:
        EstimatorError: missing or corrupt card or weights, weights that do not match the card.
    """
    from safetensors.torch import load_model

    directory, card = read_card(checkpoint)
    arch = card["architecture"]
    try:
        normalizer = Normalizer.from_dict(card["normalization"])
    except NormalizationError as exc:
        raise EstimatorError(f"{directory / CARD_FILE}: {exc}") from None
    name = card["weights"].get("file", WEIGHTS_FILE)
    if not isinstance(name, str) or not name or Path(name).name != name or name in (".", ".."):
        raise EstimatorError(
            f"{directory / CARD_FILE}: the weight file must be a file name inside the checkpoint, got {name!r}"
        )
    weights = directory / name
    if not weights.is_file():
        raise EstimatorError(f"checkpoint {directory}: weight file {weights.name} is missing")
    check_model_size(arch, weights.stat().st_size, directory)
    model = build_from_config(arch["name"], arch["config"])
    expected = card["weights"].get("sha256")
    if expected and sha256_file(weights) != expected:
        raise EstimatorError(
            f"checkpoint {directory}: {weights.name} does not match the sha256 in {CARD_FILE} "
            "(the weight file is corrupt or belongs to another checkpoint)"
        )
    try:
        load_model(model, str(weights), strict=True, device="cpu")
    except Exception as exc:  # safetensors raises its own error types for a malformed file
        raise EstimatorError(f"checkpoint {directory}: cannot read {weights.name}: {exc}") from None
    model = model.to(resolve_device(device)).eval()
    return model, normalizer, card


MAX_MODEL_ELEMENTS = 100_000_000  # parameters + buffers a card may declare (the paper's models: ~100k)


def check_model_size(arch: dict[str, Any], weight_bytes: int, where: Path) -> None:
    """Refuse a card whose architecture is larger than its weight file or than MAX_MODEL_ELEMENTS,
    before allocating it: the model is built on torch's meta device (shapes only, no memory)."""
    try:
        with torch.device("meta"):
            probe = build_from_config(arch["name"], arch["config"])
    except EstimatorError:
        raise
    except Exception as exc:  # a card's config that the architecture rejects
        raise EstimatorError(f"checkpoint {where}: the card's architecture cannot be built: {exc}") from None
    params = sum(p.numel() for p in probe.parameters())
    elements = params + sum(b.numel() for b in probe.buffers())
    if elements > MAX_MODEL_ELEMENTS:
        raise EstimatorError(
            f"checkpoint {where}: the card declares a model of {elements:,} elements, more than the "
            f"{MAX_MODEL_ELEMENTS:,} this package loads"
        )
    if 2 * params > weight_bytes + 4096:  # at least 2 bytes per stored parameter (bf16), plus the header
        raise EstimatorError(
            f"checkpoint {where}: the card declares {params:,} parameters but the weight file holds "
            f"{weight_bytes:,} bytes: card and weights do not belong together"
        )


def _dims(desc: dict[str, Any]) -> tuple[int, int, int]:
    return len(desc.get("state_names", ())), len(desc.get("obs_names", ())), len(desc.get("control_names", ()))


def check_scenario(desc: dict[str, Any], scenario: Scenario, where: str) -> None:
    """Refuse a checkpoint trained on another scenario, other dimensions or other constants.

    Args:
        desc: the checkpoint's scenario description.
        scenario: the scenario it is to serve.
        where: how to name the checkpoint in messages.
    """
    ours = scenario.describe()
    dx, dy, du = _dims(desc)
    if desc.get("scenario") != ours["scenario"]:
        raise EstimatorError(
            f"checkpoint {where} was trained on scenario {desc.get('scenario')!r} (dx={dx}, dy={dy}, du={du}), "
            f"not {ours['scenario']!r} (dx={scenario.dx}, dy={scenario.dy}, du={scenario.du})"
        )
    theirs_cfg, ours_cfg = desc.get("config", {}), ours["config"]
    diffs = [
        f"{k}={theirs_cfg.get(k, '<absent>')!r} (checkpoint) vs {ours_cfg.get(k, '<absent>')!r} (requested)"
        for k in sorted(set(theirs_cfg) | set(ours_cfg))
        if k not in EVALUATION_CONSTANTS and theirs_cfg.get(k) != ours_cfg.get(k)
    ]
    if (dx, dy, du) != (scenario.dx, scenario.dy, scenario.du):
        raise EstimatorError(
            f"checkpoint {where} was trained on scenario {ours['scenario']!r} with dx={dx}, dy={dy}, du={du}, "
            f"but the requested one has dx={scenario.dx}, dy={scenario.dy}, du={scenario.du}"
            + (f" (constants differ: {'; '.join(diffs)})" if diffs else "")
        )
    for key in ("state_names", "obs_names", "control_names", "angle_states", "angle_obs"):
        if list(desc.get(key, [])) != list(ours[key]):
            raise EstimatorError(
                f"checkpoint {where} was trained on scenario {ours['scenario']!r} with {key}={desc.get(key)}, "
                f"but the requested one has {key}={ours[key]}"
            )
    if diffs:
        raise EstimatorError(
            f"checkpoint {where} was trained on scenario {ours['scenario']!r} with other constants: "
            f"{'; '.join(diffs)}. Use the checkpoint's constants, or train a model for these "
            f"(only {', '.join(EVALUATION_CONSTANTS)} may differ)"
        )


def load_neural_estimator(
    method: str,
    scenario: Scenario,
    checkpoint: str | Path | None = None,
    device: str = "cpu",
    covariance: bool = True,
    compile_step: bool = False,
):
    """A :class:`~neural_estimator.models.neural.NeuralEstimator` of ``method`` for ``scenario``.

    Args:
        method: gru, lstm, gpt2, filterformer, mamba or mamba2.
        scenario: the system to serve; the checkpoint must have been trained on it.
        checkpoint: a checkpoint directory or its ``card.json``; None -> the shipped default at
            ``neural_estimator/zoo/<scenario>-<method>/``.
        device: cpu, cuda, cuda:N or auto.
        covariance: report Filterformer's covariance (False saves memory in ``run``).
        compile_step: serve ``step`` through ``torch.compile`` (see NeuralEstimator).

    Raises:
        EstimatorError: no shipped default (the message gives the command that trains one), a
            checkpoint of another method or scenario, missing or corrupt files.
    """
    m = check_method(method)
    if checkpoint is None:
        checkpoint = default_checkpoint(scenario.name, m)
        if not (checkpoint / CARD_FILE).is_file() or not (checkpoint / WEIGHTS_FILE).is_file():
            missing = [f for f in (CARD_FILE, WEIGHTS_FILE) if not (checkpoint / f).is_file()]
            raise EstimatorError(
                f"no trained {m} model ships for scenario {scenario.name!r}: {checkpoint} lacks "
                f"{' and '.join(missing)}. Train one with `neural-estimator train --scenario {scenario.name} "
                f"--model {m} --out {checkpoint}` or pass checkpoint=<dir> (--checkpoint)"
            )
    directory, card = read_card(checkpoint)
    if card["method"] != m:
        raise EstimatorError(f"checkpoint {directory} holds a {card['method']!r} model, not {m!r}")
    check_scenario(card["scenario"], scenario, str(directory))
    model, normalizer, card = load_checkpoint(directory, device)
    return NeuralEstimator(
        scenario, model, normalizer, m, device=device, covariance=covariance, card=card, compile_step=compile_step
    )
