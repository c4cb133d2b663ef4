"""The calibrated scenario constants: recorded, the previous ones one --set away, the
dataset cache keyed by the new revision, and the calibration script's distance."""

import importlib.util
import math
from pathlib import Path

import pytest

from neural_estimator.data import protocol, simulate
from neural_estimator.scenarios import make_scenario

ROOT = Path(__file__).resolve().parents[1]


def _script():
    spec = importlib.util.spec_from_file_location("calibrate_scenarios", ROOT / "scripts" / "calibrate_scenarios.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


CALIBRATED = {
    "bearings": {
        "prior_mean": [-200.0, 400.0, 2.0, 0.0],
        "prior_std": [10.0, 10.0, 1.0, 1.0],
        "accel_noise_std": 0.3,
        "obs_noise_std": 0.01,
    },
    "nlink": {"obs_noise_std": 0.02, "prior_angle_std": 0.1, "prior_rate_std": 0.1},
    "quadrotor": {"process_noise_std": 0.1},
}
PREVIOUS = {
    "bearings": {
        "prior_mean": [0.0, 400.0, 0.0, -50.0],
        "prior_std": [500.0, 300.0, 5.0, 10.0],
        "accel_noise_std": 1.0,
        "obs_noise_std": 0.005,
    },
    "nlink": {"obs_noise_std": 0.05, "prior_angle_std": 1.0, "prior_rate_std": 1.0},
    "quadrotor": {"process_noise_std": 0.001},
}


@pytest.mark.parametrize("name", sorted(CALIBRATED))
def test_calibrated_constants_are_the_defaults_and_recorded_in_files(name):
    s = make_scenario(name)
    cfg = s.describe()["config"]
    for k, v in CALIBRATED[name].items():
        assert cfg[k] == v, (k, cfg[k])
    data = simulate(s, 2, 3, seed=0)
    assert data.meta["config"] == cfg  # every file made with it records them


@pytest.mark.parametrize("name", sorted(PREVIOUS))
def test_previous_constants_are_one_set_away_and_the_script_lists_them(name):
    overrides = {k: (tuple(v) if isinstance(v, list) else v) for k, v in PREVIOUS[name].items()}
    old = make_scenario(name, **{k: str(v).replace("(", "[").replace(")", "]") for k, v in overrides.items()})
    for k, v in PREVIOUS[name].items():
        assert old.describe()["config"][k] == v
    script_previous, _ = _script().CANDIDATES[name]["previous"]
    assert make_scenario(name, **script_previous).describe() == old.describe()


def test_cache_revision_bumped_for_the_calibration():
    assert protocol.SIMULATION_REVISION >= 3


def test_distance_is_the_worst_log_ratio_over_ekf_and_ukf():
    d = _script().distance
    paper = {"ekf": 2.0, "ukf": 1.0}
    assert d({"ekf": 2.0, "ukf": 1.0}, paper) == 0.0
    assert d({"ekf": 3.0, "ukf": 0.5}, paper) == pytest.approx(math.log(2.0))
    assert d({"ekf": float("nan"), "ukf": 1.0}, paper) == math.inf
