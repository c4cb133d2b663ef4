"""The trained instances of a (scenario, method) pair in the zoo.

The paper trains 15 instances per architecture and reports medians over them. The zoo ships the
pair's model as instance 0 (``zoo/<scenario>-<method>/``) and further instances, each trained on
its own training set with its own initialisation, as ``zoo/instances/i<K>/<scenario>-<method>/``
(K >= 1; ``scripts/train_zoo.py --instance K`` writes them). An instance is a directory holding
a ``card.json`` and a ``model.safetensors``.
"""

from __future__ import annotations

import re
from pathlib import Path

from neural_estimator.serving.card import CARD_FILE, WEIGHTS_FILE, ZOO_DIR

INSTANCES_DIR = "instances"
_INSTANCE = re.compile(r"i(\d+)")


def instance_number(directory: str | Path) -> int | None:
    """K of a checkpoint at ``.../instances/i<K>/<pair>/``, 0 for any other directory (the shipped
    model, or a checkpoint given by hand), None for a non-directory."""
    path = Path(directory)
    match = _INSTANCE.fullmatch(path.parent.name)
    return int(match.group(1)) if match and path.parent.parent.name == INSTANCES_DIR else 0


def instance_checkpoint(scenario_name: str, method: str, instance: int, zoo: str | Path | None = None) -> Path:
    """Where instance ``instance`` of (scenario, method) lives in the zoo, whether or not it is there:
    ``zoo/<scenario>-<method>/`` for 0 (the shipped model), ``zoo/instances/i<K>/<scenario>-<method>/``
    for K >= 1. A negative ``instance`` is a ValueError."""
    if instance < 0:
        raise ValueError(f"an instance is >= 0 (0: the shipped model), got {instance}")
    root = Path(zoo) if zoo is not None else ZOO_DIR
    pair = f"{scenario_name}-{method}"
    return root / pair if instance == 0 else root / INSTANCES_DIR / f"i{instance}" / pair


def zoo_instances(scenario_name: str, method: str, zoo: str | Path | None = None) -> list[Path]:
    """The checkpoint directories of every instance of (scenario, method), instance 0 (the shipped
    model) first, then ``instances/i<K>/`` by K; only complete ones (card and weights present).
    Empty when the pair ships no model."""
    root = Path(zoo) if zoo is not None else ZOO_DIR
    pair = f"{scenario_name}-{method}"
    found = []
    if _complete(root / pair):
        found.append((0, root / pair))
    base = root / INSTANCES_DIR
    if base.is_dir():
        for sub in base.iterdir():
            match = _INSTANCE.fullmatch(sub.name)
            if match and int(match.group(1)) >= 1 and _complete(sub / pair):
                found.append((int(match.group(1)), sub / pair))
    return [path for _, path in sorted(found)]


def _complete(directory: Path) -> bool:
    return (directory / CARD_FILE).is_file() and (directory / WEIGHTS_FILE).is_file()
