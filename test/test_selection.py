"""Model selection sees validation data only: the trajectories that choose between models (early
stopping, the best epoch, train_zoo's install comparison) come from seed streams disjoint from
every evaluation set a table reports (evaluate, reproduce, the neural scoreboard)."""

import importlib.util
import json
from pathlib import Path
from types import SimpleNamespace


from neural_estimator.data import protocol
from neural_estimator.data.protocol import SELECTION_INDEX, seed_stream
from neural_estimator.scenarios import make_scenario

ROOT = Path(__file__).resolve().parents[1]

# Every evaluation seed a table here uses or a report quotes: the CLI's and reproduce's default (0),
# the fidelity measurement's (777), and a range around them.
EVAL_SEEDS = sorted({0, 1, 7, 11, 777, *range(0, 64)})
DATA_SEEDS = range(0, 64)  # training data seeds (the zoo's recipe: 0)


def _train_zoo():
    spec = importlib.util.spec_from_file_location("train_zoo", ROOT / "scripts" / "train_zoo.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_selection_and_validation_streams_are_disjoint_from_every_evaluation_stream():
    """No validation stream (a training's own, indices 0-2, or the selection set) equals any
    evaluation stream (sets 0-2 of every table seed): their generator states all differ."""
    eval_states = {
        tuple(seed_stream(s, "eval", j).generate_state(4)) for s in EVAL_SEEDS for j in range(protocol.EVALUATION_SETS)
    }
    val_states = {
        tuple(seed_stream(s, "val", j).generate_state(4)) for s in DATA_SEEDS for j in (0, 1, 2, SELECTION_INDEX)
    }
    assert len(eval_states) == len(EVAL_SEEDS) * protocol.EVALUATION_SETS  # no collision among them either
    assert eval_states.isdisjoint(val_states)


def test_the_selection_set_shares_no_trajectory_with_the_evaluation_sets():
    scenario = make_scenario("bearings")
    selection = protocol.dataset(scenario, "val", SELECTION_INDEX, 50, 3, 0, cache_dir=False)
    starts = {tuple(x) for x in selection.x[:, 0]}
    for s in (0, 777):
        for data in protocol.evaluation_sets(scenario, seed=s, trajectories=50, horizon=3, cache_dir=False):
            assert starts.isdisjoint(tuple(x) for x in data.x[:, 0])
    train_val = protocol.validation_set(scenario, trajectories=50, horizon=3, cache_dir=False)
    assert starts.isdisjoint(tuple(x) for x in train_val.x[:, 0])  # nor with the training's own


def _record_roles(monkeypatch):
    seen = []
    real = protocol.dataset

    def recording(scenario, role, index, *args, **kwargs):
        seen.append((role, index))
        return real(scenario, role, index, *args, **kwargs)

    monkeypatch.setattr(protocol, "dataset", recording)
    return seen


def test_tables_draw_evaluation_sets_only(monkeypatch):
    from neural_estimator.evaluation import evaluate

    seen = _record_roles(monkeypatch)
    evaluate(make_scenario("bearings"), ["ekf"], trajectories=3, horizon=12, sets=2, cache_dir=False, progress=False)
    assert seen and {role for role, _ in seen} == {"eval"}


def test_installing_compares_on_the_selection_set_only(tmp_path, monkeypatch, capsys):
    """train_zoo's comparison of a finished model with the shipped one scores both on validation set
    SELECTION_INDEX, never on an evaluation set."""
    zoo_script = _train_zoo()
    seen = []

    def recording(scenario, role, index, *args, **kwargs):
        seen.append((role, index))
        return protocol.dataset(scenario, role, index, *args, cache_dir=False)

    monkeypatch.setattr(zoo_script, "dataset", recording)
    scenario = make_scenario("lorenz96")
    shipped = ROOT / "neural_estimator" / "serving" / "zoo" / "lorenz96-gru"
    work, zoo = tmp_path / "state" / "lorenz96-gru", tmp_path / "zoo"
    for d in (work, zoo / "lorenz96-gru"):
        d.mkdir(parents=True)
        for f in ("card.json", "model.safetensors"):
            (d / f).write_bytes((shipped / f).read_bytes())
    monkeypatch.setattr(scenario.__class__, "horizon", property(lambda self: 20))  # a short selection set
    installed = zoo_script.install_if_better(work, zoo, scenario, trajectories=3)
    assert not installed  # the same model does not beat itself
    assert seen and set(seen) == {("val", SELECTION_INDEX)}
    assert f"validation set {SELECTION_INDEX}" in capsys.readouterr().out


def test_a_shipped_model_of_other_constants_is_not_compared(tmp_path, monkeypatch, capsys):
    """After a recalibration the shipped model (preset v3) cannot serve the new constants: the
    retrained model is installed without a comparison, which would not be possible."""
    zoo_script = _train_zoo()
    v3 = {"scenario": make_scenario("ballistic", preset="v3").describe()}  # the card of a model trained on v3
    work, zoo = tmp_path / "ballistic-gru", tmp_path / "zoo"
    (zoo / "ballistic-gru").mkdir(parents=True)
    (zoo / "ballistic-gru" / "card.json").write_text(json.dumps(v3))
    assert zoo_script.comparable_shipped(work, zoo, make_scenario("ballistic")) is None
    assert zoo_script.comparable_shipped(work, zoo, make_scenario("ballistic", preset="v3")) == zoo / "ballistic-gru"


def test_work_dir_keeps_trainings_of_other_constants_apart(tmp_path):
    zoo_script = _train_zoo()
    state = tmp_path / "state"
    legacy = state / "ballistic-mamba2"
    assert zoo_script.work_dir(state, make_scenario("ballistic"), "mamba2") == legacy  # empty: used as is
    legacy.mkdir(parents=True)
    card = {"scenario": make_scenario("ballistic", preset="v3").describe()}
    (legacy / "card.json").write_text(json.dumps(card))
    assert zoo_script.work_dir(state, make_scenario("ballistic", preset="v3"), "mamba2") == legacy
    assert zoo_script.work_dir(state, make_scenario("ballistic"), "mamba2") == state / "v4" / "ballistic-mamba2"


def test_work_dir_keeps_a_preset_in_its_own_folder_before_and_after_it_becomes_the_defaults(tmp_path, monkeypatch):
    """A preset newer than the defaults (N-link's v5 before it became the defaults) never takes the
    legacy folder, even an empty one, and its training is found in v5/ after the defaults move to
    it; with nothing recorded, a training of the defaults takes the legacy folder."""
    zoo_script = _train_zoo()
    v5 = make_scenario("nlink")  # the defaults today
    assert v5.describe()["preset"] == "v5"
    before = tmp_path / "before"
    monkeypatch.setattr(zoo_script, "default_preset", lambda name: "v4")  # the defaults before the move
    assert zoo_script.work_dir(before, v5, "mamba2") == before / "v5" / "nlink-mamba2"  # legacy empty
    (before / "v5" / "nlink-mamba2").mkdir(parents=True)
    (before / "v5" / "nlink-mamba2" / "card.json").write_text(json.dumps({"scenario": v5.describe()}))
    monkeypatch.undo()
    assert zoo_script.work_dir(before, v5, "mamba2") == before / "v5" / "nlink-mamba2"  # found after the move
    # the legacy folder holding a v4 (= v3) training: a v5 one goes to v5/, the v4 one stays found
    v4 = make_scenario("nlink", preset="v4")
    (before / "nlink-gru").mkdir(parents=True)
    (before / "nlink-gru" / "card.json").write_text(json.dumps({"scenario": v4.describe()}))
    assert zoo_script.work_dir(before, v5, "gru") == before / "v5" / "nlink-gru"
    assert zoo_script.work_dir(before, v4, "gru") == before / "nlink-gru"
    # nothing recorded: the defaults train in the legacy folder
    assert zoo_script.work_dir(tmp_path / "fresh", v5, "gru") == tmp_path / "fresh" / "nlink-gru"


def test_an_installed_model_gets_its_covariance_head_fitted_in_the_packages_zoo_only(tmp_path, monkeypatch, capsys):
    zoo_script = _train_zoo()
    calls = []
    monkeypatch.setattr(
        zoo_script.subprocess, "run", lambda cmd, check: calls.append(cmd) or SimpleNamespace(returncode=0)
    )
    dest = tmp_path / "zoo" / "ballistic-mamba"
    zoo_script.fit_head(dest, tmp_path / "zoo")  # another zoo: the command is printed, nothing runs
    assert not calls and "no covariance head fitted outside" in capsys.readouterr().out
    monkeypatch.setattr(zoo_script, "ZOO", tmp_path / "zoo")
    zoo_script.fit_head(dest, tmp_path / "zoo")
    assert calls[0][-4:] == ["--scenarios", "ballistic", "--methods", "mamba"]
    assert calls[0][1].endswith("fit_covariance_heads.py") and "covariance head fitted" in capsys.readouterr().out
    # a trained instance installed in the package's zoo/instances/i<K>/ gets its own head: --instance K
    instance = tmp_path / "zoo" / "instances" / "i2" / "nlink-gru"
    zoo_script.fit_head(instance, instance.parent)
    assert calls[1][-6:] == ["--scenarios", "nlink", "--methods", "gru", "--instance", "2"]
    assert "covariance head fitted" in capsys.readouterr().out
    # the same layout under another root is another zoo: nothing runs
    elsewhere = tmp_path / "other" / "instances" / "i2" / "nlink-gru"
    zoo_script.fit_head(elsewhere, elsewhere.parent)
    assert len(calls) == 2 and "no covariance head fitted outside" in capsys.readouterr().out
