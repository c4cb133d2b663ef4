"""Adding a built-in scenario (docs/architecture.md, "Adding a built-in scenario"): a toy one, in a
temporary registry, needs its module, its registration and its docs line, and nothing of the paper's
(presets v3/v4, a calibrated filter entry, sample bags, zoo folders belong to PAPER_SCENARIOS).

The toy's module is written under tmp_path and imported as ``neural_estimator.scenarios.toy``, its
registration is one monkeypatched entry of the registry, its docs line a row added to an in-memory copy
of docs/scenarios.md: nothing is left behind (the last test checks it)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

import test_calibration
import test_filters_contract
import test_filters_references
import test_scenario_constants
import test_scenarios
import test_uncertainty
from neural_estimator import scenarios as S
from neural_estimator.data import simulate
from neural_estimator.paper import PAPER_SCENARIOS
from neural_estimator.methods.registry import CLASSICAL_METHODS, make_estimator

NAME = "toy"
MODULE = "neural_estimator.scenarios.toy"

# 1. its module (neural_estimator/scenarios/toy.py in a real change): a nonlinear oscillator with a
# cubic spring, seen through a monotone nonlinear sensor.
TOY_SOURCE = '''
from dataclasses import dataclass

import numpy as np

from neural_estimator.scenarios.base import Scenario


@dataclass(frozen=True)
class ToyConfig:
    dt: float = 0.05  # s
    horizon: int = 100
    noise_scale: float = 1.0
    stiffness: float = 1.0  # 1/s^2
    cubic: float = 0.5  # 1/(m^2 s^2)
    damping: float = 0.1  # 1/s
    process_noise_std: float = 0.05  # m/s per step, on the velocity
    obs_noise_std: float = 0.1  # m


class Toy(Scenario):
    """x = (position, velocity): p' = p + dt v, v' = v - dt (k p + c p^3 + d v); y = p + 0.5 sin p."""

    name = "toy"
    Config = ToyConfig
    state_names, state_units = ("position", "velocity"), ("m", "m/s")
    obs_names, obs_units = ("reading",), ("m",)

    def f(self, x, u=None):
        c, p, v = self.config, x[..., 0], x[..., 1]
        acc = -(c.stiffness * p + c.cubic * p**3 + c.damping * v)
        return np.stack([p + c.dt * v, v + c.dt * acc], axis=-1)

    def h(self, x):
        return x[..., :1] + 0.5 * np.sin(x[..., :1])

    def process_cov(self):
        return np.diag([1e-8, self.config.process_noise_std**2])

    def obs_cov_nominal(self):
        return np.array([[self.config.obs_noise_std**2]])

    def prior(self):
        return np.array([1.0, 0.0]), np.diag([0.3**2, 0.3**2])
'''

# 3. its docs line: a row of the table of systems in docs/scenarios.md
TOY_ROW = (
    "| `toy` | position [m], velocity [m/s] | p + 0.5 sin p [m] | – | 0.05 s | 100 | "
    "cubic spring k = 1, c = 0.5, damping 0.1, process noise 0.05, obs noise 0.1, prior N([1, 0], 0.3² I) |"
)


def _install(monkeypatch, tmp_path: Path) -> str:
    """Make the toy a built-in for the test's duration; returns the docs page with its row."""
    path = tmp_path / "toy.py"
    path.write_text(TOY_SOURCE)
    spec = importlib.util.spec_from_file_location(MODULE, path)
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, MODULE, module)
    spec.loader.exec_module(module)
    # 2. its registration: one entry of the registry (and so of BUILTIN_SCENARIOS, made from it)
    monkeypatch.setitem(S._REGISTRY, NAME, f"{MODULE}:Toy")
    monkeypatch.setattr(S, "BUILTIN_SCENARIOS", (*S.BUILTIN_SCENARIOS, NAME))
    page = test_scenarios.SCENARIOS_PAGE.read_text()
    last = [line for line in page.splitlines() if line.startswith("| `quadrotor` |")][0]
    return page.replace(last, last + "\n" + TOY_ROW, 1)


