"""A checkpoint is resolved once: one value (directory, card, weights, digests) made by
``serving.card.resolve_checkpoint`` and passed down, so an evaluation reads its card once and
hashes its weights once, and the result cache's key is the digest it always was."""

from __future__ import annotations

import hashlib
import shutil

import pytest

from neural_estimator.evaluation import checkpoint_digest, evaluate
from neural_estimator.methods.registry import EstimatorError
from neural_estimator.scenarios import make_scenario
from neural_estimator.serving import card as C
from neural_estimator.serving.instances import zoo_instances
from neural_estimator.serving.uncertainty import heads as _heads  # noqa: F401  bound to the real sha256_file before any patch


def _counting(monkeypatch):
    calls = {"check_card": 0, "hash": 0, "sha256_file": 0}
    for name in calls:
        real = getattr(C, "_hash" if name == "hash" else name)

        def counted(*a, _real=real, _name=name, **k):
            calls[_name] += 1
            return _real(*a, **k)

        monkeypatch.setattr(C, "_hash" if name == "hash" else name, counted)
    return calls


def test_an_evaluation_reads_each_card_once_and_hashes_the_weights_once(tmp_path, monkeypatch):
    """Once per checkpoint: the evaluation runs every trained instance the zoo ships of the pair."""
    k = len(zoo_instances("lorenz96", "gru"))
    assert k >= 1
    calls = _counting(monkeypatch)
    scenario = make_scenario("lorenz96")
    kw = dict(trajectories=2, horizon=12, sets=2, cache_dir=tmp_path, progress=False)
    first = evaluate(scenario, ["gru"], **kw)
    assert calls == {"check_card": k, "hash": k, "sha256_file": 0}, calls
    assert len(first["gru"].reports) == 2 * k and first["gru"].n_instances == k
    for name in calls:
        calls[name] = 0
    second = evaluate(scenario, ["gru"], **kw)  # every run cached: still one resolution each, no loading
    assert second["gru"].cached == 2 * k and calls == {"check_card": k, "hash": k, "sha256_file": 0}, calls


def test_the_resolved_digest_is_the_result_cache_key_of_the_files():
    scenario = make_scenario("lorenz96")
    ckpt = C.resolve_checkpoint(None, "lorenz96", "gru")
    assert ckpt.directory == C.default_checkpoint("lorenz96", "gru")
    assert ckpt.sha256 == ckpt.card["weights"]["sha256"]
    h = hashlib.blake2b(digest_size=16)
    for name in (C.CARD_FILE, C.WEIGHTS_FILE):
        h.update(name.encode())
        h.update((ckpt.directory / name).read_bytes())
    assert ckpt.digest == h.hexdigest()
    assert checkpoint_digest(scenario, "gru", ckpt) == checkpoint_digest(scenario, "gru", None) == ckpt.digest
    assert checkpoint_digest(scenario, "gru", ckpt.directory / C.CARD_FILE) == ckpt.digest
    assert checkpoint_digest(scenario, "ekf", None) is None


def test_a_checkpoint_that_cannot_be_resolved_is_one_line(tmp_path):
    with pytest.raises(EstimatorError, match="does not exist"):
        C.resolve_checkpoint(tmp_path / "nowhere")
    with pytest.raises(EstimatorError, match="no trained gru model ships for scenario 'nowhere'"):
        C.resolve_checkpoint(None, "nowhere", "gru")
    ckpt = tmp_path / "ckpt"
    shutil.copytree(C.default_checkpoint("lorenz96", "gru"), ckpt)
    (ckpt / C.WEIGHTS_FILE).unlink()
    resolved = C.resolve_checkpoint(ckpt)  # the card alone: what serving the ONNX step beside it needs
    with pytest.raises(EstimatorError, match="weight file model.safetensors is missing"):
        resolved.digest
    # before training, a job's key is made from files that do not exist yet
    assert len(C.checkpoint_digest(tmp_path / "later")) == 32


def test_canonical_safetensors_sorts_the_metadata_and_keeps_every_tensor_byte(tmp_path):
    """A header whose metadata came out in another order (safetensors writes it from a hash map)
    becomes the sorted one; tensors load equal and the data bytes are untouched."""
    import json

    import torch
    from safetensors.torch import load_file

    from neural_estimator.serving.card import canonical_safetensors

    data = torch.arange(6, dtype=torch.float32).numpy().tobytes()
    header = {
        "__metadata__": {"method": "gru", "format": "neural_estimator.checkpoint"},
        "w": {"dtype": "F32", "shape": [2, 3], "data_offsets": [0, 24]},
    }
    text = json.dumps(header, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 8)
    path = tmp_path / "w.safetensors"
    path.write_bytes(len(text).to_bytes(8, "little") + text + data)
    canonical_safetensors(path)
    raw = path.read_bytes()
    n = int.from_bytes(raw[:8], "little")
    assert n == len(text) and raw[8 + n :] == data
    assert list(json.loads(raw[8 : 8 + n])["__metadata__"]) == ["format", "method"]
    assert torch.equal(load_file(str(path))["w"], torch.arange(6, dtype=torch.float32).view(2, 3))
    canonical_safetensors(path)
    assert path.read_bytes() == raw  # idempotent


def test_the_same_model_saved_again_is_the_same_file(tmp_path):
    """Two saves of one model (card entries that vary, e.g. the creation time, aside) write
    byte-identical weights: the digests and cache keys made from them survive a rerun."""
    import torch

    from neural_estimator.models import build_model
    from neural_estimator.scenarios import make_scenario
    from neural_estimator.serving.checkpoint import save_checkpoint
    from neural_estimator.serving.normalization import Normalizer

    from neural_estimator.data import simulate

    scenario = make_scenario("lorenz96")
    torch.manual_seed(0)
    model = build_model("gru", scenario, hidden=4, layers=1)
    norm = Normalizer.from_data(scenario, simulate(scenario, 2, 5, seed=0))
    card = {"scenario": scenario.describe()}
    files = set()
    for i in range(8):
        save_checkpoint(tmp_path / str(i), model, norm, dict(card))
        files.add((tmp_path / str(i) / "model.safetensors").read_bytes())
    assert len(files) == 1
