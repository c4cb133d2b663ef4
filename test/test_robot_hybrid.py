"""The robot flow with the system's model: a spec naming a scenario (``model:``), a recording with no
ground-truth topic, a hybrid (KalmanNet) trained on its observations, filters run on the recording."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from neural_estimator.bags.writer import TYPESTORE, BagWriter
from neural_estimator.cli import main
from neural_estimator.data import load_trajectories
from neural_estimator.data.simulate import simulate
from neural_estimator.robot import DataScenario, SpecError, build_dataset, load_spec
from neural_estimator.scenarios import make_scenario

SCENARIO = "quadrotor"  # dx 6, dy 3, du 2, dt 0.01 s
TYPE = "std_msgs/msg/Float64MultiArray"


def array_msg(values: np.ndarray):
    """A std_msgs/Float64MultiArray holding ``values``."""
    M = TYPESTORE.types
    layout = M["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0)
    return M[TYPE](layout=layout, data=np.asarray(values, dtype=np.float64))


def fields(n: int) -> list[str]:
    return [f"data[{i}]" for i in range(n)]


def spec_dict(state: bool = False, **model) -> dict:
    """A spec reading the simulated quadrotor's topics, naming it as the model (``model`` overrides)."""
    s = make_scenario(SCENARIO)
    out = {
        "rate": 1.0 / s.dt,
        "stamp": "log",
        "observation": {"/y": fields(s.dy)},
        "control": {"/u": fields(s.du)},
        "model": {"scenario": SCENARIO, **model},
    }
    if state:
        out["state"] = {"/truth": fields(s.dx)}
    return out


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """(bags, simulated trajectories): 6 quadrotor flights of 40 steps, one MCAP each, written with
    the project's writer at the model's period: /y the observations, /u the controls, /truth the state."""
    s = make_scenario(SCENARIO)
    sim = simulate(s, 6, 40, np.random.SeedSequence(3))
    step = int(round(s.dt * 1e9))
    bags = []
    for n in range(sim.n):
        path = tmp_path_factory.mktemp("rec") / f"flight{n}.mcap"
        with BagWriter(path) as bag:
            for k in range(sim.horizon):
                t = (k + 1) * step
                bag.write_message("/y", t, array_msg(sim.y[n, k]), TYPE)
                bag.write_message("/u", t, array_msg(sim.u[n, k]), TYPE)
                bag.write_message("/truth", t, array_msg(sim.x[n, k]), TYPE)
        bags.append(path)
    return bags, sim


# ---- the spec ---------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "spec, message",
    [
        (
            {**spec_dict(), "observation": {"/y": fields(2)}},
            "observation has 2 fields, but the model 'quadrotor' has 3",
        ),
        ({**spec_dict(), "control": {"/u": fields(1)}}, "control has 1 fields, but the model 'quadrotor' has 2"),
        (
            {**spec_dict(state=True), "state": {"/truth": fields(5)}},
            "state has 5 fields, but the model 'quadrotor' has 6",
        ),
        ({**spec_dict(), "rate": 50.0}, r"dt = 0.01 s, but rate 50 Hz samples every 0.02 s: add set: \{dt: 0.02\}"),
        (spec_dict(set={"dt": 0.02}), r"dt = 0.02 s, but rate 100 Hz samples every 0.01 s: add set: \{dt: 0.01\}"),
        (spec_dict(scenario="nosuch"), "unknown scenario 'nosuch'"),
        (spec_dict(preset="v0"), "has no preset 'v0'"),
        ({**spec_dict(), "model": "quadrotor"}, "model must be a mapping"),
        ({k: v for k, v in spec_dict().items() if k != "model"}, "missing 'state'"),
    ],
)
def test_a_model_that_does_not_fit_the_spec_is_refused_in_one_line(spec, message):
    with pytest.raises(SpecError, match=message) as err:
        load_spec(spec)
    assert "\n" not in str(err.value)


def test_the_digest_covers_the_model_and_the_state_comes_from_it():
    s = load_spec(spec_dict())
    model = make_scenario(SCENARIO)
    assert not s.has_state and s.names["state"] == model.state_names and s.angles("state") == tuple(model.angle_states)
    assert s.digest() != load_spec(spec_dict(set={"mass": 1.1 * model.config.mass})).digest()
    assert load_spec(spec_dict(set={"dt": 0.01})).model.dt == model.dt


# ---- the dataset and the data scenario --------------------------------------------------------------------
def test_a_recording_without_ground_truth_gives_a_dataset_with_no_label(recording, tmp_path):
    bags, sim = recording
    data, _, _ = build_dataset(bags, load_spec(spec_dict()), length=40)
    assert data.n == sim.n and data.labelled is not None and not data.labelled.any()
    assert data.meta["ground_truth"] is False and data.meta["labelled_steps"] == 0
    np.testing.assert_allclose(data.y, sim.y)
    np.testing.assert_allclose(data.u, sim.u)
    path = tmp_path / "d.npz"
    assert (
        main(
            [
                "dataset",
                *map(str, bags),
                "--spec",
                str(_yaml(tmp_path, spec_dict())),
                "--length",
                "40",
                "--out",
                str(path),
                "--quiet",
            ]
        )
        == 0
    )
    loaded, _ = load_trajectories(path)
    assert loaded.labelled is not None and not loaded.labelled.any()


