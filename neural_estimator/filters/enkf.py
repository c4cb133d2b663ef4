"""Stochastic ensemble Kalman filter (perturbed observations), batched over B streams.

References: G. Evensen, "Sequential data assimilation with a nonlinear quasi-geostrophic model
using Monte Carlo methods to forecast error statistics" (1994); G. Burgers, P. J. van Leeuwen and
G. Evensen, "Analysis scheme in the ensemble Kalman filter" (1998), perturbed observations;
filterpy's ``EnsembleKalmanFilter`` (the tests' independent implementation). The paper uses 50
members (Table hparams) and no inflation or localisation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from neural_estimator.filters.kernels import enkf as compiled_enkf
from neural_estimator.filters.base import (
    PHASE_INIT,
    PHASE_PREDICT,
    PHASE_UPDATE,
    MemberFilter,
    check_inflation,
    compiled_applies,
)
from neural_estimator.filters.kernels import compiled_model
from neural_estimator.filters.localization import localization_tapers
from neural_estimator.filters.numerics import (
    ScenarioOps,
    gaussian,
    psd_solve,
    sqrt_factor,
    weighted_covariance,
    weighted_cross_covariance,
)


@dataclass(frozen=True)
class EnKFHyperParams:
    """EnKF settings; defaults are the paper's (Table hparams: ensemble size 50)."""

    n_members: int = 50  # ensemble size N
    inflation: float = 1.0  # not in the paper (1 = none): multiplies forecast anomalies before the update
    q_inflation: float = 1.0  # not in the paper (1 = none): multiplies the process noise covariance Q
    localization_radius: float | None = None  # not in the paper (None = none): Gaspari-Cohn half-support c

    def validate(self) -> None:
        if int(self.n_members) != self.n_members or self.n_members < 2:
            raise ValueError(f"n_members must be an integer >= 2, got {self.n_members}")
        check_inflation(self.inflation, self.q_inflation)
        r = self.localization_radius
        if r is not None and (isinstance(r, bool) or not isinstance(r, (int, float)) or not 0.0 < r < float("inf")):
            raise ValueError(f"localization_radius must be a finite number > 0 or null, got {r!r}")


# ---- the maths: plain functions on arrays of b streams (the class below only schedules them) ----------
def _update(
    X: np.ndarray,
    y: np.ndarray,
    rng: np.random.Generator,
    *,
    ops: ScenarioOps,
    R: np.ndarray,
    sqrt_R: np.ndarray,
    sd_R: np.ndarray | None,
    inflation: float,
    rho: tuple[np.ndarray, np.ndarray] | None,
) -> np.ndarray:
    """Update with perturbed observations: A_i = X_i - xbar (times ``inflation``), Z_i = h(X_i)
    (unwrapped around y_k for angles), B_i = Z_i - zbar,

        C = sum_i A_i B_i^T / (N - 1)            (o rho_xy with localisation)
        S = sum_i B_i B_i^T / (N - 1) + R        (C_zz o rho_yy with localisation)
        K = C S^{-1}                             (solved, never inverted)
        X_i <- X_i + K (y_k + e_i - Z_i),  e_i ~ N(0, R)   (state angles wrapped after)

    Args: X (b, N, n) members, y (b, dy), rng the block's generator. Returns X (b, N, n).
    """
    N = X.shape[1]
    xbar = ops.state_mean(X)
    A = ops.state_residual(X, xbar[:, None, :])  # (b, N, n)
    if inflation != 1.0:
        A = A * inflation
        X = ops.normalize_state(xbar[:, None, :] + A)
    Z = ops.scenario.h(X)  # (b, N, dy)
    if not ops.plain_obs:
        # Unwrap each member's predicted observation onto the branch around y_k, so that the
        # anomalies (hence C and S) and the innovations use one continuous branch; the cut
        # lies opposite the observation, where the likelihood is smallest.
        Z = y[:, None, :] + ops.obs_residual(Z, y[:, None, :])
    Bz = Z - Z.mean(axis=1, keepdims=True)
    C = weighted_cross_covariance(A, Bz, None, N - 1)  # (b, n, dy)
    Czz = weighted_covariance(Bz, None, N - 1)
    if rho is not None:  # Schur-product localisation of both covariances
        C = C * rho[0]
        Czz = Czz * rho[1]
    S = Czz + R
    Kt = psd_solve(S, np.swapaxes(C, -1, -2))  # (b, dy, n) = K^T
    E = gaussian(rng, Z.shape[:2], sqrt_R, sd_R)  # (b, N, dy)
    innov = (y[:, None, :] + E) - Z
    return ops.normalize_state(X + innov @ Kt)


