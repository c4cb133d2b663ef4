"""The sample bags in bags/ are readable, hold what they claim, and replay through the methods."""

from pathlib import Path

import numpy as np
import pytest

from neural_estimator.bags import BagError, bag_to_arrays, load_bag_dataset
from neural_estimator.cli import main
from neural_estimator.estimators import CLASSICAL_METHODS, NEURAL_METHODS
from neural_estimator.scenarios import BUILTIN_SCENARIOS

ROOT = Path(__file__).resolve().parents[1]
ZOO = ROOT / "neural_estimator" / "zoo"


@pytest.mark.parametrize("scenario", BUILTIN_SCENARIOS)
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


SHIPPED = [(s, m) for s in BUILTIN_SCENARIOS for m in NEURAL_METHODS if (ZOO / f"{s}-{m}" / "card.json").exists()]


@pytest.mark.parametrize("scenario, method", SHIPPED)
def test_sample_bag_replays_through_shipped_models(scenario, method, tmp_path):
    out = tmp_path / "r.mcap"
    assert main(["replay", str(ROOT / "bags" / f"{scenario}.mcap"), "--methods", method, "--out", str(out)]) == 0
    truth, estimates, _ = load_bag_dataset(out)
    x_hat, _ = estimates[method]
    assert np.all(np.isfinite(x_hat)) and x_hat.shape == truth.x.shape
