"""N-link planar pendulum with point masses, observed through the masses' Cartesian positions.

Dynamics from the Lagrangian in paper.tex ("N-link pendulum"); constants (N = 3, lengths 1/N,
unit masses, g = 9.81, RK4 with dt = 0.01) as in VanderPlas's "triple pendulum chaos" notebook,
and the per-link process noise of Sarkka's pendulum (Bayesian Filtering and Smoothing, 2013,
pendulum example); the calibrated constants are in the config class below.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from neural_estimator.scenarios._integrate import by_component_blocks, rk4, rk4_tangent
from neural_estimator.scenarios.base import Scenario, ScenarioError

# States per block of the component-form RK4: enough that numpy's ~1 us per call (~70 calls a
# field evaluation at N = 3) is small per state, few enough that a block's rows stay in cache
# (measured at N = 3: 1.1 us a state-step with blocks of 1024, 0.7 with 8192, 1.4 with one
# block of 65,536).
_BLOCK = 8192


def _cos_sin(th: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """cos th and sin th from t = tan(th / 2): with u = 2 / (1 + t^2), cos = u - 1, sin = t u.

    One tan costs ~16 ns an element against ~24 ns for cos and sin, and the trigonometry is most of
    the field's cost. Both results are within a few ulp of 1 of cos and sin (tan is good to an ulp,
    the rest is rational), and the formulas are complex-step safe.
    """
    t = np.tan(0.5 * th)
    u = t * t
    u += 1.0
    np.divide(2.0, u, out=u)
    t *= u
    u -= 1.0
    return u, t


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
        obs_noise_std: std of the noise on each Cartesian coordinate at noise_scale = 1 [m];
            calibrated 0.01 (preset v4: 0.02; first 0.05), see "Calibration" in
            :class:`NLinkPendulum`.
        process_noise_q: spectral density q of white noise on each angular acceleration
            [rad^2/s^3]; Q per link = q [[dt^3/3, dt^2/2], [dt^2/2, dt]] (Sarkka).
        prior_angle_std: std of each initial angle around hanging straight down [rad]; the
            paper's 1.0 (preset v4: 0.1).
        prior_rate_std: std of each initial angular velocity [rad/s]; calibrated 0.1 (was 1.0).
        noise_scale: multiplies obs_noise_std.
    """

    dt: float = 0.01
    horizon: int = 500
    substeps: int = 2
    n_links: int = 3
    total_length: float = 1.0
    mass: float = 1.0
    g: float = 9.81
    obs_noise_std: float = 0.01
    process_noise_q: float = 0.01
    prior_angle_std: float = 1.0
    prior_rate_std: float = 0.1
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

    solved for w' by a batched linear solve (``_field``, the reference) or, for large batches, an
    L D L^T factorisation of M unrolled over the components (``_accel_components``). f is
    ``substeps`` RK4 steps over dt followed by wrapping the angles. Energy, conserved without noise:
    E = 1/2 w^T M(th) w - g sum_j mu_jj R_j cos th_j.

    Observation: the masses' Cartesian positions (x_i, z_i), x_i = sum_{j <= i} R_j sin th_j,
    z_i = -sum_{j <= i} R_j cos th_j (z up, pivot at the origin), ordered
    [x_1, z_1, ..., x_N, z_N], each with noise std ``obs_noise_std``.

    Process noise (Sarkka): white noise of density q on each angular acceleration, discretised
    per link as q [[dt^3/3, dt^2/2], [dt^2/2, dt]] on (theta_j, omega_j).

    Initial states: prior N(0, diag(prior_angle_std^2 I, prior_rate_std^2 I)), 1 rad and
    0.1 rad/s since the second calibration (below; 0.1 rad in preset v4). With 1 rad and 1 rad/s, a third of the
    links started beyond 57 degrees; measured over 2,000 noise-free draws and the 500-step horizon
    the angular velocities' spread was 3.7 / 4.8 / 5.8 rad/s (links 1 / 2 / 3) and the outer link
    made a full turn in 25 % of the trajectories.

    Calibration (``experiments/calibrate_scenarios.py --scenario nlink``), in two rounds. The
    first (preset ``v4``) fitted the RMSE rows alone. The paper's rows
    (EKF 0.080, UKF 0.081, EnKF 0.092, PF 0.086; MAE / RMSE = 0.79, no heavy tail; drift 1.01-1.06)
    describe a smooth regime in which all four filters track. The previous constants gave EKF / UKF
    0.31 / 0.31 (100 trajectories, seed 1; 3.9x the paper) with MedAE 0.04: a few trajectories
    whose wide initial error (1 rad, 1 rad/s) the filters take long to remove; starting the filters
    at the true x_0 (``--init truth``) still gave 0.21. Swept (50-100 trajectories, seed 1, EKF /
    UKF): prior std 0.1 or 0.3 with obs noise 0.1 / 0.05 / 0.03 / 0.02: 0.30 / 0.16 / 0.11 / 0.082
    at 0.1; process density q 0.0001-0.01 moves the RMSE by under 10 %. Chosen: prior std 0.1 rad
    and 0.1 rad/s, obs noise 0.02 m, q unchanged: EKF 0.0816, UKF 0.0812 (x1.02, x1.00). Our
    MedAE (0.016) is a third of the paper's (0.053): the paper's errors are spread more evenly.
    ``--set obs_noise_std=0.05 --set prior_angle_std=1.0 --set prior_rate_std=1.0`` gives the
    first constants.

    The second round (the defaults, preset ``v5``) fitted the RMSE rows and the spread of the true
    states jointly: v4's spread is 12x short of the paper's (RMSE / NRMSE 0.58 against 6.1-6.8;
    distances 0.06 on the RMSE rows, 2.47 on the spread). The paper's angle std 1.0, the links
    released nearly at rest (0.1 rad/s) and a 1 cm position sensor give 0.23 / 0.78 and
    0.26 / 0.63 (seeds 1, 2); docs/scenarios.md, "The calibration".

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
    dimension_fields = {"n_links": 2}  # N links: dx = dy = 2N
    Config = NLinkConfig
    # Named constants (see neural_estimator.scenarios.base, "Presets"): v5 = the defaults above,
    # the operating point fitted to the paper's RMSE rows and the spread of its true states jointly
    # (docs/scenarios.md, "The calibration"); v4 (= v3) the fit of the RMSE rows alone.
    presets = {
        "v5": {},
        "v4": {"prior_angle_std": 0.1, "obs_noise_std": 0.02},
        "v3": {"prior_angle_std": 0.1, "obs_noise_std": 0.02},
    }

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

    def _accel_components(self, th: np.ndarray, om: np.ndarray, weights: list, neg_grav: np.ndarray) -> np.ndarray:
        """Angular accelerations in component form: (N, m) angle and rate rows -> (N, m).

        Every operation below acts on rows of m states: O(N^2) of them build M and rhs, O(N^3)
        factorise and solve. With c_j = cos th_j and s_j = sin th_j:
        M_jk = W_jk (c_j c_k + s_j s_k), whose diagonal W_jj is constant;
        S_jk = W_jk (s_j c_k - c_j s_k) = -S_kj; rhs_j = -sum_k S_jk w_k^2 - G_j s_j.
        M is a mass matrix, symmetric positive definite, so M = L D L^T (Cholesky without square
        roots) needs no pivoting: eliminating column j from the upper triangle,
        a_ik -= L_ij a_jk for k >= i > j with L_ij = a_ji / d_j, d_j = a_jj, also turns rhs into
        L^-1 rhs; back substitution then gives w'_j = rhs_j / d_j - sum_{k > j} L_kj w'_k.
        """
        n = self.n_links
        c, s = _cos_sin(th)
        om2 = om * om
        acc = s * neg_grav  # -G_j s_j; becomes rhs, then L^-1 rhs, then w' in place
        c, s, om2, rhs = list(c), list(s), list(om2), list(acc)
        a = [[None] * n for _ in range(n)]  # upper triangle of M, then L_ij below the diagonal
        for j in range(n):
            a[j][j] = weights[j][j]  # cos 0 = 1
            for k in range(j + 1, n):
                skew = (s[j] * c[k] - c[j] * s[k]) * weights[j][k]
                rhs[j] -= skew * om2[k]
                rhs[k] += skew * om2[j]
                a[j][k] = (c[j] * c[k] + s[j] * s[k]) * weights[j][k]
        inv_d = []
        for j in range(n):
            inv_d.append(1.0 / a[j][j])
            for i in range(j + 1, n):
                a[i][j] = a[j][i] * inv_d[j]
                for k in range(i, n):
                    a[i][k] -= a[i][j] * a[j][k]
                rhs[i] -= a[i][j] * rhs[j]
        for j in reversed(range(n)):
            rhs[j] *= inv_d[j]
            for k in range(j + 1, n):
                rhs[j] -= a[k][j] * rhs[k]
        return acc

    def _step_components(self, x: np.ndarray) -> np.ndarray:
        """:meth:`step_unwrapped` in component form, real or complex; (..., 2N) -> (..., 2N).

        Blocks of ``_BLOCK`` states are transposed once to contiguous (2N, m) rows
        (:func:`by_component_blocks`), the whole RK4 runs on the angle and rate rows (the field
        is (w, w'), so only w' needs :meth:`_accel_components`), and the result is transposed back. The stages
        are those of
        :func:`rk4`, x_i = x + c_i h k_{i-1}, with h/6 (k1 + 2 k2 + 2 k3 + k4) summed as they come.
        """
        cfg = self.config
        n, h = self.n_links, cfg.dt / cfg.substeps
        _, weights, grav = self._constants()
        weights, neg_grav = weights.tolist(), -grav[:, None]

        def integrate(rows: np.ndarray) -> np.ndarray:
            th, om = rows[:n], rows[n:]
            for _ in range(cfg.substeps):
                k_th, k_om = om, self._accel_components(th, om, weights, neg_grav)
                new_th, new_om = th + (h / 6.0) * k_th, om + (h / 6.0) * k_om
                for to_stage, weight in ((0.5 * h, h / 3.0), (0.5 * h, h / 3.0), (h, h / 6.0)):
                    stage_om = om + to_stage * k_om
                    k_th, k_om = stage_om, self._accel_components(th + to_stage * k_th, stage_om, weights, neg_grav)
                    new_th += weight * k_th
                    new_om += weight * k_om
                th, om = new_th, new_om
            rows[:n], rows[n:] = th, om
            return rows

        return by_component_blocks(x, _BLOCK, integrate)

    def step_unwrapped(self, x: np.ndarray) -> np.ndarray:
        """RK4 over dt without wrapping the angles (complex-step safe); (..., 2N) -> (..., 2N).

        Batches of at least 4 N^2 states run in component form (:meth:`_step_components`, under
        1 us a state at N = 3); smaller ones through :func:`rk4` of the (..., N, N)
        :meth:`_field`, the reference formulation, which makes fewer numpy calls (crossovers
        measured near 20 states at N = 3 and 100 at N = 5, none at N = 1).
        """
        x = np.asarray(x)
        if not np.iscomplexobj(x):
            x = x.astype(np.float64, copy=False)
        if x.size // x.shape[-1] >= 4 * self.n_links**2:
            return self._step_components(x)
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

    def state_from_observation(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The angles from the mass positions, th_j = atan2(dx_j, -dz_j) with (dx_j, dz_j) the
        j-th link's vector p_j - p_{j-1} (p_0 the pivot); the rates are not observed (prior mean)."""
        y = np.asarray(y, dtype=np.float64)
        n = self.n_links
        p = y.reshape(y.shape[:-1] + (n, 2))  # (..., N, [x, z])
        d = np.diff(p, axis=-2, prepend=np.zeros_like(p[..., :1, :]))  # link vectors
        x = np.broadcast_to(np.asarray(self.prior()[0], dtype=np.float64), y.shape[:-1] + (2 * n,)).copy()
        x[..., :n] = np.arctan2(d[..., 0], -d[..., 1])
        observed = np.zeros(2 * n, dtype=bool)
        observed[:n] = True
        return x, observed

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

    def torch_dynamics(self):
        """f and h in torch, differentiable (:class:`~neural_estimator.scenarios.differentiable.NLinkTorch`)."""
        from neural_estimator.scenarios.differentiable import NLinkTorch

        return NLinkTorch(self)

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