def _estimate(X: np.ndarray, ops: ScenarioOps) -> tuple[np.ndarray, np.ndarray]:
    """The ensemble mean (b, n) and covariance sum_i A_i A_i^T / (N - 1) (b, n, n) of members X (b, N, n)."""
    mean = ops.state_mean(X)
    A = ops.state_residual(X, mean[:, None, :])
    return mean, weighted_covariance(A, None, X.shape[1] - 1)


class EnsembleKalmanFilter(MemberFilter):
    r"""Stochastic EnKF with perturbed observations.

    Members X_i, i = 1..N, start as draws from the prior N(m0, P0).

    Predict (k >= 1):

        X_i <- f(X_i, u_{k-1}) + w_i,   w_i ~ N(0, Q)

    Update, with anomalies A_i = X_i - xbar (state mean circular and residuals wrapped for
    angles), predicted observations Z_i = h(X_i), for angular observations unwrapped next to the
    observation, Z_i = y_k + wrap(h(X_i) - y_k), and B_i = Z_i - zbar, zbar = mean_i Z_i:

        C = sum_i A_i B_i^T / (N - 1)
        S = sum_i B_i B_i^T / (N - 1) + R
        K = C S^{-1}                                      (solved, never inverted)
        X_i <- X_i + K (y_k + e_i - Z_i),  e_i ~ N(0, R)  (state angles wrapped after)

    Unwrapping around y_k (rather than around the circular mean of the Z_i) keeps the regression
    of Z on X and the innovations on one branch; with a wide ensemble (bearings-only tracking
    right after the prior) the other choice sends members to the antipodal bearing.

    Options of the data-assimilation practice (not in the paper; all off by default):

    - ``inflation`` = lambda: multiplicative inflation of the forecast anomalies, A_i <- lambda A_i
      (X_i <- xbar + lambda A_i) before the update: the forecast covariance times lambda^2
      (Anderson & Anderson 1999). DAPPER's ``EnKF(infl=lambda)`` applies the same factor to the
      analysis anomalies, one half-cycle later.
    - ``q_inflation``: multiplies Q in the members' process noise (additive inflation).
    - ``localization_radius`` = c: covariance localisation (Houtekamer & Mitchell 2001) by
      Schur products with Gaspari-Cohn tapers of the declared distances between components
      (:mod:`neural_estimator.filters.localization`; Lorenz 96: cyclic index distance):

          C <- rho(d_xy / c) o C,    S <- rho(d_yy / c) o C_zz + R

      rho vanishes beyond distance 2c, so far observations no longer correct a variable through
      spurious sample correlations. DAPPER's ``loc_rad`` r is c = 1.82 r (it scales GC so that
      rho = exp(-1/2) at distance r).

    Output: the ensemble mean and the ensemble covariance sum_i A_i A_i^T / (N - 1) of the
    posterior members. A stream whose ensemble goes non-finite (a singular S included) is flagged
    in ``diverged``. S = C_zz + R is positive definite whenever R is, so it is solved directly.
    """

    method = "enkf"
    HyperParams = EnKFHyperParams
    # Lorenz 96 runs on the compiled kernels (filters/kernels/enkf.py: the same equations and
    # numpy's very draws, one compiled call per phase and block of streams, the blocks on the
    # filter's threads) at every batch: at B = 1 numpy's per-call cost is most of a batched step,
    # and at B = 1,000 (n = 40, one thread) the batched path is slower per trajectory than B = 1
    # while the compiled one is not (benchmarks/bench_batch_kernels.py). An int caps the batch
    # they run at; 0 turns them off.
    compiled_max_batch: int | None = None

    def __init__(self, scenario, seed: int = 0, hyperparams=None, **options) -> None:
        super().__init__(scenario, seed=seed, hyperparams=hyperparams, **options)
        self.N = int(self.hp.n_members)
        self._sqrt_P0, self._sd_P0 = sqrt_factor(self.P0)
        self._sqrt_R, self._sd_R = sqrt_factor(self.R)
        self._rho = None
        if self.hp.localization_radius is not None:
            self._rho = localization_tapers(scenario, float(self.hp.localization_radius), self.method)
        # f over the members: the scenario's compiled transition where it has one (N-link's RK4 in
        # numpy is half the EnKF's time there), else its numpy f
        self._kernels = compiled_model(scenario)
        self._transition = self._kernels.transition or scenario.f

    def _init_state(self, B: int) -> None:
        draws = self._initial_draws(PHASE_INIT, self.N, self._sqrt_P0, self._sd_P0)
        self._X = self.ops.normalize_state(self._init_mean[:, None, :] + draws)
        self._compiled = self._compiled_args(B)

    def _compiled_args(self, B: int) -> dict | None:
        """The compiled kernels' constants when they apply (a scenario whose kernels give
        ``enkf_model``: Lorenz 96, H = I; diagonal Q and R, R positive definite, a batch within
        ``compiled_max_batch``), else None."""
        model = self._kernels.enkf_model
        if not compiled_applies(self.compiled_max_batch, B) or model is None:
            return None
        if self._sd_Q is None or self._sd_R is None or not np.all(self._sd_R > 0.0):
            return None
        keyed = self._scheduler.keyed
        n = self.scenario.dx
        rho = self._rho if self._rho is not None else (np.ones((n, n)), np.ones((n, n)))
        c = {
            "model": model,
            "sd_Q": np.ascontiguousarray(self._sd_Q, dtype=np.float64),
            "update": (
                np.ascontiguousarray(self.R),
                np.ascontiguousarray(self._sd_R, dtype=np.float64),
                float(self.hp.inflation),
                np.ascontiguousarray(rho[0], dtype=np.float64),
                np.ascontiguousarray(rho[1], dtype=np.float64),
                self._rho is not None,
            ),
            "key": (keyed.pool, keyed.hc),
            "no_skip": np.zeros(B, dtype=bool),
        }
        c["step"] = (*c["model"], c["sd_Q"], *c["update"], *c["key"], (PHASE_PREDICT, PHASE_UPDATE))
        return c

    def _own_members(self) -> np.ndarray:
        """self._X as a C-contiguous float64 array the compiled kernels may write."""
        X = self._X
        if not (X.flags.writeable and X.flags.c_contiguous and X.dtype == np.float64):
            X = self._X = np.array(X, dtype=np.float64, order="C")
        return X

    def _advance(self, y: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The base class's step cycle; on the compiled kernels, one call for predict, update and
        estimate (the same cycle: rows of y with a NaN or inf only predict, non-finite estimates
        flag the stream as diverged and park it)."""
        c = self._compiled
        if c is None or (self._k == 0 and self.init == "observation"):
            return super()._advance(y, u)
        X, k = self._own_members(), self._k
        parts = self._for_blocks(lambda i, sl: compiled_enkf.step(X[sl], y[sl], k, *c["step"], i))
        if len(parts) == 1:
            mean, cov, self.skipped, bad = parts[0]
        else:  # (mean, cov, skipped, bad) of every block, stacked over the streams
            mean, cov, self.skipped, bad = (np.concatenate(p, axis=0) for p in zip(*parts))
        self._k += 1
        if bad.any():
            self.diverged |= bad
            self._park(bad)
        if self.diverged.any():
            d = self.diverged
            mean = np.where(d[:, None], np.nan, mean)
            cov = np.where(d[:, None, None], np.nan, cov)
        cov.flags.writeable = False  # the filter's own array: read it, copy it, never write it
        return mean, cov

    def _predict(self, u: np.ndarray) -> None:
        c = self._compiled
        if c is None:
            return super()._predict(u)
        X, k = self._own_members(), self._k
        self._for_blocks(
            lambda i, sl: compiled_enkf.predict(X[sl], *c["model"], c["sd_Q"], *c["key"], k, PHASE_PREDICT, i)
        )
        return None

    # The maths is the module-level _update / _estimate; these hooks schedule it over the blocks of
    # streams.
    def _update(self, y: np.ndarray, skip: np.ndarray | None) -> None:
        c = self._compiled
        if c is not None:
            X, k = self._own_members(), self._k
            no = c["no_skip"] if skip is None else skip
            self._for_blocks(
                lambda i, sl: compiled_enkf.update(X[sl], y[sl], no[sl], *c["update"], *c["key"], k, PHASE_UPDATE, i)
            )
            return None
        X_post, _ = self._blockwise(self._update_kernel, self._X, y, phase=PHASE_UPDATE)
        self._X = self._keep(skip, self._X, X_post)
        return None

    def _update_kernel(self, X: np.ndarray, y: np.ndarray, rng: np.random.Generator):
        return _update(
            X,
            y,
            rng,
            ops=self.ops,
            R=self.R,
            sqrt_R=self._sqrt_R,
            sd_R=self._sd_R,
            inflation=self.hp.inflation,
            rho=self._rho,
        ), None

    def _estimate(self) -> tuple[np.ndarray, np.ndarray]:
        if self._compiled is not None:
            X = self._own_members()
            b, _, n = X.shape
            mean, cov = np.empty((b, n)), np.empty((b, n, n))
            self._for_blocks(lambda i, sl: compiled_enkf.estimate(X[sl], mean[sl], cov[sl]))
            return mean, cov
        mean, cov, _ = self._blockwise(lambda X: (*_estimate(X, self.ops), None), self._X)
        return mean, cov

    def _park(self, mask: np.ndarray) -> None:
        self._X = np.where(mask[:, None, None], self.m0, self._X)
