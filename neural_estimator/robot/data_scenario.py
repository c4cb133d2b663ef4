"""A scenario with no model: the names, units, angles and rate of a recorded robot's data.

Neural estimators need from a scenario only its interface: dimensions, which components are
angles, the sampling period, names and units. :class:`DataScenario` is that interface, built
from a dataset's meta (``neural-estimator dataset``) or a checkpoint card, so that training,
evaluation, the metrics and the checkpoint checks work on recorded data exactly as on the
simulated systems. It has no equations: ``f``, ``h``, the noise covariances and the prior raise
a one-line error, so a classical filter cannot be built on it (they need the model the data do
not give).

Its description (recorded in cards and compared when a checkpoint is loaded) is the spec's
digest, the rate and the vectors' names, units and angles: a model trained on one recording
loads for another recording made with the same spec, and is refused for a different spec.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

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
            cfg = DataConfig(
                dt=float(meta["dt"]),
                horizon=int(meta.get("horizon", 500)),
                spec_sha256=str(meta.get("spec_sha256", "")),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise ScenarioError(f"not the meta of a recorded dataset ({exc})") from None
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
        return {**super().describe(), "spec": self.spec}

    def _validate(self) -> None:
        if not self.config.dt > 0:
            raise ScenarioError(f"recorded data: dt must be positive, got {self.config.dt}")
        if self.config.horizon < 1:
            raise ScenarioError(f"recorded data: horizon must be >= 1, got {self.config.horizon}")

    # ---- no model ----------------------------------------------------------------------------
    def _no_model(self, what: str):
        raise ScenarioError(
            f"recorded data have no {what}: only the neural estimators (trained on the data) apply; "
            "a classical filter needs the system's equations"
        )

    def f(self, x: np.ndarray, u: np.ndarray | None = None) -> np.ndarray:
        self._no_model("dynamics f")

    def h(self, x: np.ndarray) -> np.ndarray:
        self._no_model("observation model h")

    def process_cov(self) -> np.ndarray:
        self._no_model("process noise Q")

    def obs_cov_nominal(self) -> np.ndarray:
        self._no_model("observation noise R")

    def prior(self) -> tuple[np.ndarray, np.ndarray]:
        self._no_model("prior")
