"""Checkpoint cards: the JSON half of a checkpoint, read and written without running code.

A card (``card.json``) holds everything needed to rebuild and judge a model (see
:mod:`neural_estimator.serving.checkpoint`); this module reads and writes cards and other JSON
files atomically and without NaN/inf tokens, hashes the weight file, and records the software
versions. It imports no torch model code.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import platform
from pathlib import Path
from typing import Any

import numpy as np

from neural_estimator import __version__
from neural_estimator.estimator import EstimatorError

CARD_FORMAT = "neural_estimator.checkpoint"
CARD_VERSION = 1
WEIGHTS_FILE = "model.safetensors"
CARD_FILE = "card.json"


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
    import torch  # here, not at the top: reading a card (serving without torch) needs no torch

    return {
        "neural_estimator": __version__,
        "torch": torch.__version__,
        "numpy": np.__version__,
        "safetensors": safetensors.__version__,
        "python": platform.python_version(),
    }


def checkpoint_paths(checkpoint: str | Path) -> tuple[Path, Path]:
    """(directory, card path) of a checkpoint given as its directory or its ``card.json``."""
    p = Path(checkpoint)
    if p.suffix == ".json" or p.is_file():
        return p.parent, p
    return p, p / CARD_FILE


def read_card(checkpoint: str | Path) -> tuple[Path, dict[str, Any]]:
    """(directory, card) of a checkpoint; a missing or corrupt card raises EstimatorError."""
    directory, card_path = checkpoint_paths(checkpoint)
    if not directory.exists():
        raise EstimatorError(f"checkpoint {directory} does not exist")
    card = read_json(card_path, "checkpoint card")
    if card.get("format") != CARD_FORMAT:
        raise EstimatorError(f"{card_path}: not a neural_estimator checkpoint card (format {card.get('format')!r})")
    version = card.get("format_version", 0)
    if not isinstance(version, int) or isinstance(version, bool) or version < 0:
        raise EstimatorError(
            f"{card_path}: checkpoint card is corrupt (format_version {version!r} is not a version number)"
        )
    if version > CARD_VERSION:
        raise EstimatorError(
            f"{card_path}: card format version {version} is newer than this "
            f"neural_estimator reads ({CARD_VERSION}); upgrade the package"
        )
    for key in ("method", "scenario", "architecture", "normalization", "weights"):
        if key not in card:
            raise EstimatorError(f"{card_path}: checkpoint card is corrupt (no {key!r} entry)")
    for key, kind in (("scenario", dict), ("architecture", dict), ("normalization", dict), ("weights", dict)):
        if not isinstance(card[key], kind):
            raise EstimatorError(
                f"{card_path}: checkpoint card is corrupt ({key!r} is a {type(card[key]).__name__}, not an object)"
            )
    arch = card["architecture"]
    if not isinstance(arch.get("name"), str) or not isinstance(arch.get("config"), dict):
        raise EstimatorError(f"{card_path}: checkpoint card is corrupt (architecture needs a name and a config object)")
    for key, value in arch["config"].items():
        if key in COUNT_KEYS and (not isinstance(value, int) or isinstance(value, bool) or not 0 <= value <= MAX_COUNT):
            raise EstimatorError(
                f"{card_path}: the card's {arch['name']} config has {key}={value!r}; at most {MAX_COUNT} "
                "(the bound on layers, heads and components a card may declare)"
            )
    return directory, card


# Config entries that count repeated modules: bounded before a model is built (building 200,000 layers,
# even on the meta device, takes minutes). The shipped models have 2-4 layers, 4 heads, 32 components.
COUNT_KEYS = ("layers", "n_layer", "n_head", "n_components")
MAX_COUNT = 256
