"""Warm start: a training run that begins from a trained checkpoint's weights instead of a fresh
initialisation (fine-tuning).

The run is otherwise the recipe's: a fresh AdamW state and scheduler at the recipe's learning rate,
its own data, window draws and stopping rules; only the initial weights differ (step 3 of
:mod:`neural_estimator.training.loop`). Typical uses: continue a training whose resume state is gone
at a lower learning rate, or adapt a shipped model to a team's recording.

The checkpoint must hold the same architecture with the same configuration as the model the run
builds (every field of the model's config, not only the tensor shapes: a hybrid's gain form changes
no shape but changes what the weights mean). Its normalisation may differ (another dataset); the
card records whether it did, since the weights then start on inputs scaled otherwise than they
learnt.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from torch import nn

from neural_estimator.methods.interface import EstimatorError
from neural_estimator.serving.checkpoint import architecture_of, load_checkpoint
from neural_estimator.serving.normalization import Normalizer
from neural_estimator.training.recipe import TrainingError


def _plain(value: Any) -> Any:
    """``value`` as JSON gives it back (tuples as lists, keys as strings): the form a card stores."""
    return json.loads(json.dumps(value))


def warm_start(model: nn.Module, checkpoint: str | Path, system, normalizer: Normalizer) -> dict[str, Any]:
    """Copy the weights of ``checkpoint`` into ``model`` (just built for this run, on its device).

    Args:
        model: the run's model.
        checkpoint: a checkpoint directory (or its card) of the same architecture and configuration.
        system: the system the run's model is built for (the checkpoint is loaded for it).
        normalizer: the run's normalisation statistics (compared with the checkpoint's).

    Returns:
        The card's record: ``{"checkpoint", "sha256", "validation_loss", "same_normalization"}``.

    Raises:
        TrainingError: not a readable checkpoint, or one of another architecture or configuration.
    """
    try:
        source, source_norm, card = load_checkpoint(checkpoint, scenario=system)
    except EstimatorError as exc:
        raise TrainingError(f"init_from: {exc}") from None
    name, config = architecture_of(model)
    theirs, ours = card["architecture"]["name"], _plain(config)
    if theirs != name:
        raise TrainingError(f"init_from {checkpoint}: a {theirs} checkpoint cannot start a {name} training")
    differ = sorted(
        k
        for k in set(ours) | set(card["architecture"]["config"])
        if card["architecture"]["config"].get(k) != ours.get(k)
    )
    if differ:
        raise TrainingError(
            f"init_from {checkpoint}: its {name} is configured otherwise than this run's "
            f"({', '.join(differ)}): the weights would not mean the same"
        )
    device = next(model.parameters()).device
    model.load_state_dict({k: v.to(device) for k, v in source.state_dict().items()}, strict=True)
    return {
        "checkpoint": str(checkpoint),
        "sha256": card["weights"].get("sha256"),
        "validation_loss": card.get("validation_loss"),
        "same_normalization": _plain(source_norm.to_dict()) == _plain(normalizer.to_dict()),
    }
