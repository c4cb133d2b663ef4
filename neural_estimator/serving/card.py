"""Checkpoint cards: the JSON half of a checkpoint, read and written without running code.

A card (``card.json``) holds everything needed to rebuild and judge a model (see
:mod:`neural_estimator.serving.checkpoint`); this module reads and writes cards and other JSON
files atomically and without NaN/inf tokens, hashes the weight file, and records the software
versions. It imports no torch model code.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import math
import os
import platform
import stat
from pathlib import Path
from typing import Any

import numpy as np

from neural_estimator import __version__
from neural_estimator.methods.interface import EstimatorError

CARD_FORMAT = "neural_estimator.checkpoint"
CARD_VERSION = 1
WEIGHTS_FILE = "model.safetensors"
CARD_FILE = "card.json"
ZOO_DIR = Path(__file__).resolve().parent / "zoo"


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
    return parse_json(path.read_bytes(), path, what)


def parse_json(raw: bytes, path: Path, what: str = "file") -> dict[str, Any]:
    """The JSON object in ``raw`` (the bytes of ``path``); malformed JSON raises EstimatorError naming it."""
    try:
        obj = json.loads(raw.decode())
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


def canonical_safetensors(path: str | Path) -> None:
    """Rewrite a safetensors file's header so that the same tensors and metadata give the same bytes.

    The format is an 8-byte little-endian header length N, N bytes of JSON header (padded with
    spaces to a multiple of 8), then the tensor data, with offsets relative to the data's start.
    safetensors' writer orders the tensor entries by name but writes ``__metadata__`` from a hash map,
    in an order that changes from process to process: two identical trainings gave weight files that
    differed in those bytes only, and so every digest and cache key made from them. Here the
    metadata keys are sorted; the tensor entries and the data are kept byte for byte. Idempotent."""
    path = Path(path)
    with open(path, "r+b") as fh:
        n = int.from_bytes(fh.read(8), "little")
        raw = fh.read(n)
        header = json.loads(raw)
        meta = header.get("__metadata__")
        if not meta:
            return
        ordered = {"__metadata__": dict(sorted(meta.items()))}
        ordered.update((k, v) for k, v in header.items() if k != "__metadata__")
        text = json.dumps(ordered, separators=(",", ":"), ensure_ascii=False).encode()
        if len(text) > n:  # never for a reordering (same keys, same values): keep the data where it is
            raise ValueError(f"{path}: canonical safetensors header is longer than the written one")
        fh.seek(8)
        fh.write(text + b" " * (n - len(text)))


# The most parameters + buffers a card may declare (the paper's models: ~100k), and so the largest
# weight file read: every element in float64 (8 bytes) plus safetensors' own bound on its JSON header
# (100 MB). A file above it is refused from its size alone, before a byte of it is read or hashed.
MAX_MODEL_ELEMENTS = 100_000_000
MAX_WEIGHT_BYTES = 8 * MAX_MODEL_ELEMENTS + 100_000_000


def open_checkpoint_file(directory: Path, name: object, what: str, error: type[Exception] = EstimatorError):
    """Open the file ``name`` of a checkpoint for reading (binary) after checking that it is one:
    a plain file name (no directory part), not a symbolic link (opened with ``O_NOFOLLOW``: a link
    to a file outside the checkpoint is never followed, not even to print its size), a regular file
    (not a FIFO or a device), and at most :data:`MAX_WEIGHT_BYTES` long. Every refusal is one
    ``error`` line naming the checkpoint, the file and why."""
    if not isinstance(name, str) or not name or Path(name).name != name or name in (".", ".."):
        raise error(f"{directory / CARD_FILE}: the {what} must be a file name inside the checkpoint, got {name!r}")
    path = directory / name
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0))
    except FileNotFoundError:
        raise error(f"checkpoint {directory}: {what} {name} is missing") from None
    except OSError as exc:
        if path.is_symlink():
            raise error(
                f"checkpoint {directory}: {what} {name} is a symbolic link; it must be a regular file "
                "inside the checkpoint (copy the file there)"
            ) from None
        raise error(f"checkpoint {directory}: cannot open {what} {name} ({exc.strerror or exc})") from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise error(f"checkpoint {directory}: {what} {name} is not a regular file")
        if info.st_size > MAX_WEIGHT_BYTES:
            raise error(
                f"checkpoint {directory}: {what} {name} holds {info.st_size:,} bytes, over the bound of "
                f"{MAX_WEIGHT_BYTES:,} (8 bytes per element of the {MAX_MODEL_ELEMENTS:,} this package loads, "
                "plus the header)"
            )
        os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


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
    return directory, check_card(read_json(card_path, "checkpoint card"), card_path)


def check_card(card: dict[str, Any], card_path: Path) -> dict[str, Any]:
    """``card`` if it is a readable checkpoint card (format, version, entries, bounded counts);
    EstimatorError naming ``card_path`` otherwise."""
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
    return card


# Config entries that count repeated modules: bounded before a model is built (building 200,000 layers,
# even on the meta device, takes minutes). The shipped models have 2-4 layers, 4 heads, 32 components.
COUNT_KEYS = ("layers", "n_layer", "n_head", "n_components")
MAX_COUNT = 256


# ---- a checkpoint resolved once ---------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Checkpoint:
    """A checkpoint resolved once by :func:`resolve_checkpoint`: its directory and its card (read and
    checked once); on first use its weight file, the weights' SHA-256 and ``digest``, the BLAKE2b of
    card and weights that keys cached results (both from one pass over the weights, then kept).
    Passed down in place of a path, so nothing below reads the card or hashes the weights again, and
    a caller that needs no weights (the ONNX step beside the card) hashes nothing."""

    directory: Path
    card: dict[str, Any]
    card_path: Path
    card_bytes: bytes = dataclasses.field(repr=False)

    @functools.cached_property
    def weights(self) -> Path:
        """The card's weight file: a file name inside the checkpoint, present (EstimatorError otherwise)."""
        return _weight_file(self.directory, self.card)

    @functools.cached_property
    def _digests(self) -> tuple[str, str]:
        if self.card_path == self.directory / CARD_FILE and self.weights == self.directory / WEIGHTS_FILE:
            sha256, digest = _hash(self.card_bytes, self.weights)
            return str(sha256), digest
        # a card or weight file of another name: the digest is of the usual files, as for any checkpoint
        return sha256_file(self.weights), checkpoint_digest(self.directory)

    @property
    def sha256(self) -> str:
        return self._digests[0]

    @property
    def digest(self) -> str:
        return self._digests[1]


