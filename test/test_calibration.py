"""The calibrated scenario constants: the defaults (preset v4; N-link and bearings v5) recorded in
every file, the earlier constants one preset (or --set) away, the caches keyed by new revisions, non-physical draws
handled by a rule instead of a crash, and the calibration script's two distances."""

import importlib.util
import json
import math
from pathlib import Path

import numpy as np
import pytest

from neural_estimator import evaluation
from neural_estimator.data import protocol, simulate
from neural_estimator.paper import PAPER_SCENARIOS
from neural_estimator.scenarios import (
    ScenarioError,
    default_preset,
    make_scenario,
    preset_names,
    scenario_from_description,
)

ROOT = Path(__file__).resolve().parents[1]


def _script():
    spec = importlib.util.spec_from_file_location(
        "calibrate_scenarios", ROOT / "experiments" / "calibrate_scenarios.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


# The defaults (preset v4) where the spread calibration changed them, and the same constants in v3.
V4 = {
    "ballistic": {"dt": 0.01, "prior_std": [1.0, 1.0, 1.0]},
    "quadrotor": {"thrust_perturb_rel": 0.3, "prior_std": [1.0] * 6},
}
V3 = {
    "ballistic": {"dt": 0.1, "prior_std": [0.3048, 1.2192, 0.01]},
    "quadrotor": {"thrust_perturb_rel": 0.1, "prior_std": [1.0, 1.0, 0.1, 0.5, 0.5, 0.1]},
}
# Calibrated to the RMSE rows before (v3) and kept in v4; Lorenz 96 matched both distances already,
# N-link and bearings moved to the joint fit v5 (see docs/scenarios.md).
UNCHANGED = ("bearings", "lorenz96", "nlink")
# The joint fits that became the defaults of N-link and bearings (preset v5), and their v4 (= v3).
V5 = {
    "nlink": {"prior_angle_std": 1.0, "prior_rate_std": 0.1, "obs_noise_std": 0.01},
    "bearings": {"prior_mean": [-200.0, 4000.0, 2.0, 0.0], "accel_noise_std": 0.12},
}
V5_V4 = {
    "nlink": {"prior_angle_std": 0.1, "prior_rate_std": 0.1, "obs_noise_std": 0.02},
    "bearings": {"prior_mean": [-200.0, 400.0, 2.0, 0.0], "accel_noise_std": 0.3},
}


def _as_set(constants: dict) -> dict:
    """The constants as --set gives them (lists as comma-separated text)."""
    return {k: ",".join(map(str, v)) if isinstance(v, list) else v for k, v in constants.items()}


def _defaults_recorded(name: str, constants: dict, preset: str) -> dict:
    """The scenario's defaults hold ``constants``, are ``preset``, and every file records both."""
    s = make_scenario(name)
    desc = s.describe()
    for k, v in constants.items():
        assert desc["config"][k] == v, (k, desc["config"][k])
    assert desc["preset"] == default_preset(name) == preset
    data = simulate(s, 2, 3, seed=0)
    assert data.meta["config"] == desc["config"] and data.meta["preset"] == preset  # every file records both
    return desc


@pytest.mark.parametrize("name", sorted(V4))
def test_ballistic_and_quadrotor_defaults_are_preset_v4_and_recorded_in_files(name):
    _defaults_recorded(name, V4[name], "v4")


@pytest.mark.parametrize("name", sorted(V3))
def test_earlier_constants_are_one_preset_away_and_recorded_as_v3(name):
    old = make_scenario(name, preset="v3")
    desc = old.describe()
    for k, v in V3[name].items():
        assert desc["config"][k] == v
    assert desc["preset"] == "v3"
    # the same constants by --set are recognised as the preset too (files from before presets)
    by_set = make_scenario(name, **_as_set(V3[name]))
    assert by_set.describe() == desc
    # and a description read back from a file rebuilds them
    assert scenario_from_description(json.loads(json.dumps(desc))).describe() == desc


@pytest.mark.parametrize("name", UNCHANGED)
def test_scenarios_the_v4_calibration_kept_have_equal_v3_and_v4(name):
    v4 = make_scenario(name, preset="v4").describe()
    assert make_scenario(name, preset="v3").describe()["config"] == v4["config"]
    assert v4["preset"] == "v4"  # the newest preset wins a tie


@pytest.mark.parametrize("name", sorted(V5))
def test_nlink_and_bearings_defaults_are_the_joint_fit_v5_and_v4_one_preset_away(name):
    desc = _defaults_recorded(name, V5[name], "v5")
    old = make_scenario(name, preset="v4").describe()
    for k, v in V5_V4[name].items():
        assert old["config"][k] == v, (k, old["config"][k])
    # the rest of the constants unchanged, and v4's constants given by --set are recognised as v4
    assert {k: v for k, v in old["config"].items() if k not in V5[name]} == {
        k: v for k, v in desc["config"].items() if k not in V5[name]
    }
    by_set = make_scenario(name, **_as_set(V5_V4[name]))
    assert by_set.describe()["config"] == old["config"] and by_set.describe()["preset"] == "v4"


def test_every_paper_scenario_has_both_presets_and_an_unknown_one_is_a_one_line_error():
    for name in PAPER_SCENARIOS:
        assert preset_names(name)[-2:] == ["v4", "v3"]
        assert preset_names(name) == (["v5", "v4", "v3"] if name in ("nlink", "bearings") else ["v4", "v3"])
    with pytest.raises(ScenarioError) as info:
        make_scenario("ballistic", preset="v9")
    assert "no preset 'v9'" in str(info.value) and "v4, v3" in str(info.value) and "\n" not in str(info.value)


def test_set_applies_on_top_of_the_preset_and_makes_it_custom():
    s = make_scenario("ballistic", preset="v3", obs_noise_std=0.1)
    assert s.config.dt == 0.1 and s.config.obs_noise_std == 0.1
    assert s.describe()["preset"] == "custom"
    # noise scale and horizon describe an evaluation, not the system: still the preset
    assert make_scenario("ballistic", preset="v3", noise_scale=2.0, horizon=50).describe()["preset"] == "v3"


def test_cache_revisions_bumped_for_presets_and_the_new_defaults():
    assert protocol.SIMULATION_REVISION >= 6
    assert evaluation.RESULTS_REVISION >= 3


def test_ballistic_truncates_non_physical_draws_and_counts_them():
    s = make_scenario("ballistic")  # drag ~ N(1.5, 1): 6.7 % of the prior has c <= 0
    assert s.rejected_fraction() == pytest.approx(0.5 * math.erfc(1.5 / math.sqrt(2)), rel=1e-3)
    x0 = s.sample_initial(np.random.default_rng(0), 5000)
    assert (x0[:, 2] > 0).all() and (x0[:, 1] > 0).all()
    # the untruncated draw would have had about 6.7 % of them negative
    assert np.mean(x0[:, 2] < s.config.prior_mean[2]) < 0.5 - 0.03
    # deterministic in the seed
    np.testing.assert_array_equal(x0, s.sample_initial(np.random.default_rng(0), 5000))
    # a prior without mass there (v3) draws exactly the untruncated samples
    v3 = make_scenario("ballistic", preset="v3")
    assert v3.rejected_fraction() < 1e-6
    m0, p0 = v3.prior()
    rng = np.random.default_rng(4)
    np.testing.assert_array_equal(
        v3.sample_initial(np.random.default_rng(4), 100), m0 + rng.standard_normal((100, 3)) @ np.sqrt(p0)
    )


def test_a_wide_drag_prior_simulates_and_evaluates_without_an_error():
    s = make_scenario("ballistic", prior_std="0.3048,1.2192,1.0", dt=0.1)  # a reading that once crashed
    data = simulate(s, 40, seed=11)
    assert np.isfinite(data.x).all()


def test_a_trajectory_that_leaves_the_finite_range_is_a_one_line_error(monkeypatch):
    s = make_scenario("bearings")
    monkeypatch.setattr(type(s), "f", lambda self, x, u=None: x * 1e200)
    with pytest.raises(ScenarioError) as info:
        simulate(s, 3, 5, seed=0)
    assert "3 of 3 simulated trajectories left the finite range" in str(info.value)
    assert "\n" not in str(info.value)


def test_quadrotor_thrusts_are_clipped_at_zero():
    s = make_scenario("quadrotor", thrust_perturb_rel=2.0)
    u = s.sample_controls(np.random.default_rng(0), 50, 200)
    assert u.min() == 0.0 and (u == 0).mean() > 0.2
    v3 = make_scenario("quadrotor", preset="v3")  # 10 % of hover: 10 std from zero, nothing clipped
    assert v3.sample_controls(np.random.default_rng(0), 50, 200).min() > 0


def test_distance_is_the_worst_log_ratio_over_ekf_and_ukf():
    d = _script().distance
    paper = {"ekf": 2.0, "ukf": 1.0}
    assert d({"ekf": 2.0, "ukf": 1.0}, paper) == 0.0
    assert d({"ekf": 3.0, "ukf": 0.5}, paper) == pytest.approx(math.log(2.0))
    assert d({"ekf": float("nan"), "ukf": 1.0}, paper) == math.inf


def test_ratio_distance_uses_the_most_accurate_filter_and_the_papers_best_method():
    script = _script()
    res = {"ekf": {"rmse": 2.0, "nrmse": 0.5}, "ukf": {"rmse": 1.0, "nrmse": 0.1}}
    ratio, d = script.ratio_distance(res, 5.0)
    assert ratio == pytest.approx(10.0) and d == pytest.approx(math.log(2.0))
    assert script.ratio_distance({"ekf": {"rmse": math.inf, "nrmse": math.inf}}, 1.0) == (math.inf, math.inf)
    paper = script.PAPER_RATIO
    assert paper["lorenz96"][1] == pytest.approx(0.048 / 0.013, rel=1e-6)  # the UKF row (NRMSE 0.013)
    assert paper["quadrotor"] == ("ekf", pytest.approx(0.287 / 0.009, rel=1e-6))
    assert set(paper) == set(PAPER_SCENARIOS)


def test_every_candidate_names_a_preset_and_valid_constants():
    for name, table in _script().CANDIDATES.items():
        assert {"v3", "v4"} <= set(table) or name == "lorenz96", name
        assert {p for p, _, _ in table.values()} <= set(preset_names(name)), name
        assert default_preset(name) in table, name  # the defaults are a candidate of the search
        for label, (preset, overrides, _) in table.items():
            make_scenario(name, preset=preset, **overrides)  # raises on a bad constant


def test_a_candidate_that_cannot_be_simulated_prints_one_line_and_the_search_goes_on(capsys, monkeypatch):
    script = _script()
    monkeypatch.setitem(
        script.CANDIDATES,
        "lorenz96",
        {
            "bad": ("v4", {"n_vars": 5000}, "more variables than the package accepts"),
            "good": ("v4", {}, "the defaults"),
        },
    )
    assert script.main(["--scenario", "lorenz96", "--trajectories", "2", "--horizon", "20"]) == 0
    out = capsys.readouterr().out
    assert "- bad" in out and "not run:" in out and "Traceback" not in out
    assert "- good" in out and "d_rmse=" in out and "d_ratio=" in out


def test_the_preset_travels_in_bags_and_result_files():
    from neural_estimator.stream import messages as MSG
    from neural_estimator.evaluation import evaluate, results_json

    s = make_scenario("quadrotor", preset="v3")
    assert MSG.decode_scenario(MSG.encode_scenario(s.describe(), trajectories=1))["preset"] == "v3"
    res = evaluate(s, ["ekf"], trajectories=2, horizon=12, sets=1, cache_dir=False, progress=False)
    payload = json.loads(json.dumps(results_json(s, res, complete=True)))
    assert json.dumps(payload).count('"preset": "v3"') >= 1


def test_nlink_v5_is_the_joint_fit_and_recognised_by_its_constants():
    """N-link's v5 (angle std 1.0, rates 0.1, a 1 cm sensor) is the defaults; the same constants
    given by --set on top of v4 are recognised as v5 (a model trained on them is labelled so)."""
    assert make_scenario("nlink").describe()["preset"] == default_preset("nlink") == "v5"
    assert default_preset("oscillator") is None  # the example user scenario: no presets
    v5 = make_scenario("nlink", preset="v5")
    c = v5.config
    assert (c.prior_angle_std, c.prior_rate_std, c.obs_noise_std) == (1.0, 0.1, 0.01)
    assert v5.describe()["preset"] == "v5"
    by_set = make_scenario("nlink", preset="v4", prior_angle_std=1.0, prior_rate_std=0.1, obs_noise_std=0.01)
    assert by_set.describe()["preset"] == "v5" and by_set.describe()["config"] == v5.describe()["config"]
    m0, p0 = v5.prior()
    assert np.allclose(np.sqrt(np.diag(p0)), [1.0] * 3 + [0.1] * 3)


def test_bearings_v5_is_the_far_crossing_the_calibration_chose():
    assert make_scenario("bearings").describe()["preset"] == default_preset("bearings") == "v5"
    v5 = make_scenario("bearings", preset="v5")
    assert v5.config.prior_mean == (-200.0, 4000.0, 2.0, 0.0) and v5.config.accel_noise_std == 0.12
    assert v5.config.prior_std == make_scenario("bearings").config.prior_std  # the rest unchanged
    assert v5.describe()["preset"] == "v5"
    table = _script().CANDIDATES["bearings"]
    preset, overrides, _ = table["far4k-q0.12"]  # the candidate the calibration chose
    assert make_scenario("bearings", preset=preset, **overrides).describe()["preset"] == "v5"
