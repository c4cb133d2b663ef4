"""The shipped models: each loads without unpickling, has learnt (its recorded training curve went
down), and beats the trivial estimator that inverts nothing (the prior mean) on fresh data."""

import json
from pathlib import Path

import numpy as np
import pytest

from neural_estimator import metrics as M
from neural_estimator.data import simulate
from neural_estimator.methods.registry import EstimatorError, make_estimator
from neural_estimator.scenarios import make_scenario

ZOO = Path(__file__).resolve().parents[1] / "neural_estimator" / "serving" / "zoo"
SHIPPED = sorted(p.name for p in ZOO.glob("*-*") if "." not in p.name and (p / "card.json").exists())


def test_zoo_holds_only_weights_cards_and_step_graphs():
    """Weights and card, the covariance head exactly where the card names one, and the exported
    batch-1 step (step.onnx) beside every model (those validated with a bounded context: their
    restarted copies' step at batch K) but a hybrid whose system's f or h has no ONNX form (the
    model says why: N-link's linear solve)."""
    from neural_estimator.methods import table
    from neural_estimator.serving.checkpoint import load_checkpoint

    for d in (ZOO / n for n in SHIPPED):
        card = json.loads((d / "card.json").read_text())
        torch_only = False
        if table.has(card["method"], family="hybrid"):
            torch_only = load_checkpoint(d)[0].onnx_blocker is not None
        expected = ["card.json"] + (["covariance_head.safetensors"] if card.get("covariance_head") else [])
        expected += ["model.safetensors"] + ([] if torch_only else ["step.onnx"])
        assert sorted(f.name for f in d.iterdir()) == expected, d


@pytest.mark.parametrize("name", [n for n in SHIPPED if "covariance_head" in (ZOO / n / "card.json").read_text()])
def test_a_shipped_covariance_head_is_served_and_recorded_its_calibration(name):
    """A head serves a positive definite covariance beside the very estimate of the model without
    it, and its card records the calibration scale and the validation figures after it."""
    scenario_name, method = name.split("-")
    card = json.loads((ZOO / name / "card.json").read_text())
    cal = card["covariance_head"]["calibration"]
    assert cal["scale"] > 0 and 0.9 <= cal["after"]["coverage95"] <= 0.98
    scenario = make_scenario(scenario_name, **card["scenario"]["config"])
    data = simulate(scenario, 2, 40, seed=12345)
    with_head = make_estimator(method, scenario).run(data.y, data.u)
    without = make_estimator(method, scenario, covariance=False).run(data.y, data.u)
    assert np.array_equal(with_head.x, without.x)
    assert np.linalg.eigvalsh(with_head.cov).min() > 0


def test_every_trained_instance_has_its_own_covariance_head_where_the_shipped_model_has_one():
    """The tables give coverage and NEES as medians over instances, as RMSE: an instance without a head
    would leave them the shipped model's alone. Each instance's head was fitted on the shipped head's
    validation sets and is served from its own folder."""
    from neural_estimator.serving.instances import instance_number, zoo_instances

    checked = 0
    for name in SHIPPED:
        scenario_name, method = name.split("-")
        head = json.loads((ZOO / name / "card.json").read_text()).get("covariance_head")
        if head is None:
            continue
        for path in zoo_instances(scenario_name, method)[1:]:
            card = json.loads((path / "card.json").read_text())
            fix = f"scripts/fit_covariance_heads.py --scenarios {scenario_name} --instance {instance_number(path)}"
            assert "covariance_head" in card, f"{path}: no covariance head ({fix})"
            entry = card["covariance_head"]
            for part in ("head", "calibration"):  # the same validation sets (a recalibration adds its count)
                sets = [{k: f["fitted_on"][part][k] for k in ("role", "index", "seed")} for f in (entry, head)]
                assert sets[0] == sets[1], (path, part)
            assert (path / entry["file"]).is_file(), path
            assert 0.9 <= entry["calibration"]["after"]["coverage95"] <= 0.98, path
            checked += 1
    assert checked >= 9  # the N-link and Lorenz 96 networks' instances (docs/training.md)


