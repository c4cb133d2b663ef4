"""The sample bags in bags/ are readable, hold what they claim, and replay through the methods."""

from pathlib import Path

import numpy as np
import pytest

from neural_estimator.bags import BagError, bag_to_arrays, load_bag_dataset
from neural_estimator.cli import main
from neural_estimator.methods.registry import CLASSICAL_METHODS, NEURAL_METHODS
from neural_estimator.paper import PAPER_SCENARIOS
from neural_estimator.scenarios import default_preset, preset_names
from neural_estimator.serving.card import shipped_preset

pytestmark = pytest.mark.slow  # every sample bag through the shipped models

ROOT = Path(__file__).resolve().parents[1]
ZOO = ROOT / "neural_estimator" / "serving" / "zoo"


@pytest.mark.parametrize("scenario", PAPER_SCENARIOS)
def test_sample_bag_replays_through_every_classical_method(scenario, tmp_path, capsys):
    bag = ROOT / "bags" / f"{scenario}.mcap"
    with pytest.raises(BagError, match="no estimate stream"):  # nothing to score: an error, not an empty table
        load_bag_dataset(bag)
    truth = bag_to_arrays(bag)
    assert truth.description["scenario"] == scenario and truth.x.shape[0] == 2 and not truth.x_hat
    out = tmp_path / "r.mcap"
    assert (
        main(
            [
                "replay",
                str(bag),
                "--methods",
                ",".join(CLASSICAL_METHODS),
                "--out",
                str(out),
                "--option",
                "pf.n_particles=256",
            ]
        )
        == 0
    )
    truth2, estimates2, _ = load_bag_dataset(out)
    np.testing.assert_array_equal(truth2.x, truth.x)
    assert set(estimates2) == set(CLASSICAL_METHODS)
    for m, (x_hat, _) in estimates2.items():
        assert x_hat.shape == truth.x.shape


SHIPPED = [(s, m) for s in PAPER_SCENARIOS for m in NEURAL_METHODS if (ZOO / f"{s}-{m}" / "card.json").exists()]


def _card_preset(scenario: str, method: str) -> str:
    """The preset whose constants the shipped model was trained on (from its card's constants)."""
    return shipped_preset(scenario, method)


def _bag_of(scenario: str, preset: str) -> Path:
    return ROOT / "bags" / (f"{scenario}.mcap" if preset == default_preset(scenario) else f"{scenario}-{preset}.mcap")


@pytest.mark.parametrize("scenario, method", SHIPPED)
def test_sample_bag_replays_through_shipped_models(scenario, method, tmp_path):
    """Every shipped model replays the sample bag of its own constants (scripts/make_sample_bags.py)."""
    bag = _bag_of(scenario, _card_preset(scenario, method))
    assert bag.exists(), f"no sample bag on the constants of {scenario}-{method}: make_sample_bags.py --preset"
    out = tmp_path / "r.mcap"
    assert main(["replay", str(bag), "--methods", method, "--out", str(out)]) == 0
    truth, estimates, _ = load_bag_dataset(out)
    x_hat, _ = estimates[method]
    assert np.all(np.isfinite(x_hat)) and x_hat.shape == truth.x.shape


def _sample_bags(scenario: str) -> dict[str, Path]:
    """preset -> the sample bag of the scenario on that preset, for every one that exists."""
    return {p: _bag_of(scenario, p) for p in preset_names(scenario) if _bag_of(scenario, p).exists()}


# every (shipped model, sample bag of other constants): the v3 bags keep this non-empty after retraining
FOREIGN = [(s, m, p) for s, m in SHIPPED for p in _sample_bags(s) if p not in (_card_preset(s, m), "custom")]


def test_some_shipped_model_meets_a_bag_of_other_constants():
    assert FOREIGN, "no sample bag of other constants than a shipped model's: the refusal below is unchecked"


@pytest.mark.parametrize("scenario, method, preset", FOREIGN)
def test_a_model_of_other_constants_is_refused_on_that_bag_in_one_line(scenario, method, preset, tmp_path, capsys):
    out = tmp_path / "r.mcap"
    assert main(["replay", str(_bag_of(scenario, preset)), "--methods", method, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "other constants" in err
    # the advice leads somewhere: another bag or another model, not a --preset that would be refused
    assert "--preset" not in err and "replay a bag recorded with the checkpoint's constants" in err
    assert not out.exists()
    # naming the model's constants instead runs it on data of other constants only with --force
    card = _card_preset(scenario, method)
    named = ["--scenario", scenario, "--preset", card] if card not in (None, "custom") else []
    if named:
        args = ["replay", str(_bag_of(scenario, preset)), "--methods", method, "--out", str(out), *named]
        assert main(args) == 2
        err = capsys.readouterr().err
        assert "its data were made with other constants" in err and "--force" in err and not out.exists()
        assert main(args + ["--force"]) == 0 and out.exists()
