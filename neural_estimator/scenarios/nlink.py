"""N-link planar pendulum with point masses, observed through the masses' Cartesian positions.

Dynamics from the Lagrangian in paper.tex ("N-link pendulum"); constants (N = 3, lengths 1/N,
unit masses, g = 9.81, RK4 with dt = 0.01) as in VanderPlas's "triple pendulum chaos" notebook,
and the per-link process noise of Sarkka's pendulum (Bayesian Filtering and Smoothing, 2013,
pendulum example); see ``../shared/scenarios.md`` ("N-link pendulum").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from neural_estimator.scenarios._integrate import rk4, rk4_tangent
from neural_estimator.scenarios.base import Scenario, ScenarioError


@dataclass(frozen=True)
class NLinkConfig:
    """Constants of :class:`NLinkPendulum` (m, kg, s, rad).

    Attributes:
        dt: sampling period [s].
        horizon: default trajectory length [steps].
        substeps: RK4 steps per sampling period.
        n_links: N, the number of links (the state has 2N components, the observation 2N).
        total_length: sum of the link lengths [m]; every link is total_length / N long.
        mass: mass of each point mass [kg].
        g: gravitational acceleration [m/s^2].
        obs_noise_std: std of the noise on each Cartesian coordinate at noise_scale = 1 [m].
        process_noise_q: spectral density q of white noise on each angular acceleration
            [rad^2/s^3]; Q per link = q [[dt^3/3, dt^2/2], [dt^2/2, dt]] (Sarkka).
        prior_angle_std: std of each initial angle around hanging straight down [rad].
        prior_rate_std: std of each initial angular velocity [rad/s].
        noise_scale: multiplies obs_noise_std.
    """

    dt: float = 0.01
    horizon: int = 500
    substeps: int = 2
    n_links: int = 3
    total_length: float = 1.0
    mass: float = 1.0
    g: float = 9.81
    obs_noise_std: float = 0.05
    process_noise_q: float = 0.01
    prior_angle_std: float = 1.0
    prior_rate_std: float = 1.0
    noise_scale: float = 1.0


class NLinkPendulum(Scenario):
    """N-link pendulum (paper.tex, "N-link pendulum").

    State x = [theta_1..theta_N, omega_1..omega_N]; theta_j is link j's angle from the downward
    vertical, in (-pi, pi] (``angle_states``). With R_j = total_length / N, m_i = mass and
    mu_jk = sum_{i >= max(j, k)} m_i, the Lagrangian
    L = sum_i [1/2 m_i sum_{j,k <= i} R_j R_k w_j w_k cos(th_j - th_k) + m_i g sum_{j <= i} R_j cos th_j]
    gives the Euler-Lagrange equations

        sum_k M_jk(th) w'_k = -sum_k mu_jk R_j R_k sin(th_j - th_k) w_k^2 - mu_jj g R_j sin th_j,
        M_jk(th) = mu_jk R_j R_k cos(th_j - th_k),

    solved for w' by a batched linear solve. f is ``substeps`` RK4 steps over dt followed by
    wrapping the angles. Energy, conserved without noise:
    E = 1/2 w^T M(th) w - g sum_j mu_jj R_j cos th_j.

    Observation: the masses' Cartesian positions (x_i, z_i), x_i = sum_{j <= i} R_j sin th_j,
    z_i = -sum_{j <= i} R_j cos th_j (z up, pivot at the origin), ordered
    [x_1, z_1, ..., x_N, z_N], each with noise std ``obs_noise_std``.

    Process noise (Sarkka): white noise of density q on each angular acceleration, discretised
    per link as q [[dt^3/3, dt^2/2], [dt^2/2, dt]] on (theta_j, omega_j).

    Initial states: prior N(0, diag(prior_angle_std^2 I, prior_rate_std^2 I)) with 1 rad and
    1 rad/s. A 1 rad std puts a third of the links beyond 57 degrees, where sin th is far from
    linear. Measured over 2,000 noise-free draws and the 500-step horizon: the angular velocities'
    spread is 3.7 / 4.8 / 5.8 rad/s (links 1 / 2 / 3, peaks about 30 rad/s), and the outer link
    makes a full turn in 25 % of the trajectories: strongly nonlinear, coupled motion, still smooth
    on the 0.01 s scale.

    Integration: RK4 with h = dt / substeps = 0.005 s. Measured on 2,000 noise-free prior draws
    over the 500-step horizon, the energy drift relative to the depth of the potential well
    (sum_j G_j = 19.6 J) is 2e-6 (median), 2e-4 (99 %), 8e-4 (max); with substeps = 1 it is
    8e-5 / 5e-3 / 1e-2. Both are below what the process noise injects, but 2 keeps the
    integration error out of the comparison of filters at double the cost of 1.

    Jacobian of f: forward tangent propagation through the RK4 stages of the unwrapped step
    (wrapping has derivative 1), with the analytic Jacobian of the Euler-Lagrange right-hand side;
    the unwrapped step is also complex-step safe and the tests compare both.
    """

    name = "nlink"
    Config = NLinkConfig

    @property
    def n_links(self) -> int:
        return int(self.config.n_links)

    @property
    def state_names(self) -> tuple[str, ...]:
        n = self.n_links
        return tuple(f"theta{j + 1}" for j in range(n)) + tuple(f"omega{j + 1}" for j in range(n))

    @property
    def state_units(self) -> tuple[str, ...]:
        return ("rad",) * self.n_links + ("rad/s",) * self.n_links

    @property
    def obs_names(self) -> tuple[str, ...]:
        return tuple(name for j in range(self.n_links) for name in (f"x{j + 1}", f"z{j + 1}"))

    @property
    def obs_units(self) -> tuple[str, ...]:
        return ("m",) * (2 * self.n_links)

    @property
    def angle_states(self) -> tuple[int, ...]:
        return tuple(range(self.n_links))

    # ---- constants of the equations ------------------------------------------------------------
    def _constants(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(lengths R (N,), W_jk = mu_jk R_j R_k (N, N), gravity terms G_j = g mu_jj R_j (N,))."""
        cfg = self.config
        n = self.n_links
        lengths = np.full(n, float(cfg.total_length) / n)
        idx = np.arange(n)
        mu = float(cfg.mass) * (n - np.maximum(idx[:, None], idx[None, :]))  # sum over i >= max(j, k)
        weights = mu * lengths[:, None] * lengths[None, :]
        return lengths, weights, float(cfg.g) * np.diag(mu) * lengths

    # ---- the model -------------------------------------------------------------------------
    def _accel(self, th: np.ndarray, om: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Angular accelerations w' (..., N), with M (..., N, N) and S = W sin(th_j - th_k)."""
        _, weights, grav = self._constants()
        c, s = np.cos(th), np.sin(th)
        # cos/sin(th_j - th_k) by the angle-difference identities: 2N trig calls instead of 2N^2.
        cj, ck, sj, sk = c[..., :, None], c[..., None, :], s[..., :, None], s[..., None, :]
        mass = weights * (cj * ck + sj * sk)  # (..., N, N)
        skew = weights * (sj * ck - cj * sk)
        rhs = -(skew * (om * om)[..., None, :]).sum(axis=-1) - grav * s
        acc = np.linalg.solve(mass, rhs[..., None])[..., 0]
        return acc, mass, skew

    def _field(self, x: np.ndarray) -> np.ndarray:
        n = self.n_links
        th, om = x[..., :n], x[..., n:]
        acc, _, _ = self._accel(th, om)
        return np.concatenate([om, acc], axis=-1)

    def _field_jac(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The field and its Jacobian [[0, I], [dw'/dth, dw'/dw]].

        Differentiating M w' = rhs: M dw' = d rhs - (dM) w', with
        d(M w')_j/d th_l = -delta_jl (S w')_j + S_jl w'_l,
        d rhs_j / d th_l = -delta_jl (M w^2)_j + M_jl w_l^2 - delta_jl G_j cos th_j,
        d rhs_j / d w_l  = -2 S_jl w_l.
        """
        n = self.n_links
        _, _, grav = self._constants()
        th, om = x[..., :n], x[..., n:]
        acc, mass, skew = self._accel(th, om)
        om2 = om * om
        eye = np.eye(n)
        d_rhs_th = mass * om2[..., None, :] - eye * ((mass @ om2[..., None]) + (grav * np.cos(th))[..., None])
        d_mw_th = skew * acc[..., None, :] - eye * (skew @ acc[..., None])
        d_rhs_om = -2.0 * skew * om[..., None, :]
        lower = np.linalg.solve(mass, np.concatenate([d_rhs_th - d_mw_th, d_rhs_om], axis=-1))  # (..., N, 2N)
        upper = np.broadcast_to(np.concatenate([np.zeros((n, n)), eye], axis=-1), lower.shape)
        return np.concatenate([om, acc], axis=-1), np.concatenate([upper, lower], axis=-2)

    def step_unwrapped(self, x: np.ndarray) -> np.ndarray:
        """RK4 over dt without wrapping the angles (complex-step safe); (..., 2N) -> (..., 2N)."""
        x = np.asarray(x)
        if not np.iscomplexobj(x):
            x = x.astype(np.float64, copy=False)
        cfg = self.config
        return rk4(self._field, x, cfg.dt / cfg.substeps, cfg.substeps)

    def f(self, x: np.ndarray, u: np.ndarray | None = None) -> np.ndarray:
        """RK4 over dt, then angles wrapped to (-pi, pi]; (..., 2N) -> (..., 2N)."""
        return self.normalize_state(self.step_unwrapped(x))

    def jac_f(self, x: np.ndarray, u: np.ndarray | None = None) -> np.ndarray:
        """d f / d x by tangent propagation through RK4 (wrapping has derivative 1); (..., 2N, 2N)."""
        cfg = self.config
        _, phi = rk4_tangent(self._field_jac, np.asarray(x, dtype=np.float64), cfg.dt / cfg.substeps, cfg.substeps)
        return phi

    def h(self, x: np.ndarray) -> np.ndarray:
        """Positions of the masses [x_1, z_1, ..., x_N, z_N]; (..., 2N) -> (..., 2N)."""
        x = np.asarray(x)
        lengths, _, _ = self._constants()
        th = x[..., : self.n_links]
        px = np.cumsum(lengths * np.sin(th), axis=-1)
        pz = -np.cumsum(lengths * np.cos(th), axis=-1)
        return np.stack([px, pz], axis=-1).reshape(x.shape[:-1] + (2 * self.n_links,))

    def jac_h(self, x: np.ndarray) -> np.ndarray:
        """d x_i / d th_j = R_j cos th_j, d z_i / d th_j = R_j sin th_j for j <= i; (..., 2N, 2N)."""
        x = np.asarray(x, dtype=np.float64)
        n = self.n_links
        lengths, _, _ = self._constants()
        th = x[..., :n]
        below = np.tril(np.ones((n, n)))  # mass i depends on links j <= i
        jac = np.zeros(x.shape[:-1] + (2 * n, 2 * n))
        jac[..., 0::2, :n] = below * (lengths * np.cos(th))[..., None, :]
        jac[..., 1::2, :n] = below * (lengths * np.sin(th))[..., None, :]
        return jac

    def energy(self, x: np.ndarray) -> np.ndarray:
        """Total mechanical energy [J]; (..., 2N) -> (...)."""
        x = np.asarray(x, dtype=np.float64)
        n = self.n_links
        _, weights, grav = self._constants()
        th, om = x[..., :n], x[..., n:]
        mass = weights * np.cos(th[..., :, None] - th[..., None, :])
        kinetic = 0.5 * np.einsum("...j,...jk,...k->...", om, mass, om)
        return kinetic - (grav * np.cos(th)).sum(axis=-1)

    # ---- noise and prior -----------------------------------------------------------------------
    def process_cov(self) -> np.ndarray:
        cfg = self.config
        n, dt, q = self.n_links, float(cfg.dt), float(cfg.process_noise_q)
        eye = np.eye(n)
        return q * np.block([[dt**3 / 3 * eye, dt**2 / 2 * eye], [dt**2 / 2 * eye, dt * eye]])

    def obs_cov_nominal(self) -> np.ndarray:
        return float(self.config.obs_noise_std) ** 2 * np.eye(self.dy)

    def prior(self) -> tuple[np.ndarray, np.ndarray]:
        cfg = self.config
        n = self.n_links
        std = np.concatenate([np.full(n, float(cfg.prior_angle_std)), np.full(n, float(cfg.prior_rate_std))])
        return np.zeros(2 * n), np.diag(std**2)

    def sample_initial(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """n draws from the prior with the angles wrapped to (-pi, pi]."""
        return self.normalize_state(super().sample_initial(rng, n))

    def _validate(self) -> None:
        cfg = self.config
        if int(cfg.n_links) < 1:
            raise ScenarioError(f"scenario {self.name!r}: n_links must be >= 1, got {cfg.n_links}")
        if int(cfg.substeps) < 1:
            raise ScenarioError(f"scenario {self.name!r}: substeps must be >= 1, got {cfg.substeps}")
        if not (cfg.total_length > 0 and cfg.mass > 0):
            raise ScenarioError(f"scenario {self.name!r}: total_length and mass must be positive")
        super()._validate()
