"""The shipped models: each loads without unpickling, has learnt (its recorded training curve went
down), and beats the trivial estimator that inverts nothing (the prior mean) on fresh data."""

import json
from pathlib import Path

import numpy as np
import pytest

from neural_estimator import metrics as M
from neural_estimator.data import simulate
from neural_estimator.estimators import make_estimator
from neural_estimator.scenarios import make_scenario

ZOO = Path(__file__).resolve().parents[1] / "neural_estimator" / "zoo"
SHIPPED = sorted(p.name for p in ZOO.glob("*-*") if "." not in p.name and (p / "card.json").exists())


def test_zoo_holds_only_weights_and_cards():
    for d in (ZOO / n for n in SHIPPED):
        assert sorted(f.name for f in d.iterdir()) == ["card.json", "model.safetensors"], d


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_model_learnt_and_beats_the_prior_mean(name):
    scenario_name, method = name.split("-")
    card = json.loads((ZOO / name / "card.json").read_text())
    history = card["training"]["history"]
    assert history[-1]["val_loss"] < history[0]["val_loss"], "validation loss did not go down"
    scenario = make_scenario(scenario_name)
    est = make_estimator(method, scenario)  # the shipped default
    data = simulate(scenario, 16, scenario.horizon, seed=12345)  # not a training or evaluation seed stream
    x_hat = est.run(data.y, data.u).x
    m0, _ = scenario.prior()
    model = M.compute_metrics(data.x, x_hat, scenario.angle_states)
    trivial = M.compute_metrics(data.x, np.broadcast_to(m0, data.x.shape), scenario.angle_states)
    assert model.full_rmse < trivial.full_rmse, (model.full_rmse, trivial.full_rmse)
