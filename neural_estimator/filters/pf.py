"""Bootstrap particle filter (sequential importance resampling), batched over B streams.

References: N. J. Gordon, D. J. Salmond and A. F. M. Smith, "Novel approach to nonlinear /
non-Gaussian Bayesian state estimation" (1993); A. Doucet and A. M. Johansen, "A tutorial on
particle filtering and smoothing" (2009), ESS-triggered resampling; systematic resampling as in
filterpy.monte_carlo.systematic_resample (the tests' reference particle filter is built from it).

The paper's settings (Table hparams): 1024 particles, x_0 std = 1.0, ESS fraction = 0.5,
rejuvenation std = 0.0. "x_0 std = 1.0" is read as: the initial particles are
x_0^i ~ N(m0, 1.0^2 I), isotropic around the prior mean m0, whatever the prior covariance P0 is
(``init_std=None`` draws them from the prior N(m0, P0) instead). ``reset(batch, initial_mean)``
centres them on given means instead of m0 (the offline protocol's ``init="truth"``: N(x_0, 1.0^2 I)).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import solve_triangular

from neural_estimator.filters.base import (
    PHASE_INIT,
    PHASE_PREDICT,
    PHASE_REGULARIZE,
    PHASE_REJUVENATE,
    PHASE_RESAMPLE,
    MemberFilter,
)
from neural_estimator.filters.kernels import compiled_model
from neural_estimator.filters.kernels import pf as pk
from neural_estimator.filters.kernels import rng as ck
from neural_estimator.filters.numerics import (
    LOG_W_FLOOR,
    effective_sample_size,
    normalize_log_weights,
    sqrt_factor,
    systematic_resample,
    weighted_covariance,
)
from neural_estimator.scenarios import Scenario


@dataclass(frozen=True)
class PFHyperParams:
    """Particle filter settings; defaults are the paper's (Table hparams)."""

    n_particles: int = 1024  # number of particles N
    init_std: float | None = 1.0  # x_0^i ~ N(m0, init_std^2 I); None: x_0^i ~ N(m0, P0)
    ess_fraction: float = 0.5  # resample (systematic) when ESS = 1 / sum w_i^2 < ess_fraction * N
    rejuvenation_std: float = 0.0  # std of isotropic Gaussian jitter added to particles after resampling
    regularization: float = 0.0  # not in the paper (0 = none): jitter bandwidth after resampling, x Musso's h_opt
    compiled: bool = True  # not in the paper: numba kernels for noise, f (Lorenz 96) and likelihood; false: numpy

    def validate(self) -> None:
        if int(self.n_particles) != self.n_particles or self.n_particles < 1:
            raise ValueError(f"n_particles must be an integer >= 1, got {self.n_particles}")
        if self.init_std is not None and not self.init_std > 0:
            raise ValueError(f"init_std must be > 0 or None, got {self.init_std}")
        if not 0.0 <= self.ess_fraction <= 1.0:
            raise ValueError(f"ess_fraction must be in [0, 1], got {self.ess_fraction}")
        if not self.rejuvenation_std >= 0:
            raise ValueError(f"rejuvenation_std must be >= 0, got {self.rejuvenation_std}")
        if not (isinstance(self.regularization, (int, float)) and 0.0 <= self.regularization < float("inf")):
            raise ValueError(f"regularization must be a finite number >= 0, got {self.regularization!r}")
        if not isinstance(self.compiled, bool):
            raise ValueError(f"compiled must be true or false, got {self.compiled!r}")


# ---- the maths: plain functions on the particles of b streams (the class below schedules them) --------
def _log_likelihood(X: np.ndarray, y: np.ndarray, *, ops, inv_sd: np.ndarray | None, white: np.ndarray | None):
    """log p(y | x_i) up to a constant, for particles X (b, N, n) and observations y (b, m):

    r_i = y - h(x_i)              (angles wrapped)
    l_i = -|W r_i|^2 / 2,         W = R^{-1/2}: 1 / sd for a diagonal R (inv_sd), else L_R^{-1} (white)
    """
    r = ops.obs_residual(y[:, None, :], ops.scenario.h(X))  # (b, N, m)
    r = r * inv_sd if inv_sd is not None else r @ white.T
    return -0.5 * np.einsum("bnm,bnm->bn", r, r)


