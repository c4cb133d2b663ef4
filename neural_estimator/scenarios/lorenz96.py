"""Lorenz 96 with every variable observed, in DAPPER's standard setup.

Lorenz (1996), "Predictability: a problem partly solved"; DAPPER (nansencenter/DAPPER,
``dapper/mods/Lorenz96/sakov2008.py``) for J = 40, F = 8, RK4 with dt = 0.05 and H = I; the
calibrated constants and the reason for each are in :class:`Lorenz96Config` below.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from neural_estimator.scenarios._integrate import by_component_blocks, rk4, rk4_tangent
from neural_estimator.scenarios.base import Scenario, ScenarioError

# A cyclic band matrix as {offset d (mod J): (..., J) coefficients}: (A v)_j = sum_d A_d[j] v_{j+d}.
# Products of band matrices stay band matrices, so the RK4 Jacobian is built from O(J) arrays
# instead of (J, J) matrix products.
Band = dict[int, np.ndarray]
_DENSE_JACOBIAN_MAX_BATCH = 8  # batches up to this size take the dense tangent path (see jac_f)
_RING_MAJOR_MIN_STATES = 16  # f on fewer states uses _field directly (no transposes to pay back)
_RING_MAJOR_CHUNK = 8192  # states per block of the ring-major RK4 (J = 40: 2.6 MiB a buffer; fastest measured)


@lru_cache(maxsize=64)
def _names(prefix: str, n: int) -> tuple[str, ...]:
    """("x0", ..., "x{n-1}"): built once per size (``dx`` / ``dy`` read them on every filter step)."""
    return tuple(f"{prefix}{j}" for j in range(n))


@dataclass(frozen=True)
class Lorenz96Config:
    """Constants of :class:`Lorenz96` (model time units).

    Attributes:
        dt: sampling period = RK4 step (DAPPER's 0.05, about 6 h of "weather").
        horizon: default trajectory length [steps].
        substeps: RK4 steps per sampling period (DAPPER: 1).
        n_vars: J, the number of variables on the ring; calibrated 10 (was DAPPER's 40), see
            "Calibration" in :class:`Lorenz96`.
        forcing: F (8: chaotic, leading Lyapunov exponent about 1.7 per time unit).
        obs_noise_std: std of the noise on each observed variable at noise_scale = 1;
            calibrated 0.07 (was 0.25).
        process_noise_std: std of the additive per-step model noise on each variable;
            calibrated 0.05 (was 0.003).
        spinup_steps: RK4 steps from a perturbed rest state F to the attractor in
            :meth:`Lorenz96.sample_initial`.
        spinup_perturb_std: std of the Gaussian perturbation of the rest state X = F.
        prior_mean: climatological mean of one variable (measured, see :class:`Lorenz96`).
        prior_std: climatological std of one variable (measured, see :class:`Lorenz96`).
        noise_scale: multiplies obs_noise_std.
    """

    dt: float = 0.05
    horizon: int = 500
    substeps: int = 1
    n_vars: int = 10
    forcing: float = 8.0
    obs_noise_std: float = 0.07
    process_noise_std: float = 0.05
    spinup_steps: int = 200
    spinup_perturb_std: float = 1.0
    prior_mean: float = 2.30
    prior_std: float = 3.62
    noise_scale: float = 1.0


class Lorenz96(Scenario):
    """Lorenz 96 (paper.tex, "Lorenz 96"), fully observed.

    State X in R^J on a ring (X_{j+J} = X_j):

        dX_j/dt = (X_{j+1} - X_{j-2}) X_{j-1} - X_j + F

    f is one sampling period of RK4 (``substeps`` steps of dt / substeps); x_{k+1} = f(x_k) + w_k
    with w_k ~ N(0, q^2 I). Observation y_k = x_k + v_k, v_k ~ N(0, sigma^2 I) (H = I).

    Initial states are on the attractor: :meth:`sample_initial` starts every trajectory from
    X = F + N(0, spinup_perturb_std^2) (the rest state X = F is an unstable fixed point) and runs
    ``spinup_steps`` = 200 noise-free steps (10 time units, about 17 e-foldings of the leading
    Lyapunov exponent). Measured with 4,000 members and perturbation std 1: the ensemble's mean
    and std over all variables reach the climatology (2.36 / 3.62) within 50 steps and stay
    there (2.33-2.35 / 3.63-3.64 at steps 100-800); 200 adds margin for decorrelating the members
    from the rest state, and costs 200 calls of f (2-5 s for 8,000 trajectories on 2 cores).

    The prior given to the filters is the climatology, N(mu 1, s^2 I) with mu = 2.30 and
    s = 3.62, measured with :func:`measure_climatology` (J = 10, F = 8, defaults): 2,000 members
    from the perturbed rest state, 1,000 steps discarded, then the mean and std over the next
    4,000 steps, all members and all variables (mu = 2.301, s = 3.621; J = 40 gives 2.342 /
    3.640, DAPPER quotes a climatological RMSE of about 3.6). The test suite re-measures them with
    a fresh, shorter spin-up. For other (n_vars, forcing), measure again and override
    ``prior_mean`` / ``prior_std``.

    Calibration (``experiments/calibrate_scenarios.py --scenario lorenz96``). The paper states neither
    J nor the noise levels. Its classical rows (EKF 0.049, UKF 0.048, EnKF 0.054, PF 0.065, all
    four close) include a bootstrap PF with 1,024 particles, x0 std 1.0 and no rejuvenation. With
    DAPPER's ring (J = 40, obs std 0.25, process std 0.003) EKF and UKF land at 0.052 but the PF
    cannot track at all (RMSE ~5 from the prior and from the truth, any noise pair tried): a
    1,024-particle cloud of unit spread in 40 dimensions puts all weight on one particle at the
    first update, and process noise at 1.2 % of the observation noise cannot spread the copies
    again. Searched: J in {40, 10, 5} x (obs std, process std) in {(0.25, 0.003), (0.1, 0.02),
    (0.07, 0.05), (0.05, 0.1), (0.03, 0.1)}, 20 trajectories, from the prior and from the truth.
    Only J <= 10 with a process noise comparable to the observation noise lets the PF track; J = 10,
    obs std 0.07, process std 0.05 reproduces the whole row (1,000 trajectories x 3 sets, EKF /
    UKF / EnKF, filters started at the true x0: 0.049 / 0.049 / 0.052; NRMSE 0.014 (paper
    0.013-0.015), AUC 24.6 / 24.6 / 26.0 (paper 23.7 / 23.2 / 26.1), NEES median 9.3 for dx = 10;
    the PF 0.07 on 20 trajectories, see docs/fidelity.md for the full row).
    From the prior (climatology, std 3.6) EKF, UKF and EnKF are unchanged but the PF's
    N(m0, 1.0^2 I) particles cover the truth too rarely: the paper's PF row needs the truth
    reading of its initialisation (``evaluate --init truth``). The previous constants stay
    reachable: ``--set n_vars=40 --set obs_noise_std=0.25 --set process_noise_std=0.003
    --set prior_mean=2.34 --set prior_std=3.64``.

    Jacobian: forward tangent propagation through RK4. The continuous Jacobian A is a cyclic band
    matrix with offsets -2, -1, 0, +1; each RK4 stage product stays banded (13 offsets for one
    step), so the Jacobian costs O(J) per stage and is scattered into a dense (J, J) at the end.
    """

    name = "lorenz96"
    dimension_fields = {"n_vars": 1}  # J variables: dx = dy = J
    Config = Lorenz96Config
    # Named constants (see neural_estimator.scenarios.base, "Presets"): v4 = the defaults above.
    presets = {"v4": {}, "v3": {}}

    @property
    def state_names(self) -> tuple[str, ...]:
        return _names("x", int(self.config.n_vars))

    @property
    def state_units(self) -> tuple[str, ...]:
        return ("",) * int(self.config.n_vars)

    @property
    def obs_names(self) -> tuple[str, ...]:
        return _names("y", int(self.config.n_vars))

    @property
    def obs_units(self) -> tuple[str, ...]:
        return ("",) * int(self.config.n_vars)

    # ---- the model -------------------------------------------------------------------------
    def _field(self, x: np.ndarray) -> np.ndarray:
        # dX_j/dt = (X_{j+1} - X_{j-2}) X_{j-1} - X_j + F on a ring. One wrap-padded copy
        # [X_{J-2}, X_{J-1}, X_0 .. X_{J-1}, X_0] and three slices of it replace three np.roll
        # copies (the UKF calls this on (2J+1) B sigma points four times a step).
        n = x.shape[-1]
        xp = np.concatenate((x[..., -2:], x, x[..., :1]), axis=-1)  # index j + 2 holds X_j
        out = xp[..., 3 : n + 3] - xp[..., 0:n]  # X_{j+1} - X_{j-2}
        out *= xp[..., 1 : n + 1]  # * X_{j-1}
        out -= x
        out += self.config.forcing
        return out

    def f(self, x: np.ndarray, u: np.ndarray | None = None) -> np.ndarray:
        """One sampling period of RK4; (..., J) -> (..., J).

        Bit for bit :func:`~neural_estimator.scenarios._integrate.rk4` of :meth:`_field` (the
        tests check it): the same operations on every number, in the same order. Batches of
        states (the UKF's 81 sigma points per stream, the PF's 1,024 particles) are integrated
        ring-major, see :meth:`_rk4_columns`; a few states take :meth:`_field` directly.
        """
        x = np.asarray(x)
        if not np.iscomplexobj(x):
            x = x.astype(np.float64, copy=False)
        cfg = self.config
        h = cfg.dt / cfg.substeps
        n = x.shape[-1]
        if x.size < _RING_MAJOR_MIN_STATES * n:
            return rk4(self._field, x, h, cfg.substeps)
        return by_component_blocks(x, _RING_MAJOR_CHUNK, lambda rows: self._rk4_columns(rows, h))

    def _rk4_columns(self, X: np.ndarray, h: float) -> np.ndarray:
        """RK4 in place on (J, c) contiguous states, in :func:`rk4`'s order of operations; returns X.

        Ring-major: in the (c, J) layout every shifted ring X_{j+d} is a strided view whose rows are
        only J numbers long, and numpy's per-row loop overhead costs about as much as the arithmetic.
        With the ring index first, X_{j+d} for all j is the contiguous block of rows j + d of a
        padded copy [X_{J-2}; X_{J-1}; X_0 .. X_{J-1}; X_0], so each operation is one long loop.
        """
        n = X.shape[0]
        forcing = self.config.forcing
        P = np.empty((n + 3,) + X.shape[1:], dtype=X.dtype)  # the padded stage state
        K, A, T = np.empty_like(X), np.empty_like(X), np.empty_like(X)
        mid = P[2 : n + 2]

        def field(out: np.ndarray) -> np.ndarray:
            # _field's operations in _field's order
            P[0:2] = mid[n - 2 : n]
            P[n + 2] = mid[0]
            np.subtract(P[3 : n + 3], P[0:n], out=out)  # X_{j+1} - X_{j-2}
            out *= P[1 : n + 1]  # * X_{j-1}
            out -= mid
            out += forcing
            return out

        for _ in range(self.config.substeps):
            mid[...] = X
            field(K)  # k1
            np.copyto(A, K)
            np.multiply(K, 0.5 * h, out=T)
            np.add(X, T, out=mid)  # x + 0.5 h k1
            field(K)  # k2
            np.multiply(K, 2.0, out=T)
            A += T  # k1 + 2 k2
            np.multiply(K, 0.5 * h, out=T)
            np.add(X, T, out=mid)  # x + 0.5 h k2
            field(K)  # k3
            np.multiply(K, 2.0, out=T)
            A += T  # + 2 k3
            np.multiply(K, h, out=T)
            np.add(X, T, out=mid)  # x + h k3
            field(K)  # k4
            A += K
            A *= h / 6.0
            X += A  # x + h/6 (k1 + 2 k2 + 2 k3 + k4)
        return X

    def _field_band(self, x: np.ndarray) -> Band:
        """The continuous Jacobian d(dX/dt)/dX at x as a band: offsets -2, -1, 0, +1 (mod J)."""
        n = x.shape[-1]
        xm1 = np.roll(x, 1, axis=-1)  # X_{j-1}
        return _band_add(
            {
                (-2) % n: -xm1,
                (-1) % n: np.roll(x, -1, axis=-1) - np.roll(x, 2, axis=-1),
                1 % n: xm1,
            },
            {0: np.full_like(x, -1.0)},
        )

    def _field_dense(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The field and its dense (..., J, J) Jacobian (four nonzeros a row)."""
        n = x.shape[-1]
        j = np.arange(n)
        A = np.zeros(x.shape + (n,))
        A[..., j, (j + 1) % n] = np.roll(x, 1, axis=-1)  # d/dX_{j+1}: X_{j-1}
        A[..., j, (j - 2) % n] = -np.roll(x, 1, axis=-1)  # d/dX_{j-2}: -X_{j-1}
        A[..., j, (j - 1) % n] = np.roll(x, -1, axis=-1) - np.roll(x, 2, axis=-1)  # d/dX_{j-1}
        A[..., j, j] = -1.0
        return self._field(x), A

    def jac_f(self, x: np.ndarray, u: np.ndarray | None = None) -> np.ndarray:
        """d f / d x by tangent propagation through RK4; (..., J, J).

        Small batches (the live node's B = 1) use dense J x J products, whose few large BLAS calls
        cost less than the banded path's many small numpy operations (1.1 ms -> ~0.2 ms at B = 1);
        large batches use the 13-diagonal banded form, which does ~J/13 times less arithmetic.
        """
        x = np.asarray(x, dtype=np.float64)
        cfg = self.config
        if x.size // x.shape[-1] <= _DENSE_JACOBIAN_MAX_BATCH:
            return rk4_tangent(self._field_dense, x, cfg.dt / cfg.substeps, cfg.substeps)[1]
        h = cfg.dt / cfg.substeps
        ones = np.ones_like(x)
        eye: Band = {0: ones}
        phi: Band | None = None
        for _ in range(cfg.substeps):
            k1 = self._field(x)
            x2 = x + 0.5 * h * k1
            k2 = self._field(x2)
            x3 = x + 0.5 * h * k2
            k3 = self._field(x3)
            x4 = x + h * k3
            d1 = self._field_band(x)
            d2 = _band_mul(self._field_band(x2), _band_add(eye, _band_scale(d1, 0.5 * h)))
            d3 = _band_mul(self._field_band(x3), _band_add(eye, _band_scale(d2, 0.5 * h)))
            d4 = _band_mul(self._field_band(x4), _band_add(eye, _band_scale(d3, h)))
            stages = _band_add(_band_add(d1, _band_scale(d2, 2.0)), _band_add(_band_scale(d3, 2.0), d4))
            step = _band_add(eye, _band_scale(stages, h / 6.0))
            phi = step if phi is None else _band_mul(step, phi)
            x = x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + self._field(x4))
        return _band_dense(phi)

    def h(self, x: np.ndarray) -> np.ndarray:
        """H = I; (..., J) -> (..., J)."""
        return np.array(x, copy=True)

    def torch_dynamics(self):
        """f and h in torch, differentiable (:class:`~neural_estimator.scenarios.differentiable.Lorenz96Torch`)."""
        from neural_estimator.scenarios.differentiable import Lorenz96Torch

        return Lorenz96Torch(self)

    def localization_distances(self) -> tuple[np.ndarray, np.ndarray]:
        """(d_xy, d_yy) for EnKF localisation: the cyclic index distance on the ring,
        d(i, j) = min(|i - j|, J - |i - j|); every observation sits on its variable (H = I)."""
        J = self.dx
        i = np.arange(J)
        d = np.abs(i[:, None] - i[None, :])
        d = np.minimum(d, J - d).astype(np.float64)
        return d, d.copy()

    def obs_matrix(self) -> np.ndarray:
        """H = I."""
        return np.eye(self.dx)

    def jac_h(self, x: np.ndarray) -> np.ndarray:
        """I, broadcast to (..., J, J)."""
        x = np.asarray(x)
        n = x.shape[-1]
        return np.broadcast_to(np.eye(n), x.shape[:-1] + (n, n)).copy()

    # ---- noise, prior and initial states -------------------------------------------------------
    def process_cov(self) -> np.ndarray:
        return float(self.config.process_noise_std) ** 2 * np.eye(self.dx)

    def obs_cov_nominal(self) -> np.ndarray:
        return float(self.config.obs_noise_std) ** 2 * np.eye(self.dy)

    def prior(self) -> tuple[np.ndarray, np.ndarray]:
        cfg = self.config
        return np.full(self.dx, float(cfg.prior_mean)), float(cfg.prior_std) ** 2 * np.eye(self.dx)

    def sample_initial(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """n states on the attractor (n, J): a perturbed rest state spun up for spinup_steps."""
        cfg = self.config
        x = cfg.forcing + cfg.spinup_perturb_std * rng.standard_normal((n, self.dx))
        for _ in range(int(cfg.spinup_steps)):
            x = self.f(x)
        return x

    def _validate(self) -> None:
        cfg = self.config
        if int(cfg.n_vars) < 4:
            raise ScenarioError(f"scenario {self.name!r}: n_vars must be >= 4, got {cfg.n_vars}")
        if int(cfg.substeps) < 1:
            raise ScenarioError(f"scenario {self.name!r}: substeps must be >= 1, got {cfg.substeps}")
        if int(cfg.spinup_steps) < 0:
            raise ScenarioError(f"scenario {self.name!r}: spinup_steps must be >= 0, got {cfg.spinup_steps}")
        super()._validate()


def measure_climatology(
    scenario: Lorenz96, n_members: int = 2000, burn_in: int = 1000, n_steps: int = 4000, seed: int = 0
) -> tuple[float, float]:
    """Climatological mean and std of one variable, from noise-free runs.

    ``n_members`` runs start at the perturbed rest state, discard ``burn_in`` steps, then the mean
    and std are taken over the next ``n_steps`` steps, all members and all variables (the system
    is invariant under cyclic shifts, so every variable has the same climatology).
    """
    cfg = scenario.config
    rng = np.random.default_rng(seed)
    x = cfg.forcing + cfg.spinup_perturb_std * rng.standard_normal((n_members, scenario.dx))
    for _ in range(burn_in):
        x = scenario.f(x)
    total = total_sq = 0.0
    for _ in range(n_steps):
        x = scenario.f(x)
        total += x.sum()
        total_sq += np.square(x).sum()
    count = n_steps * x.size
    mean = total / count
    return float(mean), float(np.sqrt(total_sq / count - mean * mean))


# ---- cyclic band matrices ------------------------------------------------------------------------
def _band_add(a: Band, b: Band) -> Band:
    out = dict(a)
    for d, coef in b.items():
        out[d] = out[d] + coef if d in out else coef
    return out


def _band_scale(a: Band, s: float) -> Band:
    return {d: s * coef for d, coef in a.items()}


def _band_mul(a: Band, b: Band) -> Band:
    """(A B)_{j, j+d1+d2} = A_{d1}[j] B_{d2}[j+d1]."""
    out: Band = {}
    for d1, ca in a.items():
        n = ca.shape[-1]
        for d2, cb in b.items():
            d = (d1 + d2) % n
            term = ca * np.roll(cb, -d1, axis=-1)
            out[d] = out[d] + term if d in out else term
    return out


def _band_dense(a: Band) -> np.ndarray:
    """(..., J) band coefficients -> (..., J, J) dense matrix."""
    coef0 = next(iter(a.values()))
    n = coef0.shape[-1]
    out = np.zeros(coef0.shape[:-1] + (n * n,), dtype=coef0.dtype)
    # Offset d fills (j, j + d) for j < n - d and (j, j + d - n) for j >= n - d: two strided
    # slices of the row-major flat matrix, much faster than fancy indexing at batch 8000.
    for d, coef in a.items():
        out[..., d : (n - d) * n : n + 1] = coef[..., : n - d]
        if d:
            out[..., (n - d) * n :: n + 1] = coef[..., n - d :]
    return out.reshape(coef0.shape + (n,))
