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

The model is rebuilt for its scenario (:func:`~neural_estimator.models.build_model`): the scenario
being served, or the one the card describes (:func:`system_of_card`), with the card's hyperparameters;
the card's ``d_in`` / ``d_out`` must be that scenario's. The weights are read with safetensors only:
no ``torch.load``, no pickle. Trained defaults ship at
``neural_estimator/serving/zoo/<scenario>-<method>/``.

The card's reading and writing is :mod:`neural_estimator.serving.card`; serving a checkpoint for a
scenario (the shipped zoo, the scenario check, the estimator) is :mod:`neural_estimator.serving.load`.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import os
from pathlib import Path
from typing import Any

import torch
from torch import nn

from neural_estimator.methods.interface import EstimatorError
from neural_estimator.models import ARCHITECTURES, System, SystemDims, build_model, count_parameters, model_dims
from neural_estimator.models.kalmannet import HybridSystemError
from neural_estimator.serving.card import (
    canonical_safetensors,
    CARD_FILE,
    CARD_FORMAT,
    CARD_VERSION,
    MAX_MODEL_ELEMENTS,
    WEIGHTS_FILE,
    Checkpoint,
    resolve_checkpoint,
    sha256_file,
    software_versions,
    write_json,
)
from neural_estimator.serving.neural import resolve_device
from neural_estimator.serving.normalization import NormalizationError, Normalizer


# ---- architectures ----------------------------------------------------------------------------------
def architecture_of(model: nn.Module) -> tuple[str, dict[str, Any]]:
    """(architecture name, full config as a dict) of a model built by :mod:`neural_estimator.models`."""
    for name, (_, model_cls) in ARCHITECTURES.items():
        if type(model) is model_cls:
            return name, dataclasses.asdict(model.cfg)
    raise EstimatorError(f"{type(model).__name__} is not one of the registered architectures")


def system_of_card(card: dict[str, Any]) -> System:
    """The system a checkpoint was trained on, from its card's scenario description: the scenario
    itself where it can be rebuilt here (a built-in, or a registered plugin, with the card's
    constants); else (recorded data, a plugin not loaded) its dimensions, read from the
    description's names (:class:`~neural_estimator.models.SystemDims`), which serve a network but
    not a hybrid (it needs the system's f and h: :func:`build_from_config` refuses it in one line).
    A hybrid trained with a model set (its recipe's ``model_set``: f and h other than the data's) gets
    that model scenario, the one it was trained with."""
    from neural_estimator.scenarios import ScenarioError, scenario_from_description
    from neural_estimator.scenarios.model import model_scenario

    desc = card.get("scenario")
    desc = desc if isinstance(desc, dict) else {}
    training = card.get("training")
    recipe = training.get("recipe") if isinstance(training, dict) else None
    told = recipe.get("model_set") if isinstance(recipe, dict) else None
    try:
        return model_scenario(scenario_from_description(desc), told if isinstance(told, dict) else None)
    except (ScenarioError, KeyError, TypeError, ValueError, AttributeError):
        return SystemDims(*(len(desc.get(k) or ()) for k in ("state_names", "obs_names", "control_names")))


def build_from_config(name: str, config: dict[str, Any], system: System) -> nn.Module:
    """Rebuild an (untrained) model for ``system`` from a card's architecture name and full config
    dict (:func:`~neural_estimator.models.build_model`, its errors as EstimatorError naming the card's
    values); the config's ``d_in`` and ``d_out`` must be the system's (``dy + du``, ``dx``)."""
    config = dict(config)
    dims = (config.pop("d_in", None), config.pop("d_out", None))
    if dims != model_dims(system):
        raise EstimatorError(
            f"cannot build {name!r} from the card's config: it maps d_in={dims[0]} to d_out={dims[1]}, but its "
            f"system has dy + du = {model_dims(system)[0]}, dx = {model_dims(system)[1]}"
        )
    try:
        return build_model(name, system, **config)
    except HybridSystemError as exc:  # a hybrid whose card's scenario has no f and h here
        raise EstimatorError(f"cannot build {name!r}: {exc}") from None
    except KeyError as exc:
        raise EstimatorError(f"cannot build {name!r} from the card's config: {str(exc).strip(chr(39))}") from None
    except (TypeError, ValueError, AssertionError) as exc:
        raise EstimatorError(f"cannot build {name} from its config {config}: {exc}") from None


