"""The zoo script (scripts/train_zoo.py): resumable across runs, cards with budget and convergence, what it
installs, keeps and prunes, and the shipped models' bar.
"""

import json
import shutil

import pytest
import torch

from neural_estimator.training.loop import train
from neural_estimator.training.recipe import TrainConfig
from neural_estimator.scenarios import make_scenario
from conftest import load_script
from training_cases import (
    weights,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tiny tensors: one intra-op thread


# ---- the zoo script: resumable across runs, cards with budget and convergence ---------------------
def _train_zoo():
    return load_script("scripts/train_zoo.py")


@pytest.mark.slow
def test_train_zoo_resumes_unfinished_models_and_installs_finished_ones(tmp_path, monkeypatch):
    import time
    from types import SimpleNamespace

    import neural_estimator.training.loop as training

    monkeypatch.setenv("NEURAL_ESTIMATOR_CACHE", str(tmp_path / "cache"))
    zoo_script = _train_zoo()
    state, zoo = tmp_path / "state", tmp_path / "zoo"
    args = [
        "--scenarios",
        "test_spinner",
        "--methods",
        "gru",
        "--state",
        str(state),
        "--zoo",
        str(zoo),
        "--trajectories",
        "12",
        "--windows-per-epoch",
        "48",
        "--val-trajectories",
        "6",
        "--eval-trajectories",
        "4",
        "--max-epochs",
        "3",
        "--hours",
        "1",
        "--quiet",
    ]
    work = state / "test_spinner-gru"
    # first run: the session's time runs out after two epochs (train() reads the clock before each epoch)
    checks = iter([0.0, 0.0])  # read before each epoch: two epochs start, the third does not
    clock = SimpleNamespace(time=lambda: next(checks, 1e12), perf_counter=time.perf_counter)
    monkeypatch.setattr(training, "time", clock)
    monkeypatch.setattr(zoo_script.time, "time", lambda: 0.0)
    assert zoo_script.main(args) == 0
    run = zoo_script.resume_state(work)
    assert run["epoch"] == 2 and not zoo_script.finished(work) and not (zoo / work.name).exists()
    # the next run resumes from epoch 2 and finishes the epoch budget
    monkeypatch.undo()
    monkeypatch.setenv("NEURAL_ESTIMATOR_CACHE", str(tmp_path / "cache"))
    assert zoo_script.main(args) == 0
    card = json.loads((zoo / work.name / "card.json").read_text())
    t = card["training"]
    assert [h["epoch"] for h in t["history"]] == [1, 2, 3] and t["stopped"] == "max epochs"
    assert t["budget"]["max_epochs"] == 3 and t["budget"]["windows_per_epoch"] == 48
    assert t["converged"] is False and t["lr_reductions"] == 0
    assert card["metrics"]["set"]["trajectories"] == 4
    assert sorted(p.name for p in (zoo / work.name).iterdir()) == ["card.json", "model.safetensors", "step.onnx"]
    assert zoo_script.finished(work)
    # the resumed run equals an uninterrupted one
    ref = train(
        "test_spinner",
        "gru",
        tmp_path / "ref",
        TrainConfig(
            trajectories=12,
            windows_per_epoch=48,
            val_trajectories=6,
            epochs=3,
            eval_trajectories=4,
            cache_dir=str(tmp_path / "cache"),
        ),
        progress=False,
    )
    w_ref, w_zoo = weights(ref), weights(zoo / work.name)
    assert all(torch.equal(w_ref[k], w_zoo[k]) for k in w_ref)


def test_train_zoo_finish_installs_an_unfinished_model_as_it_stands(tmp_path, monkeypatch):
    import time
    from types import SimpleNamespace

    import neural_estimator.training.loop as training

    monkeypatch.setenv("NEURAL_ESTIMATOR_CACHE", str(tmp_path / "cache"))
    zoo_script = _train_zoo()
    state, zoo = tmp_path / "state", tmp_path / "zoo"
    args = ["--scenarios", "test_spinner", "--methods", "gru", "--state", str(state), "--zoo", str(zoo)]
    args += ["--trajectories", "12", "--windows-per-epoch", "48", "--val-trajectories", "6"]
    args += ["--eval-trajectories", "4", "--max-epochs", "50", "--quiet"]
    work = state / "test_spinner-gru"
    assert zoo_script.main([*args, "--finish"]) == 0  # not started: nothing to finish, nothing installed
    assert not work.exists() and not zoo.exists()
    checks = iter([0.0])  # one epoch starts, then the session's time is up
    monkeypatch.setattr(
        training, "time", SimpleNamespace(time=lambda: next(checks, 1e12), perf_counter=time.perf_counter)
    )
    monkeypatch.setattr(zoo_script.time, "time", lambda: 0.0)
    assert zoo_script.main([*args, "--hours", "1"]) == 0
    monkeypatch.undo()
    monkeypatch.setenv("NEURAL_ESTIMATOR_CACHE", str(tmp_path / "cache"))
    assert zoo_script.resume_state(work)["epoch"] == 1 and not zoo_script.finished(work)
    assert zoo_script.main([*args, "--finish"]) == 0
    card = json.loads((zoo / work.name / "card.json").read_text())
    t = card["training"]
    assert len(t["history"]) == 1 and t["stopped"].startswith("finished by hand (--finish) after 1 epochs")
    assert t["budget"]["max_epochs"] == 50 and card["metrics"]["set"]["trajectories"] == 4
    assert zoo_script.finished(work)


def test_train_zoo_does_not_install_a_model_that_never_beat_its_first_epoch(tmp_path):
    zoo_script = _train_zoo()
    work = tmp_path / "s-m"
    work.mkdir()
    card = {"validation_loss": 0.5, "training": {"history": [{"val_loss": 0.5}, {"val_loss": 0.7}]}}
    (work / "card.json").write_text(json.dumps(card))
    assert "never went below its first epoch" in zoo_script.not_installable(work)
    card["validation_loss"] = 0.4
    card["training"]["history"].append({"val_loss": 0.4})
    (work / "card.json").write_text(json.dumps(card))
    assert zoo_script.not_installable(work) is None
    card = {"validation_loss": 0.5, "training": {"history": [{"val_loss": 0.5}]}}  # --finish after one epoch
    (work / "card.json").write_text(json.dumps(card))
    assert zoo_script.not_installable(work) is None


def test_train_zoo_prune_never_removes_the_weights_of_a_zoo_kept_inside_the_state(tmp_path, capsys):
    """``--prune --state S --zoo S/zoo``: the zoo's own folders carry cards too, and comparing one
    with itself must not count as "the zoo ships the same weights"."""
    zoo_script = _train_zoo()
    state, zoo = tmp_path / "v5", tmp_path / "v5" / "zoo"
    finished_card = json.dumps({"training": {"stopped": "plateau"}})
    for folder in (state / "s-m", zoo / "s-m"):
        folder.mkdir(parents=True)
        (folder / "card.json").write_text(finished_card)
        (folder / "model.safetensors").write_bytes(b"same weights")
    (state / "s-m" / "resume").mkdir()
    assert zoo_script.main(["--prune", "--state", str(state), "--zoo", str(zoo)]) == 0
    assert (zoo / "s-m" / "model.safetensors").read_bytes() == b"same weights"  # the shipped copy stays
    assert sorted(f.name for f in (state / "s-m").iterdir()) == ["card.json"]  # the training's copy goes
    assert "zoo/s-m: nothing to remove" in capsys.readouterr().out


@pytest.mark.slow
def test_train_zoo_keeps_the_shipped_model_unless_the_new_one_scores_lower_on_the_same_set(
    tmp_path, monkeypatch, capsys
):
    monkeypatch.setenv("NEURAL_ESTIMATOR_CACHE", str(tmp_path / "cache"))
    zoo_script = _train_zoo()
    zoo = tmp_path / "zoo"
    args = ["--scenarios", "test_spinner", "--methods", "gru", "--zoo", str(zoo)]
    args += ["--trajectories", "12", "--windows-per-epoch", "48", "--val-trajectories", "6"]
    args += ["--eval-trajectories", "4", "--max-epochs", "2", "--quiet"]
    assert zoo_script.main([*args, "--state", str(tmp_path / "a")]) == 0
    shipped = zoo / "test_spinner-gru"
    first = json.loads((shipped / "card.json").read_text())
    stamp = (shipped / "card.json").stat().st_mtime_ns  # install copies the card with its mtime
    # the installed model is the finished one; the training keeps only its card (history and recipe)
    work = tmp_path / "a" / "test_spinner-gru"
    assert first == json.loads((work / "card.json").read_text())
    assert sorted(f.name for f in work.iterdir()) == ["card.json"]  # resume state and shipped weights pruned
    assert first["training"]["history"] and first["training"]["recipe"]
    capsys.readouterr()
    assert zoo_script.main([*args, "--state", str(tmp_path / "a"), "--install"]) == 0
    assert "its weights were pruned: the zoo ships it" in capsys.readouterr().out
    # with a model of these constants shipped, a plain run in a fresh state starts nothing
    assert zoo_script.main([*args, "--state", str(tmp_path / "b")]) == 0
    assert "the zoo ships a model of these constants, nothing to retrain" in capsys.readouterr().out
    assert not (tmp_path / "b" / "test_spinner-gru").exists()
    # the same recipe again trains the same model: not lower, so the shipped one stays
    assert zoo_script.main([*args, "--state", str(tmp_path / "b"), "--retrain"]) == 0
    out = capsys.readouterr().out
    assert "is not below the shipped model's" in out and "selection set: validation set 100" in out
    # not installed: the training keeps no resume state (its weights only where they differ from the shipped ones)
    kept = {f.name for f in (tmp_path / "b" / "test_spinner-gru").iterdir()}
    assert "card.json" in kept and "resume" not in kept and kept <= {"card.json", "model.safetensors"}
    # the selection set (validation data) is not the card's evaluation set
    assert zoo_script.selection_rmse(shipped, make_scenario("test_spinner"), 4) != first["metrics"]["rmse"]
    assert (shipped / "card.json").stat().st_mtime_ns == stamp
    # --no-compare installs it regardless
    assert zoo_script.main([*args, "--state", str(tmp_path / "c"), "--no-compare", "--retrain"]) == 0
    assert "installed" in capsys.readouterr().out
    assert (shipped / "card.json").stat().st_mtime_ns != stamp


@pytest.mark.slow
def test_train_zoo_val_context_trains_a_variant_that_replaces_no_shipped_model_until_installed(
    tmp_path, monkeypatch, capsys
):
    monkeypatch.setenv("NEURAL_ESTIMATOR_CACHE", str(tmp_path / "cache"))
    zoo_script = _train_zoo()
    monkeypatch.setattr(zoo_script, "ZOO", tmp_path / "zoo")  # the default zoo, were it used
    args = ["--scenarios", "test_spinner", "--methods", "gru", "--state", str(tmp_path / "s")]
    args += ["--trajectories", "12", "--windows-per-epoch", "48", "--val-trajectories", "6"]
    args += ["--eval-trajectories", "4", "--max-epochs", "1", "--quiet", "--val-context", "10"]
    assert zoo_script.main(args) == 0
    assert "not installed without --zoo" in capsys.readouterr().out and not (tmp_path / "zoo").exists()
    card = json.loads((tmp_path / "s" / "test_spinner-gru" / "card.json").read_text())
    assert card["training"]["recipe"]["val_context"] == 10 and card["metrics"]["set"]["context"] == 10
    # --install puts the finished variant into the shipped zoo without training it again
    stamp = (tmp_path / "s" / "test_spinner-gru" / "card.json").stat().st_mtime_ns
    assert zoo_script.main([*args, "--install"]) == 0
    assert "installed" in capsys.readouterr().out
    shipped = json.loads((tmp_path / "zoo" / "test_spinner-gru" / "card.json").read_text())
    assert shipped == card and (tmp_path / "s" / "test_spinner-gru" / "card.json").stat().st_mtime_ns == stamp
    # installed again, the same model does not score lower than itself: the shipped one stays
    assert zoo_script.main([*args, "--install"]) == 0
    assert "is not below the shipped model's" in capsys.readouterr().out
    # a model that has not finished (here: never started) is not installed
    lstm = ["--state", str(tmp_path / "s"), "--scenarios", "test_spinner", "--methods", "lstm"]
    assert zoo_script.main([*lstm, "--val-context", "10", "--install", "--quiet"]) == 0
    assert "not finished, nothing to install" in capsys.readouterr().out


def test_train_zoo_not_better_compares_rmse_only_when_both_exist():
    zoo_script = _train_zoo()
    assert zoo_script.not_better(0.5, None) is None  # nothing comparable ships
    assert zoo_script.not_better(0.5, 0.6) is None
    assert "0.5 is not below the shipped model's 0.4" in zoo_script.not_better(0.5, 0.4)
    assert "not below" in zoo_script.not_better(0.5, 0.5)  # a tie keeps the shipped model


@pytest.mark.slow
def test_train_zoo_finishes_a_model_on_the_plateau_rule(tmp_path, monkeypatch):
    monkeypatch.setenv("NEURAL_ESTIMATOR_CACHE", str(tmp_path / "cache"))
    zoo_script = _train_zoo()
    calls = []

    def fake_rule(initial_lr, epochs, tol):
        calls.append((initial_lr, epochs, tol))
        return lambda history: "plateau (test)" if len(history) == 2 else None

    monkeypatch.setattr(zoo_script, "plateau_rule", fake_rule)
    state, zoo = tmp_path / "state", tmp_path / "zoo"
    args = ["--scenarios", "test_spinner", "--methods", "gru", "--state", str(state), "--zoo", str(zoo)]
    args += ["--trajectories", "12", "--windows-per-epoch", "48", "--val-trajectories", "6"]
    args += ["--eval-trajectories", "4", "--max-epochs", "6", "--quiet"]
    assert zoo_script.main(args) == 0
    assert calls == [(2e-3, 10, 0.01)]  # the defaults: 10 epochs, 1 %
    t = json.loads((zoo / "test_spinner-gru" / "card.json").read_text())["training"]
    assert t["stopped"] == "plateau (test)" and t["epochs_run"] == 2
    assert zoo_script.finished(state / "test_spinner-gru")
    # --plateau-epochs 0: no rule at all
    calls.clear()
    assert (
        zoo_script.main(
            [
                *args,
                "--scenarios",
                "test_spinner",
                "--state",
                str(tmp_path / "s2"),
                "--plateau-epochs",
                "0",
                "--retrain",
            ]
        )
        == 0
    )
    assert calls == []
    t = json.loads((zoo / "test_spinner-gru" / "card.json").read_text())["training"]
    assert t["stopped"] == "max epochs" and t["epochs_run"] == 6


def test_every_shipped_model_is_full_recipe_and_converged_by_its_own_curve():
    """The zoo's bar: every shipped model had the paper's budget (20,000 windows per epoch), its card's
    "converged" follows from its own history (early stopping: patience epochs after the best one, none
    lower; or >= 3 learning-rate reductions), and every network (the paper's rows) converged. A
    hybrid, beyond the paper, ships as far as its stated budget took it: unconverged only where its
    card says a wall budget or a hand finish stopped it (docs/methods.md lists them)."""
    from pathlib import Path

    from neural_estimator.methods import table
    from neural_estimator.training.stopping import converged, lr_reductions

    zoo = Path(__file__).resolve().parents[1] / "neural_estimator" / "serving" / "zoo"
    cards = sorted(zoo.glob("*/card.json"))
    for path in cards:
        card = json.loads(path.read_text())
        t = card["training"]
        for key in ("converged", "budget", "lr_reductions", "convergence_rule", "history", "stopped"):
            assert key in t, f"{path}: training.{key} missing"
        hist, lr0 = t["history"], t["recipe"]["lr"]
        assert t["lr_reductions"] == lr_reductions(hist, lr0), path
        if t["stopped"].startswith("early stopping"):  # the curve must show it
            patience = t["recipe"]["patience"]
            best = min(range(len(hist)), key=lambda i: hist[i]["val_loss"])
            assert len(hist) - 1 - best >= patience, f"{path}: early stopping without {patience} epochs after the best"
        assert t["converged"] == converged(t["stopped"], hist, lr0), path
        assert t["budget"]["windows_per_epoch"] >= 20000, f"{path}: not the paper's 20,000 windows per epoch"
        if table.has(card["method"], family="hybrid") and not t["converged"]:
            assert t["stopped"].startswith(("wall budget", "finished by hand")), f"{path}: {t['stopped']}"
            continue
        assert t["converged"], f"{path}: shipped before it converged"
    networks = [c for c in cards if table.has(c.parent.name.rsplit("-", 1)[1], family="neural")]
    assert len(networks) == 30  # five scenarios x six networks (the hybrids ship as they finish training)


def test_train_zoo_finishes_a_model_whose_wall_budget_is_spent(tmp_path, monkeypatch):
    monkeypatch.setenv("NEURAL_ESTIMATOR_CACHE", str(tmp_path / "cache"))
    zoo_script = _train_zoo()
    state, zoo = tmp_path / "state", tmp_path / "zoo"
    args = [
        "--scenarios",
        "test_spinner",
        "--methods",
        "gru",
        "--state",
        str(state),
        "--zoo",
        str(zoo),
        "--trajectories",
        "12",
        "--windows-per-epoch",
        "48",
        "--val-trajectories",
        "6",
        "--eval-trajectories",
        "4",
        "--quiet",
    ]
    real_prune = zoo_script.prune
    monkeypatch.setattr(zoo_script, "prune", lambda work, zoo=None: [])  # keep the resume state this once
    assert zoo_script.main(args + ["--max-epochs", "1"]) == 0  # one epoch, finished on its epoch budget
    monkeypatch.setattr(zoo_script, "prune", real_prune)
    work = state / "test_spinner-gru"
    shutil.rmtree(zoo / work.name)
    card = json.loads((work / "card.json").read_text())
    card["training"]["stopped"] = "in progress"  # as if that run had been cut off after its first epoch
    (work / "card.json").write_text(json.dumps(card))
    assert zoo_script.main(args + ["--max-epochs", "5", "--model-hours", "1e-9"]) == 0
    t = json.loads((zoo / work.name / "card.json").read_text())["training"]
    assert t["stopped"] == "wall budget spent (1e-09 h)" and t["epochs_run"] == 1
    assert t["budget"]["max_epochs"] == 5 and t["converged"] is False


def test_train_zoo_leaves_a_pair_that_another_process_holds_and_takes_it_once_released(tmp_path, monkeypatch, capsys):
    """Two train_zoo.py processes on one queue: a pair whose lock another process holds is skipped
    (nothing trained, nothing written but the lock file); once that process is gone (killed: the
    kernel drops its lock) the pair trains."""
    import subprocess
    import sys

    monkeypatch.setenv("NEURAL_ESTIMATOR_CACHE", str(tmp_path / "cache"))
    zoo_script = _train_zoo()
    state, zoo = tmp_path / "state", tmp_path / "zoo"
    work = state / "test_spinner-gru"
    work.mkdir(parents=True)
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import fcntl, sys, time\n"
            f"h = open({str(work / zoo_script.LOCK_NAME)!r}, 'a+')\n"
            "fcntl.flock(h, fcntl.LOCK_EX)\nprint('held', flush=True)\ntime.sleep(120)\n",
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    args = ["--scenarios", "test_spinner", "--methods", "gru", "--state", str(state), "--zoo", str(zoo)]
    args += ["--trajectories", "12", "--windows-per-epoch", "48", "--val-trajectories", "6"]
    args += ["--eval-trajectories", "4", "--max-epochs", "1", "--quiet"]
    try:
        assert holder.stdout.readline().strip() == "held"
        with zoo_script.claimed(work) as mine:
            assert mine is False
        assert zoo_script.main(args) == 0
        assert "test_spinner-gru: another train_zoo.py process is training it, skipped" in capsys.readouterr().out
        assert sorted(p.name for p in work.iterdir()) == [zoo_script.LOCK_NAME] and not zoo.exists()
    finally:
        holder.kill()
        holder.wait()
    assert zoo_script.main(args) == 0
    assert zoo_script.finished(work) and (zoo / work.name / "model.safetensors").is_file()
    with zoo_script.claimed(work) as mine:  # released at the end of the training
        assert mine is True


def test_train_zoo_fallback_context_trains_the_bounded_variant_of_a_model_the_zoo_did_not_take(
    tmp_path, monkeypatch, capsys
):
    """--fallback-context N: a finished full-recipe model the zoo does not take (here: its validation
    "never beat its first epoch") is followed by its bounded-context variant, trained in
    STATE/context<N>/ and installed; a second run finds both finished and trains nothing."""
    monkeypatch.setenv("NEURAL_ESTIMATOR_CACHE", str(tmp_path / "cache"))
    zoo_script = _train_zoo()
    real = zoo_script.not_installable
    # the full-recipe run is refused as a model whose best epoch was its first; the variant is judged as usual
    refused = "its validation loss never went below its first epoch's"
    monkeypatch.setattr(zoo_script, "not_installable", lambda w: refused if "context" not in str(w) else real(w))
    state, zoo = tmp_path / "s", tmp_path / "zoo"
    args = ["--scenarios", "test_spinner", "--methods", "gru", "--state", str(state), "--zoo", str(zoo)]
    args += ["--trajectories", "12", "--windows-per-epoch", "48", "--val-trajectories", "6"]
    args += ["--eval-trajectories", "4", "--max-epochs", "2", "--quiet", "--fallback-context", "10"]
    assert zoo_script.main(args) == 0
    out = capsys.readouterr().out
    assert "test_spinner-gru: not installed: its validation loss never went below" in out
    assert "test_spinner-gru: not in the zoo; training its bounded-context variant (context 10)" in out
    full, variant = state / "test_spinner-gru", state / "context10" / "test_spinner-gru"
    assert zoo_script.finished(full) and (full / "model.safetensors").is_file()  # kept: not shipped
    shipped = json.loads((zoo / "test_spinner-gru" / "card.json").read_text())
    assert shipped["training"]["recipe"]["val_context"] == 10 == shipped["metrics"]["set"]["context"]
    assert shipped == json.loads((variant / "card.json").read_text())
    # resumable and idempotent: nothing left to train
    assert zoo_script.main(args) == 0
    out = capsys.readouterr().out
    assert "training its bounded-context variant" not in out and "installed" not in out
    # the flag follows a full-recipe run only
    with pytest.raises(SystemExit):
        zoo_script.main([*args, "--val-context", "10"])


def test_train_zoo_instance_trains_on_its_own_data_set_and_seed_and_is_kept_beside_the_shipped_model(
    tmp_path, monkeypatch, capsys
):
    """--instance K: training set K and initialisation K (the card says so), its own state and zoo
    folders, installed with no comparison against the shipped model (every instance is kept)."""
    monkeypatch.setenv("NEURAL_ESTIMATOR_CACHE", str(tmp_path / "cache"))
    zoo_script = _train_zoo()
    assert zoo_script.instance_seeds(0) == {"data_index": 0, "init_seed": 0}  # the shipped model's recipe
    assert zoo_script.instance_paths(2, None, None) == (
        zoo_script.STATE / "instances" / "i2",
        zoo_script.ZOO / "instances" / "i2",
    )
    args = ["--scenarios", "test_spinner", "--methods", "gru", "--trajectories", "12"]
    args += ["--windows-per-epoch", "48", "--val-trajectories", "6", "--eval-trajectories", "4"]
    args += ["--max-epochs", "1", "--quiet"]
    zoo0, zoo1 = tmp_path / "zoo", tmp_path / "zoo-i1"
    assert zoo_script.main([*args, "--state", str(tmp_path / "s0"), "--zoo", str(zoo0)]) == 0
    assert zoo_script.main([*args, "--instance", "1", "--state", str(tmp_path / "s1"), "--zoo", str(zoo1)]) == 0
    assert "selection set" not in capsys.readouterr().out  # kept without a comparison
    c0 = json.loads((zoo0 / "test_spinner-gru" / "card.json").read_text())
    c1 = json.loads((zoo1 / "test_spinner-gru" / "card.json").read_text())
    assert (c0["data"]["index"], c0["init_seed"]) == (0, 0) and (c1["data"]["index"], c1["init_seed"]) == (1, 1)
    w0, w1 = weights(zoo0 / "test_spinner-gru"), weights(zoo1 / "test_spinner-gru")
    assert any(not torch.equal(w0[k], w1[k]) for k in w0)
    with pytest.raises(SystemExit):
        zoo_script.main([*args, "--instance", "1", "--val-context", "8"])
