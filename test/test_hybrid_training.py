"""The hybrid's training (neural_estimator/training/hybrid.py): TBPTT over whole trajectories from the
prior, the state and the observation-only losses, resume, the card, the command line. Tiny recipes:
the plumbing and the arithmetic, not accuracy."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from neural_estimator.cli import main
from neural_estimator.data.simulate import simulate
from neural_estimator.models import build_model
from neural_estimator.scenarios import make_scenario
from neural_estimator.serving.checkpoint import load_checkpoint
from neural_estimator.serving.normalization import Normalizer
from neural_estimator.training.loop import train
from neural_estimator.training.recipe import TrainConfig, TrainingError

TINY = dict(
    trajectories=12,
    val_trajectories=6,
    train_length=30,
    window=10,
    warmup=3,
    batch_size=6,
    eval_trajectories=0,
)


def tiny(tmp_path, **changes) -> TrainConfig:
    return TrainConfig(**{**TINY, "cache_dir": str(tmp_path / "cache"), **changes})


def card_of(path) -> dict:
    return json.loads((path / "card.json").read_text())


def test_chunks_with_the_state_carried_equal_one_rollout():
    """TBPTT's forward pass: chunks of the window with the state carried are the whole trajectory
    run once (the training sees the filter it serves), and a chunk started afresh is not."""
    scen = make_scenario("lorenz96")
    data = simulate(scen, 4, 30, seed=1)
    model = build_model("kalmannet", scen)
    model.set_normalization(Normalizer.from_data(scen, data))
    model.eval()
    z = torch.as_tensor(Normalizer.from_data(scen, data).normalize_inputs(data.y, data.u * 0)[0], dtype=torch.float32)
    with torch.no_grad():
        whole = model(z)
        state, parts = model.init_state(4), []
        for t0 in range(0, 30, 10):
            x, _, state = model.rollout(z[:, t0 : t0 + 10], tuple(s.detach() for s in state))
            parts.append(x)
        fresh = model(z[:, 10:20])
    torch.testing.assert_close(torch.cat(parts, dim=1), whole)
    assert not torch.allclose(fresh, whole[:, 10:20])


def test_state_training_runs_and_the_card_says_so(tmp_path):
    out = train("lorenz96", "kalmannet", tmp_path / "m", tiny(tmp_path, epochs=2), progress=False)
    card = card_of(out)
    t = card["training"]
    assert t["supervision"] == "states" and "supervision" not in t["recipe"]  # the default, as older cards
    assert t["tbptt"] == {"chunk": 10, "chunks_per_trajectory": 3}
    assert card["data"]["windows_per_epoch"] == 12 * 3 and t["steps_per_epoch"] == 2
    assert len(t["history"]) == 2 and all(np.isfinite(h["val_loss"]) for h in t["history"])
    model, norm, _ = load_checkpoint(out, "cpu", make_scenario("lorenz96"))
    np.testing.assert_allclose(model.out_std.numpy(), norm.out_std, rtol=1e-6)  # the statistics travel with it


def test_observation_training_reads_no_state_label(tmp_path):
    """Every state of the training and validation sets NaN: the observation-only run trains and
    validates to finite losses (a state loss would be NaN at its first step)."""
    scen = make_scenario("lorenz96")
    train_set, val_set = simulate(scen, 12, 30, seed=2), simulate(scen, 6, 30, seed=3)
    blind = [dataclasses.replace(d, x=np.full_like(d.x, np.nan)) for d in (train_set, val_set)]
    cfg = tiny(tmp_path, epochs=2, supervision="observations")
    out = train(scen, "kalmannet", tmp_path / "obs", cfg, progress=False, data=tuple(blind))
    t = card_of(out)["training"]
    assert t["supervision"] == "observations" and t["recipe"]["supervision"] == "observations"
    assert all(np.isfinite(h["train_loss"]) and np.isfinite(h["val_loss"]) for h in t["history"])
    from neural_estimator.serving.normalization import NormalizationError

    with pytest.raises(NormalizationError, match="NaN"):  # the same sets trained on states: refused
        train(scen, "kalmannet", tmp_path / "st", tiny(tmp_path, epochs=1), progress=False, data=tuple(blind))


def test_an_interrupted_run_resumed_gives_the_uninterrupted_weights(tmp_path):
    straight = train("quadrotor", "kalmannet", tmp_path / "a", tiny(tmp_path, epochs=2), progress=False)
    train("quadrotor", "kalmannet", tmp_path / "b", tiny(tmp_path, epochs=1), progress=False)
    resumed = train("quadrotor", "kalmannet", tmp_path / "b", tiny(tmp_path, epochs=2, resume=True), progress=False)
    from safetensors.torch import load_file

    a, b = load_file(straight / "resume" / "model.safetensors"), load_file(resumed / "resume" / "model.safetensors")
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_a_network_cannot_train_on_observations(tmp_path):
    with pytest.raises(TrainingError, match="trains a hybrid"):
        train("lorenz96", "gru", tmp_path / "g", tiny(tmp_path, supervision="observations"), progress=False)
    with pytest.raises(TrainingError, match="supervision must be one of"):
        tiny(tmp_path, supervision="labels")


def test_train_command_line_supervision(tmp_path, capsys):
    args = ["train", "--scenario", "quadrotor", "--model", "kalmannet", "--out", str(tmp_path / "q"), "--quiet"]
    args += ["--trajectories", "8", "--val-trajectories", "4", "--train-length", "20", "--window", "10"]
    args += ["--warmup", "2", "--batch-size", "4", "--epochs", "1", "--eval-trajectories", "0"]
    args += ["--cache-dir", str(tmp_path / "cache")]
    assert main(args + ["--supervision", "observations"]) == 0
    assert card_of(tmp_path / "q")["training"]["supervision"] == "observations"
    assert main(args[:4] + ["gru"] + args[5:] + ["--supervision", "observations"]) == 2
    assert "trains a hybrid" in capsys.readouterr().err


def test_a_hybrid_trains_with_the_model_set_it_is_given(tmp_path):
    """``model_set``: the data come from the true system (forcing 8), the hybrid's f is the team's
    wrong one (forcing 9), during training, in the card metrics and when its checkpoint is loaded."""
    cfg = tiny(tmp_path, epochs=1, model_set={"forcing": "9"}, eval_trajectories=3)
    out = train("lorenz96", "kalmannet", tmp_path / "wrong", cfg, progress=False)
    card = card_of(out)
    assert card["training"]["recipe"]["model_set"] == {"forcing": "9"}
    assert card["scenario"]["config"]["forcing"] == 8.0  # the data's constants
    model, _, _ = load_checkpoint(out)  # standalone: the card's model set applies
    assert model.dynamics.config.forcing == 9.0
    exact = train("lorenz96", "kalmannet", tmp_path / "exact", tiny(tmp_path, epochs=1), progress=False)
    assert "model_set" not in card_of(exact)["training"]["recipe"]  # as every recipe before the field
    assert load_checkpoint(exact)[0].dynamics.config.forcing == 8.0


def test_a_model_set_is_for_hybrids_and_names_constants(tmp_path, capsys):
    with pytest.raises(TrainingError, match="gru reads no model"):
        train("lorenz96", "gru", tmp_path / "g", tiny(tmp_path, model_set={"forcing": "9"}), progress=False)
    args = ["train", "--scenario", "lorenz96", "--model", "kalmannet", "--out", str(tmp_path / "q"), "--quiet"]
    for flags, words in (
        (["--model-set", "prior_gain=0"], "an architecture hyperparameter; give it as --arch-set prior_gain=VALUE"),
        (["--model-set", "forcin=9"], "no constant 'forcin'"),
        (["--model-set", "forcing"], "expects NAME=VALUE"),
    ):
        assert main(args + flags) == 2
        err = capsys.readouterr().err.strip()
        assert words in err and "\n" not in err
    assert main(args[:4] + ["gru"] + args[5:] + ["--model-set", "forcing=9"]) == 2
    assert "gru reads no model" in capsys.readouterr().err