# ---- save ---------------------------------------------------------------------------------------
def savable(model: nn.Module) -> nn.Module:
    """The model itself where every weight owns its storage; else a CPU copy in which each does.

    On a GPU, cuDNN packs a GRU's or LSTM's weights into one buffer that each weight is a view of,
    which safetensors refuses to save ("no suitable name to keep"). Weights tied on purpose (one
    parameter registered twice) stay tied: the copy keeps each parameter object.
    """

    def packed(p: torch.Tensor) -> bool:
        return p.device.type != "cpu" or p.untyped_storage().nbytes() != p.numel() * p.element_size()

    if not any(packed(p) for p in model.parameters()):
        return model
    import copy

    plain = copy.deepcopy(model).cpu()
    for p in plain.parameters():
        p.data = p.data.clone()  # its own storage, exactly its size
    return plain


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
    save_model(savable(model), str(tmp), metadata={"format": CARD_FORMAT, "method": name}, force_contiguous=True)
    canonical_safetensors(tmp)  # the same weights, the same bytes (and digests, cache keys)
    os.replace(tmp, weights)
    from neural_estimator.serving.uncertainty.heads import HEAD_FILE

    (directory / HEAD_FILE).unlink(missing_ok=True)  # a covariance head belongs to the weights it was fitted on
    from neural_estimator.serving.onnx_runtime import ONNX_FILE

    (directory / ONNX_FILE).unlink(missing_ok=True)  # so does the exported step (train writes it anew)
    full = {
        "format": CARD_FORMAT,
        "format_version": CARD_VERSION,
        "method": name,
        "scenario": card["scenario"],
        "architecture": {"name": name, "config": config, "parameters": count_parameters(model)},
        "normalization": normalizer.to_dict(),
    }
    for key, value in card.items():
        if key not in full and key != "covariance_head":  # a head is fitted afterwards, on these weights
            full[key] = value
    full["weights"] = {"file": WEIGHTS_FILE, "sha256": sha256_file(weights), "tensors": len(model.state_dict())}
    full["software"] = software_versions()
    full.setdefault("created", _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"))
    write_json(directory / CARD_FILE, full)
    return directory


# ---- load ---------------------------------------------------------------------------------------
def load_checkpoint(
    checkpoint: str | Path | Checkpoint, device: str | torch.device = "cpu", scenario: System | None = None
) -> tuple[nn.Module, Normalizer, dict[str, Any]]:
    """(model in eval mode on ``device``, normalizer, card) of a checkpoint directory, its card, or a
    :class:`~neural_estimator.serving.card.Checkpoint` already resolved (its card is not read again,
    its weights not hashed again).

    ``scenario``: the system the model is built for (:func:`~neural_estimator.models.build_model`);
    None: the one its card describes (:func:`system_of_card`). Either way the card's ``d_in`` and
    ``d_out`` must be its dimensions; whether the checkpoint may serve a scenario (its name and
    constants) is :func:`~neural_estimator.serving.load.check_scenario`'s question.

    Raises:
        EstimatorError: missing or corrupt card or weights, weights that do not match the card.
    """
    from safetensors.torch import load_model

    ckpt = resolve_checkpoint(checkpoint)
    directory, card = ckpt.directory, ckpt.card
    arch = card["architecture"]
    try:
        normalizer = Normalizer.from_dict(card["normalization"])
    except NormalizationError as exc:
        raise EstimatorError(f"{directory / CARD_FILE}: {exc}") from None
    weights = ckpt.weights
    system = system_of_card(card) if scenario is None else scenario
    check_model_size(arch, weights.stat().st_size, directory, system)
    model = build_from_config(arch["name"], arch["config"], system)
    expected = card["weights"].get("sha256")
    if expected and ckpt.sha256 != expected:
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


def check_model_size(arch: dict[str, Any], weight_bytes: int, where: Path, system: System) -> None:
    """Refuse a card whose architecture is larger than its weight file or than MAX_MODEL_ELEMENTS, or
    smaller than its weight file can hold (8 bytes an element plus the header),
    before allocating it: the model is built on torch's meta device (shapes only, no memory)."""
    try:
        with torch.device("meta"):
            probe = build_from_config(arch["name"], arch["config"], system)
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
    tensors = len(probe.state_dict())
    most = 8 * elements + HEADER_BYTES_PER_TENSOR * tensors + 4096
    if weight_bytes > most:  # checked before the file is hashed: a huge (or sparse) file costs no read
        raise EstimatorError(
            f"checkpoint {where}: the weight file holds {weight_bytes:,} bytes, more than the {most:,} that "
            f"the card's model of {elements:,} elements can fill (8 bytes each, plus the header): card and "
            "weights do not belong together"
        )


# A safetensors header entry: name, dtype, shape and offsets in JSON, under 200 bytes for this
# package's tensor names (the zoo's headers: measured in test_checkpoint_files.py); 1 KiB leaves room.
HEADER_BYTES_PER_TENSOR = 1024
