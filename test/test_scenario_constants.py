"""Extreme constants are refused when a scenario is built, in one line naming the constant and its
bound: non-finite values always, magnitudes beyond MAX_CONSTANT unless the scenario bounds the
constant itself, and the work constants (integration substeps, Lorenz 96's spin-up) by WORK_BOUNDS,
so nothing runs for minutes or overflows into a traceback later."""

from __future__ import annotations

import dataclasses
import time

import pytest

from neural_estimator.scenarios import ScenarioError, make_scenario, scenario_names
from neural_estimator.scenarios.base import MAX_CONSTANT, WORK_BOUNDS

CASES = [
    ("ballistic", {"obs_noise_std": "1e308"}, "obs_noise_std = 1e+308 is outside [-1e+06, 1e+06]"),
    ("ballistic", {"dt": "1e308"}, "dt = 1e+308 is outside"),
    ("bearings", {"accel_noise_std": "nan"}, "accel_noise_std = nan is not a finite number"),
    ("lorenz96", {"forcing": "1e308"}, "forcing = 1e+308 is outside"),
    ("lorenz96", {"substeps": "1000000000"}, "substeps = 1e+09 is outside [1, 100], its bound"),
    ("lorenz96", {"spinup_steps": "1000000000"}, "spinup_steps = 1e+09 is outside [0, 100000], its bound"),
    ("nlink", {"substeps": "0"}, "substeps = 0 is outside [1, 100]"),
    ("quadrotor", {"prior_std": "1,1,1,1,inf,1"}, "prior_std = inf is not a finite number"),
    ("nlink", {"mass": "-inf"}, "mass = -inf is not a finite number"),
]


@pytest.mark.parametrize("name,overrides,words", CASES, ids=[f"{c[0]}-{next(iter(c[1]))}" for c in CASES])
def test_an_extreme_constant_is_refused_at_construction(name, overrides, words):
    t0 = time.perf_counter()
    with pytest.raises(ScenarioError) as info:
        make_scenario(name, **overrides)
    assert time.perf_counter() - t0 < 5.0  # refused before anything runs (a bound, not a timing)
    assert words in str(info.value) and "\n" not in str(info.value)


def test_every_built_in_constant_is_within_its_bound():
    # the bounds refuse no preset of the package: they leave every built-in system as it is
    for name in scenario_names():
        scenario = make_scenario(name)
        for preset in scenario.presets:
            make_scenario(name, preset=preset)
        for field in dataclasses.fields(scenario.config):
            lo, hi = WORK_BOUNDS.get(field.name, (-MAX_CONSTANT, MAX_CONSTANT))
            value = getattr(scenario.config, field.name)
            flat = value if isinstance(value, tuple) else (value,)
            for v in (x for e in flat for x in (e if isinstance(e, tuple) else (e,))):
                if isinstance(v, (int, float)) and not isinstance(v, bool):
                    assert lo <= v <= hi, (name, field.name, v)


def test_a_scenario_can_declare_a_wider_bound(oscillator):
    cls = type(make_scenario("oscillator"))  # examples/custom_scenario.py, registered by conftest
    wide = type("WideOscillator", (cls,), {"constant_bounds": {"omega": (0.0, 1e15)}})
    with pytest.raises(ScenarioError, match="MAX_CONSTANT"):
        cls(omega=1e9)
    assert wide(omega=1e9).config.omega == 1e9
    with pytest.raises(ScenarioError, match=r"omega = 1e\+16 is outside \[0, 1e\+15\], its bound"):
        wide(omega=1e16)