def _weighted_estimate(X: np.ndarray, w: np.ndarray, *, ops) -> tuple[np.ndarray, np.ndarray]:
    """m = sum_i w_i x_i (circular for angles), P = sum_i w_i (x_i - m)(x_i - m)^T (residuals wrapped)."""
    mean = ops.state_mean(X, w)
    D = ops.state_residual(X, mean[:, None, :])
    return mean, weighted_covariance(D, w)


def _systematic_gather(X: np.ndarray, w: np.ndarray, offsets: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """The resampled particles of streams ``rows``: x_{idx_i}, idx by systematic resampling with one
    offset per stream (positions (u + i) / N against the cumulative weights); (r, N, n)."""
    N, n = X.shape[1], X.shape[2]
    idx = systematic_resample(w[rows], offsets[rows])  # (r, N) into each row's particles
    flat = (idx + (rows * N)[:, None]).ravel()
    return np.take(X.reshape(-1, n), flat, axis=0).reshape(rows.size, N, n)  # one row gather: fast


def _regularize(Xr: np.ndarray, P: np.ndarray, z: np.ndarray, scale: float, *, ops) -> np.ndarray:
    """Musso's kernel jitter x_i <- x_i + scale S z_i, S S^T = P by eigendecomposition (a collapsed
    ensemble's P is singular, and then the jitter stays in the span the particles still cover)."""
    lam, V = np.linalg.eigh(P)
    S = V * np.sqrt(np.clip(lam, 0.0, None))[:, None, :]
    return ops.normalize_state(Xr + scale * (z @ np.swapaxes(S, -1, -2)))


class ParticleFilter(MemberFilter):
    r"""Bootstrap particle filter with ESS-triggered systematic resampling.

    Particles X_i with log-weights l_i, i = 1..N; initially X_i ~ N(m0, init_std^2 I) and
    l_i = -log N.

    Predict (k >= 1), the transition as proposal:

        X_i <- f(X_i, u_{k-1}) + w_i,   w_i ~ N(0, Q)

    Update, the likelihood as weight (log space, normalised by log-sum-exp):

        r_i = y_k - h(X_i)                         (angles wrapped)
        l_i <- l_i - r_i^T R^{-1} r_i / 2,   w_i = exp(l_i) / sum_j exp(l_j)

    Estimate (before resampling, from the weighted particles; residuals wrapped, mean circular):

        m = sum_i w_i X_i,   P = sum_i w_i (X_i - m)(X_i - m)^T

    Resample (systematic) the streams whose ESS = 1 / sum_i w_i^2 < ess_fraction N, reset their
    weights to 1/N and, if rejuvenation_std > 0, add N(0, rejuvenation_std^2 I) jitter to the
    resampled particles. A stream whose weights or estimate go non-finite is flagged in
    ``diverged``.

    Regularisation (``regularization`` = c > 0; the regularised PF of Musso, Oudjane & Le Gland,
    "Improving regularised particle filters", 2001): the resampled particles of a stream are
    drawn from a Gaussian kernel density instead of the weighted Diracs,

        X_i <- X_i + c h_opt S eps_i,   eps_i ~ N(0, I),   S S^T = P (the weighted covariance above)
        h_opt = (4 / (N (n + 2)))^(1 / (n + 4))       (the kernel's optimal bandwidth for a
                                                       Gaussian density, n = dx)

    so the jitter follows the spread and shape of the ensemble; c = 1 is the optimal bandwidth,
    smaller values jitter less (less bias, less diversity). DAPPER's ``PartFilt(reg=r)`` uses
    Scott's rule N^(-1/(n+4)) instead: c = r N^(-1/(n+4)) / h_opt gives its jitter.

    Compiled kernels (``compiled=true``, the default): the predict step (f fused with the process
    noise where the scenario has a kernel: Lorenz 96, N-link, ballistic, bearings, quadrotor; the
    process noise everywhere), the likelihood (the scenario's h kernel, or any linear observation
    with diagonal R), the log-sum-exp normalisation of the weights, and the estimate (weighted mean,
    circular for angular states, and covariance, for any scenario with the base class's angle
    semantics) run as numba kernels (:mod:`neural_estimator.filters.kernels`: the scenario's own,
    looked up by its class, and the noise and weight kernels of its ``rng`` and ``pf``), fused per
    particle or over a stream's particles. Their process noise comes from per-stream keyed
    generators, not numpy's, so the two paths agree in distribution, and to rounding given the same
    draws (tested); ``compiled=false`` is the numpy reference path.
    """

    method = "pf"
    HyperParams = PFHyperParams
    require_definite_R = True

    def __init__(self, scenario, seed: int = 0, hyperparams=None, **options) -> None:
        super().__init__(scenario, seed=seed, hyperparams=hyperparams, **options)
        self.N = int(self.hp.n_particles)
        n = scenario.dx
        if self.hp.init_std is None:
            self._sqrt_init, self._sd_init = sqrt_factor(self.P0)
        else:
            self._sqrt_init, self._sd_init = float(self.hp.init_std) * np.eye(n), np.full(n, float(self.hp.init_std))
        # Whitening of the innovation: r^T R^{-1} r = |W r|^2 with W = L_R^{-1} (a constant, solved once).
        L_R = np.linalg.cholesky(self.R)
        R_diag = np.count_nonzero(self.R - np.diag(np.diag(self.R))) == 0
        self._inv_sd_R = 1.0 / np.sqrt(np.diag(self.R)) if R_diag else None
        self._white_R = None if R_diag else solve_triangular(L_R, np.eye(scenario.dy), lower=True)
        self._setup_compiled()

    def _setup_compiled(self) -> None:
        """Choose the compiled kernels that apply to this scenario (none with compiled=false)."""
        s = self.scenario
        self._compiled = bool(self.hp.compiled)
        # noise: sd (diagonal Q) or a full square root L; the unused one is empty
        self._ck_sd = self._sd_Q if self._sd_Q is not None else np.zeros(0)
        self._ck_L = np.ascontiguousarray(self._sqrt_Q) if self._sd_Q is None else np.zeros((0, 0))
        # the scenario's own f and h kernels, looked up by its class (none for a subclass, which may redefine f or h)
        model = compiled_model(s)
        self._ck_predict = model.predict
        self._ck_loglik = model.log_likelihood if self._inv_sd_R is not None else None
        # the weighted mean (circular for angles) and covariance: plain states, or the base class's
        # angle semantics (a scenario with its own mean or residual keeps the numpy path)
        cls, base = type(s), Scenario
        standard_angles = cls.state_mean is base.state_mean and cls.state_residual is base.state_residual
        self._ck_angles = None
        if self._compiled and (self.ops.plain_state or standard_angles):
            self._ck_angles = np.isin(np.arange(s.dx), list(s.angle_states))
        # likelihood otherwise: h(x) = H x, R diagonal, no angular observation
        H = s.obs_matrix()
        self._ck_H = None
        if self._ck_loglik is None and H is not None and self._inv_sd_R is not None and self.ops.plain_obs:
            H = np.ascontiguousarray(np.asarray(H, dtype=np.float64))
            self._ck_H = (H, bool(H.shape == (s.dy, s.dx) and np.array_equal(H, np.eye(s.dx))))

    def _init_state(self, B: int) -> None:
        draws = self._initial_draws(PHASE_INIT, self.N, self._sqrt_init, self._sd_init)
        self._X = self.ops.normalize_state(self._init_mean[:, None, :] + draws)
        self._logw = np.full((B, self.N), -np.log(self.N))
        self._w = np.full((B, self.N), 1.0 / self.N)

    def _predict(self, u: np.ndarray) -> None:
        if not self._compiled:
            return super()._predict(u)
        self._for_blocks(lambda i, sl: self._predict_compiled(sl, u[sl]))
        return None

    def _predict_compiled(self, sl: slice, u: np.ndarray) -> None:
        """The block's particles, in place: x <- f(x, u) + w, w from stream b's generator keyed by
        (seed, k, PHASE_PREDICT, b); f compiled and fused with the noise where there is a kernel."""
        X = self._X[sl]
        key = (self.seed, self._k, PHASE_PREDICT, sl.start)
        if self._ck_predict is not None:  # f, noise and the angle wrapping fused
            self._ck_predict(X, u, self._ck_L, self._ck_sd, key)
            return
        X[...] = self.scenario.f(X, self._broadcast_u(u, self.N))
        ck.add_process_noise(X, self._ck_L, self._ck_sd, *key)
        if not self.ops.plain_state:
            X[...] = self.ops.normalize_state(X)

    def _update(self, y: np.ndarray, skip: np.ndarray | None) -> None:
        compiled = self._compiled and (self._ck_loglik is not None or self._ck_H is not None)
        kernel = self._update_block_compiled if compiled else self._update_block
        logw, w, _ = self._blockwise(kernel, self._X, self._logw, y)
        self._logw, self._w = self._keep(skip, self._logw, logw), self._keep(skip, self._w, w)
        return None

    def _update_block(self, X: np.ndarray, logw: np.ndarray, y: np.ndarray):
        loglik = _log_likelihood(X, y, ops=self.ops, inv_sd=self._inv_sd_R, white=self._white_R)
        return (*normalize_log_weights(logw + loglik), None)

    def _update_block_compiled(self, X: np.ndarray, logw: np.ndarray, y: np.ndarray):
        logw = logw.copy()
        if self._ck_loglik is not None:
            self._ck_loglik(X, y, self._inv_sd_R, logw)
        else:
            pk.linear_log_likelihood(X, self._ck_H[0], self._ck_H[1], y, self._inv_sd_R, logw)
        w = np.empty_like(logw)
        pk.normalize_log_weights_rows(logw, w, LOG_W_FLOOR)
        return logw, w, None

    def _estimate(self) -> tuple[np.ndarray, np.ndarray]:
        mean, cov, _ = self._blockwise(self._estimate_block, self._X, self._w)
        self._spread = cov  # the weighted covariance P, which regularisation scales its jitter by
        return mean, cov

    @property
    def bandwidth(self) -> float:
        """Musso's optimal bandwidth h_opt = (4 / (N (n + 2)))^(1 / (n + 4)) for N particles in n dims."""
        n = self.scenario.dx
        return (4.0 / (self.N * (n + 2))) ** (1.0 / (n + 4))

    def _estimate_block(self, X: np.ndarray, w: np.ndarray):
        if self._ck_angles is not None:
            mean, cov = np.empty(X.shape[::2]), np.empty(X.shape[:1] + X.shape[2:] * 2)
            pk.weighted_moments(X, w, self._ck_angles, mean, cov)
            return mean, cov, None
        return (*_weighted_estimate(X, w, ops=self.ops), None)

    def _park(self, mask: np.ndarray) -> None:
        self._X = np.where(mask[:, None, None], self.m0, self._X)
        self._logw = np.where(mask[:, None], -np.log(self.N), self._logw)
        self._w = np.where(mask[:, None], 1.0 / self.N, self._w)

    def _after_estimate(self) -> None:
        """Systematic resampling of the streams whose ESS fell below ess_fraction * N, block by block
        on the worker threads, in place (most steps resample only some streams)."""
        self._for_blocks(self._resample_block)

    def _resample_block(self, block: int, sl: slice) -> None:
        X, logw, w = self._X[sl], self._logw[sl], self._w[sl]  # views: written in place
        offsets = self.block_rng(block, PHASE_RESAMPLE).random(X.shape[0])  # one per stream, used or not
        need = effective_sample_size(w) < self.hp.ess_fraction * self.N
        if not need.any():
            return
        rows = np.flatnonzero(need)
        N = self.N
        if self._compiled:  # the same systematic resampling, walked per row in place
            pk.systematic_resample_rows(X, w, offsets, need)
            if self.hp.rejuvenation_std <= 0 and self.hp.regularization <= 0:  # nothing else to do to X
                logw[rows] = -np.log(N)
                w[rows] = 1.0 / N
                return
            Xr = X[rows]
        else:
            Xr = _systematic_gather(X, w, offsets, rows)
        if self.hp.rejuvenation_std > 0:
            # drawn for every stream of the block, so a stream's numbers do not depend on the others
            z = self.block_rng(block, PHASE_REJUVENATE).standard_normal(X.shape)[rows]
            Xr = self.ops.normalize_state(Xr + self.hp.rejuvenation_std * z)
        if self.hp.regularization > 0:
            z = self.block_rng(block, PHASE_REGULARIZE).standard_normal(X.shape)[rows]
            scale = self.hp.regularization * self.bandwidth
            Xr = _regularize(Xr, self._spread[sl][rows], z, scale, ops=self.ops)
        X[rows] = Xr
        logw[rows] = -np.log(N)
        w[rows] = 1.0 / N
