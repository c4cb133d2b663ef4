"""Ballistic re-entry: a body falling through an exponential atmosphere, tracked by range.

Athans, Wishner & Bertolini (1968), Julier & Uhlmann (2004), in the km scaling of SSMToybox
(jacobnzw/SSMToybox, ``ssmtoybox/dynsys.py``, reentry vehicle); the constants and the reason for
each are in :class:`BallisticConfig` below (docs/systems.md has the table).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from neural_estimator.scenarios._integrate import rk4, rk4_tangent
from neural_estimator.scenarios.base import Scenario, ScenarioError


@dataclass(frozen=True)
class BallisticConfig:
    """Constants of :class:`Ballistic` (km, s).

    Attributes:
        dt: sampling period [s]. 0.1 s, chosen so that 500 steps (50 s) end before any body
            reaches the ground (see :class:`Ballistic`); also SSMToybox's step.
        horizon: default trajectory length [steps].
        substeps: RK4 steps per sampling period; 2 (h = 0.05 s) keeps the integration error
            below 5e-8 km over the horizon, far under the process noise.
        g: gravitational acceleration [km/s^2].
        k: inverse density scale height [1/km] (6.096 km = 20,000 ft, the classic 5e-5 1/ft).
        r0: horizontal offset of the radar [km].
        a_ref: altitude of the radar [km].
        obs_noise_std: range noise std at noise_scale = 1 [km] (100 ft).
        process_noise_std: per-step std of the additive noise on (altitude [km], velocity
            [km/s], drag coefficient [1/km]); small, only so that the PF and EnKF are well posed.
        prior_mean: m0 = (altitude [km], velocity [km/s], drag coefficient [1/km]).
        prior_std: square roots of diag(P0) (P0 = diag(0.3048^2, 1.2192^2, 1e-4)).
        noise_scale: multiplies obs_noise_std.
    """

    dt: float = 0.1
    horizon: int = 500
    substeps: int = 2
    g: float = 9.81e-3
    k: float = 1.0 / 6.096
    r0: float = 30.0
    a_ref: float = 30.0
    obs_noise_std: float = 0.03048
    process_noise_std: tuple = (1e-3, 1e-3, 1e-4)
    prior_mean: tuple = (90.0, 6.0, 1.5)
    prior_std: tuple = (0.3048, 1.2192, 0.01)
    noise_scale: float = 1.0


class Ballistic(Scenario):
    """Ballistic re-entry with a range-only radar.

    State x = [a, v, c]: altitude [km], downward velocity [km/s], drag coefficient [1/km].
    Continuous dynamics (paper.tex, "Ballistic re-entry"):

        a' = -v
        v' = g - c v^2 E(a),   E(a) = min(exp(-k a), 1)
        c' = 0

    integrated by RK4 over ``dt`` in ``substeps`` steps; f is that map, and Q adds a small
    per-step noise. Observation: y_k = sqrt(r0^2 + (a_k - a_ref)^2) + nu_k, nu_k ~ N(0, R).

    Sampling period: the prior N([90, 6, 1.5], diag(0.3048^2, 1.2192^2, 1e-4)) was simulated
    without noise for 20,000 draws (RK4, h = 0.01 s). Bodies decelerate from 3-9 km/s to the
    terminal speed sqrt(g / c) ~ 0.08 km/s between 10 and 40 s and reach the ground
    (a = 0) after 60.8 s at the earliest, 63.3 s at the 0.1 % quantile, 75.8 s at the median.
    dt = 0.1 s puts the 500-step horizon at 50 s, before every impact in that sample, with
    altitudes of 1.4 / 2.4 / 4.8 km (1 / 50 / 99 %) at the last step; so E(a) = 1 (its
    kink) is never reached on the default horizon. dt = 0.12 s would already end below ground for
    the fastest bodies.

    Jacobians: f's by forward tangent propagation through the same RK4 stages (exact for the
    discrete map); h's analytically. The code is also complex-step safe (E uses ``np.where`` on
    the real part instead of ``min``), so the base class's complex-step Jacobian agrees.

    Calibration (``scripts/calibrate_scenarios.py --scenario ballistic``): not reached,
    constants unchanged. The paper's rows (EKF 5.29, UKF 0.63, EnKF 0.82, PF 0.66; EKF MedAE 0.90
    against the UKF's 0.15, EKF drift 3.8) need a regime where the EKF's linearisation fails and
    the UKF's does not. With these km constants the EKF and UKF agree to three digits
    (0.036 / 0.036 at 1,000 trajectories x 3 sets, paper x0.007 / x0.06) in every variant swept
    (100 trajectories, seed 1): range noise 0.03-1 km, prior std up to (3 km, 3 km/s, 0.3), dt 0.1-0.5 s
    (the latter past ground impact, where E(a) = 1): all give EKF = UKF = 0.04-0.22. A prior wide
    in the drag coefficient (std 1) makes some true bodies' drag negative and the simulation
    overflow, so the paper's "x0 std = 1.0" cannot be the spread of this prior. The PF started
    N(m0, 1.0^2 I) around this prior (drag 1.5 +- 1.0) diverges on 6 % of the trajectories.
    """

    name = "ballistic"
    Config = BallisticConfig
    state_names = ("altitude", "velocity", "drag_coefficient")
    state_units = ("km", "km/s", "1/km")
    obs_names = ("range",)
    obs_units = ("km",)

    # ---- the model -------------------------------------------------------------------------
    def _atmosphere(self, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """E(a) and dE/da; the min() written with np.where on the real part (complex-step safe)."""
        k = self.config.k
        above = np.real(a) > 0.0
        # exp of a very negative altitude would overflow in the branch np.where discards.
        e = np.where(above, np.exp(-k * np.where(above, a, 0.0)), 1.0)
        return e, np.where(above, -k * e, 0.0)

    def _field(self, x: np.ndarray) -> np.ndarray:
        a, v, c = x[..., 0], x[..., 1], x[..., 2]
        e, _ = self._atmosphere(a)
        return np.stack([-v, self.config.g - c * v * v * e, np.zeros_like(c)], axis=-1)

    def _field_jac(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        a, v, c = x[..., 0], x[..., 1], x[..., 2]
        e, de = self._atmosphere(a)
        field = np.stack([-v, self.config.g - c * v * v * e, np.zeros_like(c)], axis=-1)
        jac = np.zeros(x.shape + (3,), dtype=x.dtype)  # (..., 3, 3)
        jac[..., 0, 1] = -1.0
        jac[..., 1, 0] = -c * v * v * de
        jac[..., 1, 1] = -2.0 * c * v * e
        jac[..., 1, 2] = -v * v * e
        return field, jac

    def f(self, x: np.ndarray, u: np.ndarray | None = None) -> np.ndarray:
        """x_{k+1} = RK4 flow of the drag dynamics over dt; (..., 3) -> (..., 3)."""
        x = np.asarray(x)
        if not np.iscomplexobj(x):
            x = x.astype(np.float64, copy=False)
        cfg = self.config
        return rk4(self._field, x, cfg.dt / cfg.substeps, cfg.substeps)

    def jac_f(self, x: np.ndarray, u: np.ndarray | None = None) -> np.ndarray:
        """d f / d x by tangent propagation through RK4; (..., 3, 3)."""
        cfg = self.config
        _, phi = rk4_tangent(self._field_jac, np.asarray(x, dtype=np.float64), cfg.dt / cfg.substeps, cfg.substeps)
        return phi

    def h(self, x: np.ndarray) -> np.ndarray:
        """Range from the radar at (r0, a_ref); (..., 3) -> (..., 1)."""
        x = np.asarray(x)
        cfg = self.config
        d = x[..., 0] - cfg.a_ref
        return np.sqrt(cfg.r0**2 + d * d)[..., None]

    def jac_h(self, x: np.ndarray) -> np.ndarray:
        """d range / d x = [(a - a_ref) / range, 0, 0]; (..., 1, 3)."""
        x = np.asarray(x, dtype=np.float64)
        cfg = self.config
        d = x[..., 0] - cfg.a_ref
        jac = np.zeros(x.shape[:-1] + (1, 3))
        jac[..., 0, 0] = d / np.sqrt(cfg.r0**2 + d * d)
        return jac

    # ---- noise and prior -----------------------------------------------------------------------
    def process_cov(self) -> np.ndarray:
        return np.diag(np.square(np.asarray(self.config.process_noise_std, dtype=np.float64)))

    def obs_cov_nominal(self) -> np.ndarray:
        return np.array([[float(self.config.obs_noise_std) ** 2]])

    def prior(self) -> tuple[np.ndarray, np.ndarray]:
        cfg = self.config
        std = np.asarray(cfg.prior_std, dtype=np.float64)
        return np.asarray(cfg.prior_mean, dtype=np.float64), np.diag(std * std)

    def _validate(self) -> None:
        super()._validate()
        cfg = self.config
        if int(cfg.substeps) < 1:
            raise ScenarioError(f"scenario {self.name!r}: substeps must be >= 1, got {cfg.substeps}")
        if not cfg.obs_noise_std > 0:
            raise ScenarioError(f"scenario {self.name!r}: obs_noise_std must be positive, got {cfg.obs_noise_std}")
