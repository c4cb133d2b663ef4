"""benchmarks/loss_units.py: a state-unit training is compared only with a model of the same recipe."""

import importlib.util
from pathlib import Path

import pytest

from neural_estimator.data.recipe import TrainConfig


@pytest.fixture(scope="module")
def bench():
    path = Path(__file__).resolve().parents[1] / "benchmarks" / "loss_units.py"
    spec = importlib.util.spec_from_file_location("loss_units", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _card(**kw):
    return {"training": {"recipe": TrainConfig(epochs=20, windows_per_epoch=2000, **kw).recipe()}}


def test_same_recipe_ignores_only_the_loss_units(bench):
    state, normalised = _card(), _card(loss_units="normalised")
    assert "loss_units" in state["training"]["recipe"] and "loss_units" not in normalised["training"]["recipe"]
    assert bench.same_recipe(normalised, state)
    assert not bench.same_recipe(_card(loss_units="normalised", init_seed=1), state)
    assert not bench.same_recipe({"training": {"recipe": TrainConfig(epochs=84).recipe()}}, state)
