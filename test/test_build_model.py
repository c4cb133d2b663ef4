"""build_model(name, scenario, **hp) through the checkpoint: a model is rebuilt for the scenario it
serves or the one its card describes; the shipped cards (which record d_in / d_out) load unchanged."""

from __future__ import annotations

import json

import pytest
import torch

from neural_estimator.methods.interface import EstimatorError
from neural_estimator.models import SystemDims, build_model, model_dims
from neural_estimator.scenarios import Scenario, make_scenario
from neural_estimator.serving.card import default_checkpoint
from neural_estimator.serving.checkpoint import load_checkpoint, save_checkpoint, system_of_card
from neural_estimator.serving.normalization import Normalizer

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def small_checkpoint(tmp_path, scenario, data=None):
    from neural_estimator.data import simulate

    torch.manual_seed(0)
    model = build_model("gru", scenario, hidden=4, layers=1)
    norm = Normalizer.from_data(scenario, data if data is not None else simulate(scenario, 2, 5, seed=0))
    save_checkpoint(tmp_path, model, norm, {"scenario": scenario.describe()})
    return model


@pytest.mark.parametrize("name", ["quadrotor", "nlink"])
def test_a_shipped_card_resolves_its_scenario(name):
    """The zoo's cards rebuild their scenario (with its constants) and the model for it, weights and all."""
    ckpt = default_checkpoint(name, "gru")
    card = json.loads((ckpt / "card.json").read_text())
    system = system_of_card(card)
    assert isinstance(system, Scenario) and system.describe()["config"] == card["scenario"]["config"]
    cfg = card["architecture"]["config"]
    assert model_dims(system) == (cfg["d_in"], cfg["d_out"])
    model, _, _ = load_checkpoint(ckpt)
    served, _, _ = load_checkpoint(ckpt, scenario=make_scenario(name))
    for (k, a), (_, b) in zip(model.state_dict().items(), served.state_dict().items()):
        assert torch.equal(a, b), k


def test_a_card_of_a_scenario_not_registered_here_loads_by_its_dimensions(tmp_path):
    scenario = make_scenario("quadrotor")
    model = small_checkpoint(tmp_path, scenario)
    card_file = tmp_path / "card.json"
    card = json.loads(card_file.read_text())
    card["scenario"]["scenario"] = "a_plugin_not_loaded"
    card_file.write_text(json.dumps(card))
    assert system_of_card(card) == SystemDims(dx=6, dy=3, du=2)
    loaded, _, _ = load_checkpoint(tmp_path)
    assert (loaded.cfg.d_in, loaded.cfg.d_out) == (5, 6)
    assert all(torch.equal(a, b) for a, b in zip(model.state_dict().values(), loaded.state_dict().values()))


def test_a_card_whose_network_does_not_fit_its_scenario_is_refused(tmp_path):
    scenario = make_scenario("lorenz96")
    small_checkpoint(tmp_path, scenario)
    with pytest.raises(EstimatorError, match="d_in=10 to d_out=10, but its system has dy \\+ du = 11, dx = 10"):
        load_checkpoint(tmp_path, scenario=SystemDims(dx=10, dy=10, du=1))


def test_recorded_data_builds_and_loads_its_model(tmp_path):
    """The robot flow: a DataScenario (no equations) sizes the model; its card loads with and without it."""
    import numpy as np

    from neural_estimator.data.simulate import Trajectories
    from neural_estimator.robot.data_scenario import DataScenario

    meta = {
        "dt": 0.05,
        "state_names": ["x", "y", "yaw"],
        "state_units": ["m", "m", "rad"],
        "obs_names": ["range", "bearing"],
        "obs_units": ["m", "rad"],
        "control_names": ["v"],
        "control_units": ["m/s"],
        "angle_states": [2],
        "angle_obs": [1],
    }
    data_scenario = DataScenario(meta)
    rng = np.random.default_rng(0)
    data = Trajectories(
        x=rng.standard_normal((2, 5, 3)), y=rng.standard_normal((2, 5, 2)), u=rng.standard_normal((2, 5, 1))
    )
    model = small_checkpoint(tmp_path, data_scenario, data)
    assert (model.cfg.d_in, model.cfg.d_out) == (3, 3)
    for scenario in (None, data_scenario):
        loaded, _, _ = load_checkpoint(tmp_path, scenario=scenario)
        assert all(torch.equal(a, b) for a, b in zip(model.state_dict().values(), loaded.state_dict().values()))
