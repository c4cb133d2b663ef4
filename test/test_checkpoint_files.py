"""A checkpoint's weight file is a regular file inside the checkpoint, and its size is checked
before a byte of it is read or hashed: a symbolic link is never followed (not even to print the
size of what it points at), a FIFO never blocks, and a huge or sparse file is refused at once."""

from __future__ import annotations

import json
import os
import shutil
import struct
import time
from pathlib import Path

import pytest

from neural_estimator.methods.interface import EstimatorError
from neural_estimator.serving.card import MAX_WEIGHT_BYTES, WEIGHTS_FILE, resolve_checkpoint
from neural_estimator.serving.checkpoint import HEADER_BYTES_PER_TENSOR, load_checkpoint

ZOO = Path(__file__).resolve().parents[1] / "neural_estimator" / "serving" / "zoo"


@pytest.fixture
def ckpt(tmp_path) -> Path:
    out = tmp_path / "ckpt"
    shutil.copytree(ZOO / "lorenz96-gru", out)
    return out


def _refused(ckpt: Path, *words: str) -> str:
    t0 = time.perf_counter()
    with pytest.raises(EstimatorError) as info:
        load_checkpoint(ckpt)
    assert time.perf_counter() - t0 < 10.0  # nothing of size was read (a bound, not a timing)
    text = str(info.value)
    assert "\n" not in text and all(w in text for w in words), text
    return text


def test_weights_behind_a_symlink_are_not_followed(ckpt, tmp_path):
    outside = tmp_path / "secret.bin"
    outside.write_bytes(b"x" * 123_457)
    (ckpt / WEIGHTS_FILE).unlink()
    (ckpt / WEIGHTS_FILE).symlink_to(outside)
    text = _refused(ckpt, "symbolic link", "regular file inside the checkpoint")
    assert "123,457" not in text and "123457" not in text  # the target's size is not printed
    with pytest.raises(EstimatorError, match="symbolic link"):  # nor hashed for a cache key
        resolve_checkpoint(ckpt).digest


def test_a_huge_sparse_weight_file_is_refused_before_hashing(ckpt, monkeypatch):
    import neural_estimator.serving.card as card

    def no_hash(*_a, **_k):
        raise AssertionError("the weight file was hashed before its size was checked")

    monkeypatch.setattr(card, "_hash", no_hash)
    monkeypatch.setattr(card, "sha256_file", no_hash)
    weights = ckpt / WEIGHTS_FILE
    with open(weights, "r+b") as f:
        f.truncate(5 * 10**9)  # sparse: 5 GB of size, no blocks
    _refused(ckpt, f"{5 * 10**9:,} bytes", f"{MAX_WEIGHT_BYTES:,}")
    with open(weights, "r+b") as f:
        f.truncate(50 * 2**20)  # under the absolute bound, far over what the card's model can fill
    _refused(ckpt, f"{50 * 2**20:,} bytes", "card and weights do not belong together")


def test_a_fifo_as_weights_does_not_block(ckpt):
    weights = ckpt / WEIGHTS_FILE
    weights.unlink()
    os.mkfifo(weights)
    _refused(ckpt, "not a regular file")


def test_the_zoo_loads_and_its_headers_fit_the_allowance():
    for d in sorted(p for p in ZOO.iterdir() if (p / WEIGHTS_FILE).is_file()):
        raw = (d / WEIGHTS_FILE).read_bytes()
        n = struct.unpack("<Q", raw[:8])[0]
        per_tensor = n / len(json.loads(raw[8 : 8 + n]))
        assert per_tensor < HEADER_BYTES_PER_TENSOR / 5, (d.name, per_tensor)  # measured: under 100 bytes
    model, _, _ = load_checkpoint(ZOO / "lorenz96-gru")
    assert sum(p.numel() for p in model.parameters()) > 0