def default_checkpoint(scenario_name: str, method: str) -> Path:
    """Where the shipped model of (scenario, method) lives."""
    return ZOO_DIR / f"{scenario_name}-{method}"


def shipped_preset(scenario_name: str, method: str) -> str | None:
    """The preset whose constants the shipped model of (scenario, method) was trained on (read from
    its card's constants; the default preset for a scenario without presets), or None when none ships."""
    from neural_estimator.scenarios import scenario_class

    path = default_checkpoint(scenario_name, method) / CARD_FILE
    if not path.exists():
        return None
    config = read_json(path, "card")["scenario"]["config"]
    return scenario_class(scenario_name).preset_of(config)


def resolve_checkpoint(
    checkpoint: str | Path | Checkpoint | None, scenario_name: str | None = None, method: str | None = None
) -> Checkpoint:
    """The :class:`Checkpoint` of a directory or ``card.json`` (a :class:`Checkpoint` is returned as it
    is); None: the shipped model of (``scenario_name``, ``method``).

    Raises:
        EstimatorError: no shipped model (the message gives the command that trains one), a missing
            or corrupt card (the weight file is checked where it is first used).
    """
    if isinstance(checkpoint, Checkpoint):
        return checkpoint
    if checkpoint is None:
        checkpoint = default_checkpoint(str(scenario_name), str(method))
        missing = [f for f in (CARD_FILE, WEIGHTS_FILE) if not (checkpoint / f).is_file()]
        if missing:
            raise EstimatorError(
                f"no trained {method} model ships for scenario {scenario_name!r}: {checkpoint} lacks "
                f"{' and '.join(missing)}. Train one with `neural-estimator train --scenario {scenario_name} "
                f"--model {method} --out {checkpoint}` or pass checkpoint=<dir> (--checkpoint)"
            )
    directory, card_path = checkpoint_paths(checkpoint)
    if not directory.exists():
        raise EstimatorError(f"checkpoint {directory} does not exist")
    if not card_path.is_file():
        raise EstimatorError(f"{card_path}: checkpoint card is missing")
    raw = card_path.read_bytes()
    card = check_card(parse_json(raw, card_path, "checkpoint card"), card_path)
    return Checkpoint(directory, card, card_path, raw)


def checkpoint_digest(directory: Path) -> str:
    """BLAKE2b of a checkpoint directory's ``card.json`` and ``model.safetensors``, the key of its
    cached results; a missing file hashes as "missing" (so a key can be made before training)."""
    card = directory / CARD_FILE
    return _hash(card.read_bytes() if card.is_file() else None, directory / WEIGHTS_FILE)[1]


def _hash(card: bytes | None, weights: Path) -> tuple[str | None, str]:
    """(SHA-256 of the weights, BLAKE2b of card and weights), one pass over the weight file."""
    h = hashlib.blake2b(digest_size=16)
    h.update(CARD_FILE.encode())
    h.update(b"missing" if card is None else card)
    h.update(WEIGHTS_FILE.encode())
    if not weights.is_file() and not weights.is_symlink():
        h.update(b"missing")
        return None, h.hexdigest()
    sha = hashlib.sha256()
    with open_checkpoint_file(weights.parent, weights.name, "weight file") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            sha.update(block)
            h.update(block)
    return sha.hexdigest(), h.hexdigest()


def _weight_file(directory: Path, card: dict[str, Any]) -> Path:
    """The card's weight file: a regular file inside the checkpoint, present, within MAX_WEIGHT_BYTES
    (:func:`open_checkpoint_file`), checked before anything reads or hashes it."""
    name = card["weights"].get("file", WEIGHTS_FILE)
    open_checkpoint_file(directory, name, "weight file").close()
    return directory / name


def recorded_data_checkpoint(checkpoint: str) -> "Checkpoint | None":
    """The resolved :class:`~neural_estimator.serving.card.Checkpoint` when ``checkpoint`` is a
    readable card of a model trained with ``train --data`` (passed on, so its card is read once)."""
    try:
        read = resolve_checkpoint(checkpoint)
    except EstimatorError:
        return None  # the estimator node reports a missing or corrupt checkpoint itself
    return read if read.card.get("scenario", {}).get("scenario") == "data" else None
