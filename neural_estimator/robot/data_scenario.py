"""A scenario with no model: the names, units, angles and rate of a recorded robot's data.

Neural estimators need from a scenario only its interface: dimensions, which components are
angles, the sampling period, names and units. :class:`DataScenario` is that interface, built
from a dataset's meta (``neural-estimator dataset``) or a checkpoint card, so that training,
evaluation, the metrics and the checkpoint checks work on recorded data exactly as on the
simulated systems. Without a model it has no equations: ``f``, ``h``, the noise covariances and
the prior raise a one-line error, so a classical filter cannot be built on it (they need the
model the data do not give).

With a model (the spec's ``model:`` entry, recorded in the meta as ``model``: a registered
scenario, its preset and constants; :func:`model_scenario_of`) it delegates the equations to that
scenario: f, h and their Jacobians, the differentiable form, Q, R, the prior and the samplers, so
the classical filters and a hybrid (KalmanNet) run on the recording.

Its description (recorded in cards and compared when a checkpoint is loaded) is the spec's
digest, the rate and the vectors' names, units and angles, and with a model ``model_sha256``, the
SHA-256 of the model's description (every constant) and, for a plugin, of its source file: a model
trained on one recording loads for another recording made with the same spec and model, and is
refused for a different spec or model.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from neural_estimator.scenarios import code_digest, make_scenario
from neural_estimator.scenarios.base import MAX_DIMENSION, Scenario, ScenarioError

DATA_SCENARIO = "data"
# State names that make a pose for nav_msgs/Odometry output (the keys of Scenario.pose_states)
POSE_NAMES = ("x", "y", "z", "roll", "pitch", "yaw", "vx", "vy", "vz", "wx", "wy", "wz")


@dataclass(frozen=True)
class DataConfig:
    """The recording's constants: sampling period [s], trajectory length, the spec's digest."""

    dt: float = 0.05
    horizon: int = 500
    spec_sha256: str = ""
    noise_scale: float = 1.0
    model_sha256: str = ""  # with a model: model_digest() of it ("" without)


MODEL_KEYS = ("scenario", "preset", "set")


def model_scenario_of(entry: Any) -> Scenario:
    """The scenario a spec's ``model:`` entry names: ``{scenario: NAME, preset: P, set: {NAME: VALUE}}``
    (preset and set optional), built by :func:`~neural_estimator.scenarios.make_scenario` (a plugin's
    name once ``--plugin`` has loaded it); ScenarioError in one line otherwise."""
    if not isinstance(entry, Mapping) or set(entry) - set(MODEL_KEYS) or not isinstance(entry.get("scenario"), str):
        raise ScenarioError(
            f"model must be a mapping {{scenario: NAME, preset: P, set: {{NAME: VALUE}}}}, got {str(entry)[:100]}"
        )
    preset, constants = entry.get("preset"), entry.get("set") or {}
    if preset is not None and not isinstance(preset, str):
        raise ScenarioError(f"model: preset must be a name, got {preset!r}")
    if not isinstance(constants, Mapping) or not all(isinstance(k, str) for k in constants):
        raise ScenarioError(f"model: set must map constant names to values, got {str(constants)[:100]}")
    try:
        return make_scenario(entry["scenario"], preset, **constants)
    except (TypeError, ValueError) as exc:  # ScenarioError is a ValueError
        raise ScenarioError(f"model {entry['scenario']!r}: {exc}") from None


def model_digest(model: Scenario) -> str:
    """SHA-256 of a model's description (every constant) and, for a plugin, its source file's digest."""
    text = json.dumps({"model": model.describe(), "code": code_digest(model)}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


class DataScenario(Scenario):
    """The interface of recorded data (see the module docstring)."""

    name = DATA_SCENARIO
    Config = DataConfig

    def __init__(self, meta: dict[str, Any]) -> None:
        try:
            names = {
                k: tuple(str(v) for v in meta.get(k, ()))
                for k in ("state_names", "state_units", "obs_names", "obs_units", "control_names", "control_units")
            }
            angles = {k: tuple(int(i) for i in meta.get(k, ())) for k in ("angle_states", "angle_obs")}
            dt, horizon = float(meta["dt"]), int(meta.get("horizon", 500))
        except (KeyError, TypeError, ValueError) as exc:
            raise ScenarioError(f"not the meta of a recorded dataset ({exc})") from None
        self.model_entry = meta.get("model")
        self.system = None if self.model_entry is None else model_scenario_of(self.model_entry)
        cfg = DataConfig(
            dt=dt,
            horizon=horizon,
            spec_sha256=str(meta.get("spec_sha256", "")),
            model_sha256="" if self.system is None else model_digest(self.system),
        )
        for k in ("state", "obs", "control"):
            if len(names[f"{k}_names"]) > MAX_DIMENSION:
                raise ScenarioError(
                    f"recorded data: {len(names[f'{k}_names'])} {k} components, more than {MAX_DIMENSION}"
                )
            if len(names[f"{k}_units"]) != len(names[f"{k}_names"]):
                raise ScenarioError(
                    f"recorded data: {k} has {len(names[f'{k}_names'])} names but {len(names[f'{k}_units'])} units"
                )
        if not names["state_names"] or not names["obs_names"]:
            raise ScenarioError("recorded data: the state and the observation need at least one component")
        for key, n in (("angle_states", len(names["state_names"])), ("angle_obs", len(names["obs_names"]))):
            if any(not 0 <= i < n for i in angles[key]):
                raise ScenarioError(f"recorded data: {key} {list(angles[key])} out of range for {n} components")
        self.state_names, self.state_units = names["state_names"], names["state_units"]
        self.obs_names, self.obs_units = names["obs_names"], names["obs_units"]
        self.control_names, self.control_units = names["control_names"], names["control_units"]
        self.angle_states, self.angle_obs = angles["angle_states"], angles["angle_obs"]
        self.spec = meta.get("spec")
        # a state named like a pose (x, y, yaw, ...) is published as nav_msgs/Odometry by the nodes
        self.pose_states = {name: i for i, name in enumerate(self.state_names) if name in POSE_NAMES}
        super().__init__(cfg)
        if self.system is not None:
            self._check_model()

    @classmethod
    def from_description(cls, desc: dict[str, Any]) -> "DataScenario":
        """The scenario a card's ``scenario`` entry describes (see :meth:`describe`)."""
        cfg = desc.get("config", {})
        return cls(
            {
                **desc,
                "dt": cfg.get("dt", desc.get("dt")),
                "horizon": cfg.get("horizon", 500),
                "spec_sha256": cfg.get("spec_sha256", ""),
            }
        )

    def describe(self) -> dict[str, Any]:
        model = {} if self.model_entry is None else {"model": self.model_entry}
        return {**super().describe(), "spec": self.spec, **model}

    def _check_model(self) -> None:
        """The recorded vectors are the model's: dimensions, angles, period (the spec checked them;
        a meta or card edited since is refused here, in one line)."""
        m = self.system
        ours = (self.dx, self.dy, self.du, self.angle_states, self.angle_obs)
        theirs = (m.dx, m.dy, m.du, tuple(m.angle_states), tuple(m.angle_obs))
        if ours != theirs:
            raise ScenarioError(
                f"recorded data: (dx, dy, du, angle_states, angle_obs) = {ours}, but the model {m.name!r} has {theirs}"
            )
        if abs(m.dt - self.dt) > 1e-9 * self.dt:
            raise ScenarioError(f"recorded data: dt = {self.dt:g} s, but the model {m.name!r} has dt = {m.dt:g} s")

    def _validate(self) -> None:
        if not self.config.dt > 0:
            raise ScenarioError(f"recorded data: dt must be positive, got {self.config.dt}")
        if self.config.horizon < 1:
            raise ScenarioError(f"recorded data: horizon must be >= 1, got {self.config.horizon}")

    # ---- the model: the named scenario's, or none ---------------------------------------------
    def _model(self, what: str) -> Scenario:
        """The named scenario; without one, a one-line error saying only the networks apply."""
        if self.system is None:
            raise ScenarioError(
                f"recorded data have no {what}: only the neural estimators (trained on the data) apply; "
                "a classical filter needs the system's equations (name one with model: in the spec)"
            )
        return self.system

    def f(self, x: np.ndarray, u: np.ndarray | None = None) -> np.ndarray:
        return self._model("dynamics f").f(x, u)

    def h(self, x: np.ndarray) -> np.ndarray:
        return self._model("observation model h").h(x)

    def jac_f(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        return self._model("dynamics f").jac_f(x, u)

    def jac_h(self, x: np.ndarray) -> np.ndarray:
        return self._model("observation model h").jac_h(x)

    def torch_dynamics(self) -> Any:
        return None if self.system is None else self.system.torch_dynamics()

    def obs_matrix(self) -> np.ndarray | None:
        return None if self.system is None else self.system.obs_matrix()

    def state_from_observation(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        return None if self.system is None else self.system.state_from_observation(y)

    def process_cov(self) -> np.ndarray:
        return self._model("process noise Q").process_cov()

    def obs_cov_nominal(self) -> np.ndarray:
        return self._model("observation noise R").obs_cov_nominal()

    def obs_cov(self) -> np.ndarray:  # the model's noise_scale, not the data's
        return self._model("observation noise R").obs_cov()

    def prior(self) -> tuple[np.ndarray, np.ndarray]:
        return self._model("prior").prior()

    def sample_initial(self, rng: np.random.Generator, n: int) -> np.ndarray:
        return self._model("prior").sample_initial(rng, n)

    def sample_controls(self, rng: np.random.Generator, n: int, horizon: int) -> np.ndarray:
        return self._model("control law").sample_controls(rng, n, horizon)
