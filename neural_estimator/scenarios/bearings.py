"""Bearings-only tracking of a constant-velocity target from a static sensor at the origin.

Gordon, Salmond & Smith (1993), "Novel approach to nonlinear/non-Gaussian Bayesian state
estimation", section 4, scaled by 1000 to metres as ``../shared/scenarios.md`` recommends;
Lascala & Morelande (2008) for the paper's framing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from neural_estimator.angles import wrap_angle
from neural_estimator.scenarios.base import Scenario, ScenarioError


@dataclass(frozen=True)
class BearingsConfig:
    """Constants of :class:`Bearings` (m, s, rad).

    Attributes:
        dt: sampling period T [s] (Gordon 1993).
        horizon: default trajectory length [steps].
        accel_noise_std: std of the per-step white acceleration [m/s^2] (Gordon's 0.001 x 1000).
        obs_noise_std: bearing noise std at noise_scale = 1 [rad] (Gordon 1993).
        prior_mean: m0 in the paper's order (px [m], py [m], vx [m/s], vy [m/s]); Gordon's
            (x, vx, y, vy) = (0, 0, 0.4, -0.05) x 1000, reordered.
        prior_std: square roots of diag(P0), same order; Gordon's (0.5, 0.005, 0.3, 0.01) x 1000.
        noise_scale: multiplies obs_noise_std.
    """

    dt: float = 1.0
    horizon: int = 500
    accel_noise_std: float = 1.0
    obs_noise_std: float = 0.005
    prior_mean: tuple = (0.0, 400.0, 0.0, -50.0)
    prior_std: tuple = (500.0, 300.0, 5.0, 10.0)
    noise_scale: float = 1.0


class Bearings(Scenario):
    """Bearings-only tracking (paper.tex, "Bearings-only tracking").

    State x = [px, py, vx, vy] (m, m/s). Constant-velocity dynamics with discrete white-noise
    acceleration a_k ~ N(0, sigma_a^2 I_2):

        x_{k+1} = F x_k + G a_k,   F = [[I, T I], [0, I]],   G = [[T^2/2 I], [T I]]
        Q = sigma_a^2 G G^T   (rank 2: position and velocity noise are fully correlated)

    Observation: the bearing from the origin, y_k = wrap(atan2(py, px)) + nu_k, nu_k ~ N(0, R),
    an angle (``angle_obs = (0,)``): innovations are wrapped to (-pi, pi].

    Range is unobservable from one static sensor. The typical target starts about 400 m north of
    the sensor heading south at about 50 m/s, so it passes the sensor's latitude after about 8
    steps, where the bearing changes fastest and the filters are tested hardest, and then
    recedes (about 25 km away at step 500).

    Jacobians are analytic: F, and d atan2(py, px) / d(px, py) = (-py, px) / (px^2 + py^2).
    """

    name = "bearings"
    Config = BearingsConfig
    state_names = ("px", "py", "vx", "vy")
    pose_states = {"x": 0, "y": 1, "vx": 2, "vy": 3}  # planar pose for Odometry output
    state_units = ("m", "m", "m/s", "m/s")
    obs_names = ("bearing",)
    obs_units = ("rad",)
    angle_obs = (0,)

    def _transition_matrix(self) -> np.ndarray:
        t = float(self.config.dt)
        return np.array(
            [[1.0, 0.0, t, 0.0], [0.0, 1.0, 0.0, t], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
        )

    def f(self, x: np.ndarray, u: np.ndarray | None = None) -> np.ndarray:
        """x_{k+1} = F x_k; (..., 4) -> (..., 4)."""
        x = np.asarray(x)
        t = float(self.config.dt)
        # Written out rather than as x @ F.T so that complex inputs pass through unchanged.
        return np.stack([x[..., 0] + t * x[..., 2], x[..., 1] + t * x[..., 3], x[..., 2], x[..., 3]], axis=-1)

    def jac_f(self, x: np.ndarray, u: np.ndarray | None = None) -> np.ndarray:
        """F, broadcast to (..., 4, 4)."""
        x = np.asarray(x)
        return np.broadcast_to(self._transition_matrix(), x.shape[:-1] + (4, 4)).copy()

    def h(self, x: np.ndarray) -> np.ndarray:
        """Bearing in (-pi, pi]; (..., 4) -> (..., 1)."""
        x = np.asarray(x, dtype=np.float64)
        # atan2 returns -pi for (py = -0.0, px < 0); wrap maps it to pi.
        return wrap_angle(np.arctan2(x[..., 1], x[..., 0]))[..., None]

    def jac_h(self, x: np.ndarray) -> np.ndarray:
        """d bearing / d x = [-py, px, 0, 0] / (px^2 + py^2); (..., 1, 4)."""
        x = np.asarray(x, dtype=np.float64)
        px, py = x[..., 0], x[..., 1]
        r2 = px * px + py * py
        jac = np.zeros(x.shape[:-1] + (1, 4))
        jac[..., 0, 0] = -py / r2
        jac[..., 0, 1] = px / r2
        return jac

    def process_cov(self) -> np.ndarray:
        t = float(self.config.dt)
        g = np.array([[0.5 * t * t, 0.0], [0.0, 0.5 * t * t], [t, 0.0], [0.0, t]])  # (4, 2)
        return float(self.config.accel_noise_std) ** 2 * (g @ g.T)

    def obs_cov_nominal(self) -> np.ndarray:
        return np.array([[float(self.config.obs_noise_std) ** 2]])

    def prior(self) -> tuple[np.ndarray, np.ndarray]:
        cfg = self.config
        std = np.asarray(cfg.prior_std, dtype=np.float64)
        return np.asarray(cfg.prior_mean, dtype=np.float64), np.diag(std * std)

    def _validate(self) -> None:
        super()._validate()
        if not self.config.obs_noise_std > 0:
            raise ScenarioError(
                f"scenario {self.name!r}: obs_noise_std must be positive, got {self.config.obs_noise_std}"
            )
