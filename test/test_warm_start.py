"""Warm start (``TrainConfig.init_from``, ``train --init-from``, ``train_zoo.py --fine-tune``): a run
that begins from a trained checkpoint's weights, recorded in its card, refused for another
architecture or configuration."""

from __future__ import annotations

import json

import pytest

from neural_estimator.training.loop import train
from neural_estimator.training.recipe import TrainingError
from conftest import load_script
from training_cases import tiny_config, weights

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tiny tensors: one intra-op thread


def _card(directory):
    return json.loads((directory / "card.json").read_text())


def test_a_warm_start_begins_where_its_checkpoint_ended_and_its_card_says_so(tmp_path):
    """With a learning rate too small to move the weights, the first epoch's validation loss of a run
    started from checkpoint A is A's own (same data, same validation set), where a fresh start's is not."""
    cache = tmp_path / "cache"
    a = train("test_spinner", "gru", tmp_path / "a", tiny_config(cache, epochs=2), progress=False)
    still = dict(lr=1e-12, weight_decay=0.0, epochs=1)
    warm = train("test_spinner", "gru", tmp_path / "b", tiny_config(cache, init_from=str(a), **still), progress=False)
    cold = train("test_spinner", "gru", tmp_path / "c", tiny_config(cache, init_from=None, **still), progress=False)
    first_warm = _card(warm)["training"]["history"][0]["val_loss"]
    first_cold = _card(cold)["training"]["history"][0]["val_loss"]
    assert first_warm == pytest.approx(_card(a)["validation_loss"], rel=1e-4)
    assert abs(first_cold - first_warm) > 1e-3 * first_warm  # a fresh initialisation does not start there
    record = _card(warm)["training"]["init_from"]
    assert record["checkpoint"] == str(a) and record["sha256"] == _card(a)["weights"]["sha256"]
    assert record["same_normalization"] is True and record["validation_loss"] == _card(a)["validation_loss"]
    assert _card(warm)["training"]["recipe"]["init_from"] == str(a)
    assert "init_from" not in _card(cold)["training"] and "init_from" not in _card(cold)["training"]["recipe"]


def test_a_warm_start_refuses_another_architecture_or_configuration(tmp_path):
    cache = tmp_path / "cache"
    a = train("test_spinner", "gru", tmp_path / "a", tiny_config(cache, epochs=1), progress=False)
    wider = tiny_config(cache, init_from=str(a), model_overrides={"hidden": 16})
    with pytest.raises(TrainingError, match=r"configured otherwise than this run's \(hidden\)"):
        train("test_spinner", "gru", tmp_path / "b", wider, progress=False)
    with pytest.raises(TrainingError, match="a gru checkpoint cannot start a lstm training"):
        train("test_spinner", "lstm", tmp_path / "c", tiny_config(cache, init_from=str(a)), progress=False)
    with pytest.raises(TrainingError, match="init_from: .*card"):
        train("test_spinner", "gru", tmp_path / "d", tiny_config(cache, init_from=str(tmp_path)), progress=False)


def test_train_zoo_fine_tune_starts_from_the_shipped_weights_and_installs_only_a_better_model(
    tmp_path, monkeypatch, capsys
):
    monkeypatch.setenv("NEURAL_ESTIMATOR_CACHE", str(tmp_path / "cache"))
    zoo_script = load_script("scripts/train_zoo.py")
    zoo = tmp_path / "zoo"
    args = ["--scenarios", "test_spinner", "--methods", "gru", "--zoo", str(zoo), "--trajectories", "12"]
    args += ["--windows-per-epoch", "48", "--val-trajectories", "6", "--eval-trajectories", "4", "--quiet"]
    fine = [*args, "--fine-tune", "--state", str(tmp_path / "state")]
    assert zoo_script.main([*fine, "--max-epochs", "1"]) == 0  # nothing shipped yet: nothing to start from
    assert "the zoo ships no model of these constants to fine-tune" in capsys.readouterr().out
    assert zoo_script.main([*args, "--max-epochs", "1", "--state", str(tmp_path / "s0")]) == 0
    shipped = zoo / "test_spinner-gru"
    before = weights(shipped)
    assert zoo_script.main([*fine, "--max-epochs", "3", "--lr", "1e-3"]) == 0
    card = _card(tmp_path / "state" / "test_spinner-gru")  # --state given: the fine-tunes' state itself
    assert card["training"]["init_from"]["checkpoint"] == str(shipped)
    assert card["training"]["recipe"]["lr"] == 1e-3
    out = capsys.readouterr().out
    after = weights(shipped)
    installed = any(not (before[k] == after[k]).all() for k in before)
    assert installed == ("installed " in out) and installed != (
        "not installed" in out
    )  # replaced only where it scored lower on the selection set
    with pytest.raises(SystemExit):
        zoo_script.main([*fine, "--instance", "1"])
    with pytest.raises(SystemExit):
        zoo_script.main([*fine, "--lr", "0"])


def test_train_command_line_init_from(tmp_path, capsys):
    """``train --init-from DIR``: the run starts from DIR's weights (its card says so); a directory
    that holds no checkpoint is one line on stderr and exit status 2."""
    from neural_estimator.cli import main

    args = ["train", "--scenario", "lorenz96", "--model", "gru", "--quiet", "--arch-set", "hidden=8"]
    args += ["--trajectories", "8", "--val-trajectories", "4", "--train-length", "20", "--window", "10"]
    args += ["--warmup", "2", "--batch-size", "4", "--epochs", "1", "--eval-trajectories", "0"]
    args += ["--cache-dir", str(tmp_path / "cache")]
    assert main([*args, "--out", str(tmp_path / "a")]) == 0
    assert main([*args, "--out", str(tmp_path / "b"), "--init-from", str(tmp_path / "a")]) == 0
    assert _card(tmp_path / "b")["training"]["init_from"]["sha256"] == _card(tmp_path / "a")["weights"]["sha256"]
    capsys.readouterr()
    assert main([*args, "--out", str(tmp_path / "c"), "--init-from", str(tmp_path / "nothing")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "init_from" in err[0], err