def test_data_scenario_with_a_model_has_the_models_equations(recording):
    bags, sim = recording
    data, _, _ = build_dataset(bags, load_spec(spec_dict(state=True)), length=40)
    assert data.labelled is None  # every step has ground truth
    np.testing.assert_allclose(data.x, sim.x)
    s, model = DataScenario(data.meta), make_scenario(SCENARIO)
    x, u = sim.x[:, 5], sim.u[:, 5]
    np.testing.assert_array_equal(s.f(x, u), model.f(x, u))
    np.testing.assert_array_equal(s.h(x), model.h(x))
    np.testing.assert_array_equal(s.jac_h(x), model.jac_h(x))
    np.testing.assert_array_equal(s.process_cov(), model.process_cov())
    np.testing.assert_array_equal(s.obs_cov(), model.obs_cov())
    np.testing.assert_array_equal(s.prior()[0], model.prior()[0])
    assert s.torch_dynamics() is not None and s.describe()["model"] == {"scenario": SCENARIO}
    other = DataScenario({**data.meta, "model": {"scenario": SCENARIO, "set": {"mass": 2 * model.config.mass}}})
    assert other.describe()["config"]["model_sha256"] != s.describe()["config"]["model_sha256"]


# ---- training and evaluation ----------------------------------------------------------------------------
def _yaml(tmp_path: Path, spec: dict) -> Path:
    import yaml

    path = tmp_path / f"spec{len(list(tmp_path.glob('spec*.yaml')))}.yaml"
    path.write_text(yaml.safe_dump(spec))
    return path


def _dataset(tmp_path, bags, spec: dict, name: str) -> Path:
    out = tmp_path / name
    args = ["dataset", *map(str, bags), "--spec", str(_yaml(tmp_path, spec)), "--length", "40", "--out", str(out)]
    assert main(args + ["--quiet"]) == 0
    return out


TRAIN = ["--model", "kalmannet", "--epochs", "1", "--window", "20", "--warmup", "2", "--batch-size", "2", "--quiet"]


def _evaluate(data: Path, methods: str, checkpoint: Path, *extra: str) -> int:
    return main(
        ["evaluate", "--data", str(data), "--methods", methods, "--checkpoint", f"kalmannet={checkpoint}", *extra]
    )


def test_a_hybrid_trains_on_observations_of_a_recording_without_ground_truth(recording, tmp_path, capsys):
    import json

    from neural_estimator.serving.load import load_neural_estimator

    bags, _ = recording
    data = _dataset(tmp_path, bags, spec_dict(), "unlabelled.npz")
    out = tmp_path / "knet"
    # a state-supervised run has nothing to learn from
    assert main(["train", "--data", str(data), "--out", str(out), *TRAIN]) == 2
    err = capsys.readouterr().err.strip()
    assert "no state labels: train a hybrid with --supervision observations" in err and "\n" not in err
    assert main(["train", "--data", str(data), "--out", str(out), *TRAIN, "--supervision", "observations"]) == 0
    card = json.loads((out / "card.json").read_text())
    assert card["training"]["supervision"] == "observations" and card["metrics"] is None  # nothing to score
    assert card["scenario"]["model"] == {"scenario": SCENARIO}
    # the checkpoint loads for the recording's scenario and filters it
    recorded, _ = load_trajectories(data)
    est = load_neural_estimator("kalmannet", DataScenario(recorded.meta), out, covariance=False)
    x_hat = est.run(recorded.y, recorded.u).x
    assert x_hat.shape == recorded.x.shape and np.isfinite(x_hat).all()
    # evaluate: nothing to score on a recording without ground truth, said in one line
    assert _evaluate(data, "ekf,kalmannet", out) == 2
    err = capsys.readouterr().err.strip()
    assert "nothing to score against" in err and "\n" not in err


def test_filters_and_the_hybrid_are_scored_on_a_recording_with_ground_truth(recording, tmp_path, capsys):
    import json

    bags, _ = recording
    data = _dataset(tmp_path, bags, spec_dict(state=True), "labelled.npz")
    out = tmp_path / "knet"
    assert main(["train", "--data", str(data), "--out", str(out), *TRAIN, "--supervision", "observations"]) == 0
    card = json.loads((out / "card.json").read_text())
    assert np.isfinite(card["metrics"]["rmse"])  # the card's metrics on the labelled validation set
    capsys.readouterr()
    assert _evaluate(data, "ekf,openloop,kalmannet", out, "--json", "--no-cache") == 0
    methods = json.loads(capsys.readouterr().out)["methods"]
    rmse = {m: methods[m]["summary"]["rmse"]["median"] for m in ("ekf", "openloop", "kalmannet")}
    assert all(np.isfinite(v) and v > 0 for v in rmse.values())
    assert rmse["ekf"] < rmse["openloop"]  # the model's filter reads the recording's observations
    # a recording of another model (and so another spec): the checkpoint is refused in one line
    other = _dataset(tmp_path, bags, spec_dict(state=True, set={"mass": 0.6}), "other.npz")
    assert _evaluate(other, "kalmannet", out) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "model_sha256" in err


def test_a_plugins_scenario_is_a_model_once_the_plugin_is_loaded(tmp_path):
    from neural_estimator.scenarios import load_plugins

    root = Path(__file__).resolve().parents[1]
    spec = {"rate": 10.0, "observation": {"/y": ["data[0]"]}, "model": {"scenario": "oscillator"}}
    load_plugins([root / "examples" / "custom_scenario.py"])  # registers "oscillator": dx 2, dy 1, dt 0.1 s
    s = load_spec(spec)
    assert (s.model.name, s.names["state"], s.model.dt) == ("oscillator", s.model.state_names, 0.1)
    with pytest.raises(SpecError, match="observation has 2 fields, but the model 'oscillator' has 1"):
        load_spec({**spec, "observation": {"/y": fields(2)}})


def test_a_run_is_not_scored_against_a_spec_without_ground_truth():
    from neural_estimator.robot.score import scoring_spec

    with pytest.raises(SpecError, match="no ground truth .*nothing to score against"):
        scoring_spec(load_spec(spec_dict()), ["/estimates/gru"], "/", None)
