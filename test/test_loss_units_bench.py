"""experiments/loss_units.py: a state-unit training is compared only with a model of the same recipe."""

import pytest

from neural_estimator.training.recipe import TrainConfig
from conftest import load_script


@pytest.fixture(scope="module")
def bench():
    return load_script("experiments/loss_units.py")


def _card(**kw):
    return {"training": {"recipe": TrainConfig(epochs=20, windows_per_epoch=2000, **kw).recipe()}}


def test_same_recipe_ignores_only_the_loss_units(bench):
    state, normalised = _card(), _card(loss_units="normalised")
    assert "loss_units" in state["training"]["recipe"] and "loss_units" not in normalised["training"]["recipe"]
    assert bench.same_recipe(normalised, state)
    assert not bench.same_recipe(_card(loss_units="normalised", init_seed=1), state)
    assert not bench.same_recipe({"training": {"recipe": TrainConfig(epochs=84).recipe()}}, state)