def _changed_constants(card: dict, scenario) -> list[str]:
    """Constants (evaluation-only ones aside) whose default differs from the card's (the
    calibration changed some scenarios after the zoo was trained)."""
    from neural_estimator.serving.load import EVALUATION_CONSTANTS

    theirs, ours = card["scenario"]["config"], scenario.describe()["config"]
    return sorted(k for k in set(theirs) | set(ours) if k not in EVALUATION_CONSTANTS and theirs.get(k) != ours.get(k))


@pytest.mark.slow
@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_model_learnt_and_beats_the_prior_mean(name):
    """On the constants it was trained on (its card's), every shipped model loads and has learnt."""
    scenario_name, method = name.split("-")
    card = json.loads((ZOO / name / "card.json").read_text())
    history = card["training"]["history"]
    # the shipped weights are the best epoch's: its validation loss is below the first epoch's
    assert card["validation_loss"] < history[0]["val_loss"], "validation loss did not go down"
    assert card["validation_loss"] == min(h["val_loss"] for h in history)
    scenario = make_scenario(scenario_name, **card["scenario"]["config"])
    est = make_estimator(method, scenario)  # the shipped default
    data = simulate(scenario, 16, scenario.horizon, seed=12345)  # not a training or evaluation seed stream
    x_hat = est.run(data.y, data.u).x
    m0, _ = scenario.prior()
    model = M.compute_metrics(data.x, x_hat, scenario.angle_states)
    trivial = M.compute_metrics(data.x, np.broadcast_to(m0, data.x.shape), scenario.angle_states)
    assert model.full_rmse < trivial.full_rmse, (model.full_rmse, trivial.full_rmse)


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_model_on_the_default_constants_loads_or_is_refused_naming_them(name):
    """Where the scenario's defaults still equal the card's constants the model loads; where the
    calibration changed them it is refused with one line naming every changed constant."""
    scenario_name, method = name.split("-")
    card = json.loads((ZOO / name / "card.json").read_text())
    scenario = make_scenario(scenario_name)
    changed = _changed_constants(card, scenario)
    if not changed:
        make_estimator(method, scenario)
        return
    with pytest.raises(EstimatorError) as info:
        make_estimator(method, scenario)
    message = str(info.value)
    assert "\n" not in message and "other constants" in message
    for k in changed:
        assert f"{k}=" in message, (k, message)


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_model_loads_on_the_preset_its_card_names(name):
    """Every shipped model's constants are a named preset (v3 for those trained before the spread
    calibration, v4 for the retrained), and it loads on that preset by name; on the other preset of
    a changed scenario it is refused with a one-line message that names the preset to use."""
    from neural_estimator.scenarios import preset_names, scenario_class

    scenario_name, method = name.split("-")
    card = json.loads((ZOO / name / "card.json").read_text())
    preset = scenario_class(scenario_name).preset_of(card["scenario"]["config"])
    assert preset in preset_names(scenario_name), (name, preset)
    make_estimator(method, make_scenario(scenario_name, preset=preset))
    for other in preset_names(scenario_name):
        if _changed_constants(card, make_scenario(scenario_name, preset=other)):
            with pytest.raises(EstimatorError) as info:
                make_estimator(method, make_scenario(scenario_name, preset=other))
            assert f"--preset {preset}" in str(info.value) and "\n" not in str(info.value)


def test_a_shipped_model_says_how_many_leading_steps_its_training_skipped():
    """The estimator node warns about them (a neural model's first estimates were never optimised)."""
    from neural_estimator.methods.registry import make_estimator
    from neural_estimator.scenarios import make_scenario

    est = make_estimator("mamba2", make_scenario("lorenz96"))
    assert est.untrained_steps == 10
    est.card = {}
    assert est.untrained_steps == 0
    assert not hasattr(make_estimator("ukf", make_scenario("lorenz96")), "untrained_steps")
