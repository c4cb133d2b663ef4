"""The model a model-based method is given, on purpose other than the system that made the data.

By default every filter is told the simulator's own equations and noise levels (its best case). A
*model set* (``--model-set NAME=VALUE`` on the command line, the nodes' ``model_set`` parameter)
gives the model-based methods (``table.has(m, needs_model=True)``: the filters, the baselines, the
hybrid) a *model scenario*: the data scenario's constants (preset and ``--set``) with the model set
on top. The data are simulated with the data scenario; data-trained networks never see either.

Two names are not constants but scales of the noise the model is told:

    Q_model = q Q(constants),    R_model = r R(constants)        (q, r > 0; default 1)

``Q=2`` tells the filters twice the process-noise covariance the system has (an over-cautious
model), ``R=0.5`` half the observation-noise covariance. They change only what the filters are
told (``process_cov()``, ``obs_cov()``), never ``noise_scale`` (which also scales what the
simulator draws).

A model scenario describes itself with its model set: ``describe()["model_set"]`` = the assignments
as given (so the result cache keys it and every output records it beside the preset).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from neural_estimator.scenarios.base import Scenario, ScenarioError, replace_config

NOISE_SCALES = ("Q", "R")  # model-only names: scales of the covariances the model is told


def parse_model_set(text: str | None) -> dict[str, str]:
    """``"forcing=8.5,g=9.0"`` (the nodes' parameter) as {name: value}; empty or None: {}."""
    out: dict[str, str] = {}
    for item in (text or "").split(","):
        if not item.strip():
            continue
        name, sep, value = item.partition("=")
        if not sep or not name.strip() or not value.strip():
            raise ScenarioError(f"model_set expects name=value[,name=value...], got {item.strip()!r}")
        out[name.strip()] = value.strip()
    return out


def _noise_scale(name: str, value: Any, scenario: str) -> float:
    try:
        scale = float(value)
    except (TypeError, ValueError):
        raise ScenarioError(f"scenario {scenario!r}: model {name} must be a number (a scale), got {value!r}") from None
    if not (np.isfinite(scale) and scale > 0):
        raise ScenarioError(f"scenario {scenario!r}: model {name} must be a finite scale > 0, got {value!r}")
    return scale


def model_scenario(scenario: Scenario, assignments: Mapping[str, Any] | None) -> Scenario:
    """The model scenario: ``scenario``'s constants with ``assignments`` on top (``Q``/``R`` scale the
    told covariances, see the module docstring). No assignments: ``scenario`` itself. Unknown names
    and bad values raise the scenario's own one-line :class:`ScenarioError`."""
    assignments = dict(assignments or {})
    if not assignments:
        return scenario
    constants = {k: v for k, v in assignments.items() if k not in NOISE_SCALES}
    q = _noise_scale("Q", assignments["Q"], scenario.name) if "Q" in assignments else 1.0
    r = _noise_scale("R", assignments["R"], scenario.name) if "R" in assignments else 1.0
    config = replace_config(scenario.config, constants, scenario=scenario.name)
    base = type(scenario)
    model = _model_class(base)(config=config)
    model._model_set = {k: str(v) for k, v in assignments.items()}
    model._q_scale, model._r_scale = q, r
    return model


def model_set_of(scenario: Scenario) -> dict[str, str]:
    """The model set a scenario was made with ({} for a data scenario)."""
    return dict(getattr(scenario, "_model_set", {}) or {})


_CLASSES: dict[type, type] = {}


def _model_class(base: type) -> type:
    """``base`` with the told covariances scaled and the model set in its description (one class per
    scenario class, so the scenario's name, dimensions and methods are its own)."""
    if base in _CLASSES:
        return _CLASSES[base]

    def process_cov(self) -> np.ndarray:
        return self._q_scale * base.process_cov(self)

    def obs_cov(self) -> np.ndarray:
        return self._r_scale * base.obs_cov(self)

    def describe(self) -> dict[str, Any]:
        out = base.describe(self)
        out["model_set"] = dict(self._model_set)
        return out

    cls = type(
        base.__name__,
        (base,),
        {
            "process_cov": process_cov,
            "obs_cov": obs_cov,
            "describe": describe,
            "_q_scale": 1.0,  # until model_scenario sets them (the constructor validates Q and R)
            "_r_scale": 1.0,
            "_model_set": {},
            "__module__": base.__module__,
            "__doc__": base.__doc__,
        },
    )
    _CLASSES[base] = cls
    return cls