@pytest.fixture
def toy_page(monkeypatch, tmp_path):
    return _install(monkeypatch, tmp_path)


def test_the_every_builtin_tests_accept_the_toy(toy_page):
    assert NAME not in PAPER_SCENARIOS and NAME in S.BUILTIN_SCENARIOS
    test_scenarios.assert_builtin(NAME, toy_page)
    assert set(test_scenarios.documented_scenarios(toy_page)) == set(S.BUILTIN_SCENARIOS)
    for batch in [(), (5,), (2, 3)]:
        test_scenarios.test_shapes_over_leading_axes(NAME, batch)
    test_scenarios.test_jacobians_match_central_differences(NAME)
    test_scenarios.test_obs_cov_scales_with_noise_scale_squared(NAME)
    test_scenarios.test_overrides_and_unknown_names(NAME)
    test_scenarios.test_description_round_trips_through_json(NAME)
    test_scenario_constants.test_every_built_in_constant_is_within_its_bound()  # every registered name
    test_filters_references.test_obs_matrix_declarations_are_true(NAME)
    # without presets, a calibrated entry, sample bags or zoo folders: those tests are the paper's five's
    assert S.preset_names(NAME) == [] and S.default_preset(NAME) is None
    test_calibration.test_every_paper_scenario_has_both_presets_and_an_unknown_one_is_a_one_line_error()
    test_uncertainty.test_every_calibrated_filter_setting_was_chosen_on_its_scenarios_default_constants()


def test_a_page_without_the_toys_row_fails_the_docs_check(toy_page):
    """The docs line is needed: the same check on the page without the row fails."""
    with pytest.raises(AssertionError, match="no row"):
        test_scenarios.assert_builtin(NAME, toy_page.replace(TOY_ROW + "\n", ""))


@pytest.mark.parametrize("method", CLASSICAL_METHODS)
def test_the_toy_simulates_and_every_classical_filter_tracks_it(toy_page, method):
    scenario = S.make_scenario(NAME)
    tr = simulate(scenario, 16, seed=0)
    assert tr.x.shape == (16, 100, 2) and tr.y.shape == (16, 100, 1) and np.all(np.isfinite(tr.y))
    opts = {"n_particles": 256} if method == "pf" else {}
    out = make_estimator(method, scenario, seed=0, **opts).run(tr.y, tr.u)
    assert out.x.shape == tr.x.shape and not np.any(out.diverged)
    rmse = float(np.sqrt(np.mean((out.x[:, 20:, 0] - tr.x[:, 20:, 0]) ** 2)))
    open_loop = float(np.sqrt(np.mean((tr.x[:, 20:, 0] - tr.x[:, 20:, 0].mean(axis=0)) ** 2)))
    assert rmse < 0.5 * open_loop, (rmse, open_loop)  # it tracks the state, not the prior's mean
    assert rmse < 0.1  # below the observation noise (0.1 m, through a sensor of slope 0.5 to 1.5)


@pytest.mark.parametrize("method", CLASSICAL_METHODS)
def test_the_filter_contract_tests_accept_the_toy(toy_page, method):
    test_filters_contract.test_run_equals_loop_of_step(method, NAME)
    test_filters_contract.test_threads_do_not_change_results(method, NAME)
    if method in ("ekf", "ukf"):
        test_filters_contract.test_blocking_does_not_change_results(method, NAME)


def test_nothing_of_the_toy_is_left_behind(monkeypatch, tmp_path):
    with monkeypatch.context() as m:
        _install(m, tmp_path)
        assert S.make_scenario(NAME).name == NAME
    assert NAME not in S.scenario_names() and NAME not in S.BUILTIN_SCENARIOS
    assert MODULE not in sys.modules
    assert not (Path(S.__file__).parent / "toy.py").exists()
    with pytest.raises(S.ScenarioError, match="unknown scenario 'toy'"):
        S.make_scenario(NAME)
