"""Checkpoints (safetensors + JSON): identical outputs after a round trip, shared buffers, never unpickled,
the wrong, missing or corrupt checkpoint refused with its name.
"""

import json
import pickle

import numpy as np
import pytest
import torch

from neural_estimator.data import simulate
from neural_estimator.methods.registry import EstimatorError, make_estimator
from neural_estimator.serving.checkpoint import save_checkpoint
from neural_estimator.serving.load import load_neural_estimator
from neural_estimator.scenarios import make_scenario
from training_cases import (
    ARCHS,
    estimator_for,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tiny tensors: one intra-op thread


# ---- checkpoints ----------------------------------------------------------------------------------
def _save(tmp_path, scenario, arch, name="ckpt"):
    data = simulate(scenario, 4, 30, seed=0)
    est = estimator_for(scenario, arch, data)
    path = save_checkpoint(tmp_path / name, est.model, est.normalizer, {"scenario": scenario.describe()})
    return est, path, data


@pytest.mark.parametrize("arch", ARCHS)
def test_checkpoint_round_trip_gives_identical_outputs(arch, oscillator, tmp_path):
    est, path, data = _save(tmp_path, oscillator, arch)
    assert sorted(p.name for p in path.iterdir()) == ["card.json", "model.safetensors"]
    back = load_neural_estimator(arch, oscillator, path)
    a, b = est.run(data.y, data.u), back.run(data.y, data.u)
    np.testing.assert_array_equal(a.x, b.x)
    card = back.card
    assert card["method"] == arch and card["architecture"]["name"] == arch
    assert card["architecture"]["parameters"] == sum(p.numel() for p in est.model.parameters())
    assert card["scenario"] == oscillator.describe()
    assert {"torch", "numpy", "safetensors", "neural_estimator"} <= set(card["software"])
    # the card path works too, and so does the registry
    again = make_estimator(arch, oscillator, checkpoint=path / "card.json")
    np.testing.assert_array_equal(again.run(data.y, data.u).x, a.x)


def test_a_model_whose_weights_share_one_buffer_saves_and_loads(oscillator, tmp_path):
    """cuDNN packs a GRU's weights into one buffer on a GPU; the same packing, made here by hand,
    must save (a plain copy) and load to the same outputs."""
    data = simulate(oscillator, 4, 30, seed=0)
    est = estimator_for(oscillator, "gru", data)
    before = est.run(data.y, data.u).x
    params = list(est.model.parameters())
    flat = torch.cat([p.detach().reshape(-1) for p in params])
    offset = 0
    for p in params:
        p.data = flat[offset : offset + p.numel()].view_as(p)
        offset += p.numel()
    assert params[0].untyped_storage().data_ptr() == params[-1].untyped_storage().data_ptr()
    path = save_checkpoint(tmp_path / "packed", est.model, est.normalizer, {"scenario": oscillator.describe()})
    np.testing.assert_array_equal(load_neural_estimator("gru", oscillator, path).run(data.y, data.u).x, before)
    assert params[0].untyped_storage().data_ptr() == flat.untyped_storage().data_ptr()  # the model untouched


def test_loading_never_unpickles(oscillator, tmp_path, monkeypatch):
    _, path, data = _save(tmp_path, oscillator, "gru")

    def forbidden(*args, **kwargs):
        raise AssertionError("a checkpoint load reached torch.load / pickle")

    monkeypatch.setattr(torch, "load", forbidden)
    monkeypatch.setattr(pickle, "load", forbidden)
    monkeypatch.setattr(pickle, "loads", forbidden)
    monkeypatch.setattr(pickle, "Unpickler", forbidden)
    load_neural_estimator("gru", oscillator, path).run(data.y, data.u)


def test_loading_refuses_the_wrong_checkpoint(oscillator, spinner, tmp_path):
    _, path, _ = _save(tmp_path, oscillator, "gru")
    with pytest.raises(
        EstimatorError,
        match=r"was trained on scenario 'oscillator' \(dx=2, dy=1, du=0\), "
        r"not 'test_spinner' \(dx=2, dy=1, du=1\)",
    ):
        load_neural_estimator("gru", spinner, path)
    with pytest.raises(EstimatorError, match="holds a 'gru' model, not 'lstm'"):
        load_neural_estimator("lstm", oscillator, path)
    with pytest.raises(EstimatorError, match=r"other constants: omega=1\.0 \(checkpoint\) vs 2\.0 \(requested\)"):
        load_neural_estimator("gru", make_scenario("oscillator", omega=2.0), path)
    # the evaluation-only constants may differ (the noise-robustness study)
    load_neural_estimator("gru", make_scenario("oscillator", noise_scale=3.0, horizon=50), path)
    # other dimensions under the same name
    card = json.loads((path / "card.json").read_text())
    card["scenario"]["state_names"].append("extra")
    (path / "card.json").write_text(json.dumps(card))
    with pytest.raises(EstimatorError, match=r"with dx=3, dy=1, du=0, but the requested one has dx=2, dy=1, du=0"):
        load_neural_estimator("gru", oscillator, path)


def test_loading_names_missing_and_corrupt_files(oscillator, tmp_path):
    _, path, _ = _save(tmp_path, oscillator, "gru")
    blob = (path / "model.safetensors").read_bytes()
    (path / "model.safetensors").write_bytes(blob[:-7] + b"garbage")
    with pytest.raises(EstimatorError, match="model.safetensors does not match the sha256"):
        load_neural_estimator("gru", oscillator, path)
    card = json.loads((path / "card.json").read_text())
    del card["weights"]["sha256"]
    (path / "card.json").write_text(json.dumps(card))
    broken = b"\x08\x00\x00\x00\x00\x00\x00\x00{broken}"
    # far smaller than the card's model: refused by its size before anything is allocated or parsed
    (path / "model.safetensors").write_bytes(broken)
    with pytest.raises(EstimatorError, match="weight file holds 16 bytes: card and weights do not belong"):
        load_neural_estimator("gru", oscillator, path)
    # the model's size but not a safetensors file: the parser's refusal, named
    (path / "model.safetensors").write_bytes(broken + bytes(len(blob)))
    with pytest.raises(EstimatorError, match="cannot read model.safetensors"):
        load_neural_estimator("gru", oscillator, path)
    (path / "model.safetensors").unlink()
    with pytest.raises(EstimatorError, match="weight file model.safetensors is missing"):
        load_neural_estimator("gru", oscillator, path)
    (path / "card.json").write_text('{"format": "neural_estimator.checkpoint", ')
    with pytest.raises(EstimatorError, match=r"card.json: checkpoint card is corrupt \(not valid JSON"):
        load_neural_estimator("gru", oscillator, path)
    (path / "card.json").unlink()
    with pytest.raises(EstimatorError, match="card.json: checkpoint card is missing"):
        load_neural_estimator("gru", oscillator, path)
    with pytest.raises(EstimatorError, match="does not exist"):
        load_neural_estimator("gru", oscillator, tmp_path / "nowhere")
    with pytest.raises(
        EstimatorError,
        match=r"no trained gru model ships for scenario 'oscillator'.*lacks card.json "
        r"and model.safetensors.*neural-estimator train --scenario oscillator "
        r"--model gru --out",
    ):
        make_estimator("gru", oscillator)
