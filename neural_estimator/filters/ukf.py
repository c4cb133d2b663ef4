"""Unscented Kalman filter with Merwe's scaled sigma points, batched over B streams.

References: E. A. Wan and R. van der Merwe, "The unscented Kalman filter for nonlinear
estimation" (2000); R. van der Merwe, PhD thesis (2004), scaled sigma points; filterpy's
``UnscentedKalmanFilter`` + ``MerweScaledSigmaPoints`` (the tests' independent implementation),
including its choice of redrawing sigma points from the predicted (m^-, P^-) before the update.
The paper uses alpha = 1e-3, beta = 2, kappa = 0 (Table hparams).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import NamedTuple

import numpy as np

from neural_estimator.methods.interface import EstimatorError
from neural_estimator.filters.base import ClassicalFilter, check_inflation
from neural_estimator.filters.numerics import JitterPolicy, ScenarioOps, cholesky, psd_solve, symmetrize


@dataclass(frozen=True)
class UKFHyperParams:
    """UKF settings; defaults are the paper's (Table hparams)."""

    alpha: float = 1e-3  # spread of the sigma points around the mean
    beta: float = 2.0  # prior knowledge of the distribution (2 is optimal for Gaussians)
    kappa: float = 0.0  # secondary scaling
    jitter: float = 1e-9  # not in the paper: first Cholesky jitter on P, relative to its mean diagonal
    jitter_tries: int = 6  # not in the paper: retries, each jitter 10x the previous
    linear_update: bool = True  # not in the paper: closed-form update where h(x) = H x (same result)
    inflation: float = 1.0  # not in the paper (1 = none): P^- = inflation^2 sum_i Wc_i d_i d_i^T + q_inflation Q
    q_inflation: float = 1.0  # not in the paper (1 = none): multiplies the process noise covariance Q

    def validate(self) -> None:
        check_inflation(self.inflation, self.q_inflation)
        if not self.alpha > 0:
            raise ValueError(f"alpha must be > 0, got {self.alpha}")
        if not self.jitter > 0 or self.jitter_tries < 0:
            raise ValueError("jitter must be > 0 and jitter_tries >= 0")


def merwe_weights(n: int, alpha: float, beta: float, kappa: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Mean and covariance weights (2n+1,) of Merwe's scaled sigma points and c = n + lambda.

    lambda = alpha^2 (n + kappa) - n;  Wm_0 = lambda / c,  Wc_0 = Wm_0 + 1 - alpha^2 + beta,
    Wm_i = Wc_i = 1 / (2 c) for i = 1..2n.
    """
    lam = alpha**2 * (n + kappa) - n
    c = n + lam
    if not c > 0:
        raise ValueError(f"n + lambda must be > 0 (alpha={alpha}, kappa={kappa}, n={n})")
    Wm = np.full(2 * n + 1, 0.5 / c)
    Wc = Wm.copy()
    Wm[0] = lam / c
    Wc[0] = lam / c + (1.0 - alpha**2 + beta)
    return Wm, Wc, c


class _Constants(NamedTuple):
    """What the UKF's maths needs besides the state: the scenario's operations, the weights and noise."""

    ops: ScenarioOps
    Wm: np.ndarray  # (2n+1,) mean weights
    Wc: np.ndarray  # (2n+1,) covariance weights
    sqrt_c: float  # sqrt(n + lambda)
    jitter: JitterPolicy
    Q: np.ndarray  # (n, n), already multiplied by q_inflation
    R: np.ndarray  # (dy, dy)
    inflation: float
    H: np.ndarray | None  # (dy, n) where the closed-form linear update applies
    H_is_identity: bool


# ---- the maths: plain functions on arrays of b streams (the class below only schedules them) ----------
def _factor(P: np.ndarray, c: _Constants) -> tuple[np.ndarray, np.ndarray | None]:
    """sqrt(c) chol(P) for stored covariances, jitter fallback; failed streams get 0 (and ok False)."""
    L, ok = cholesky(P, c.jitter)
    if ok is not None:
        L = np.where(ok[:, None, None], L, 0.0)
    L *= c.sqrt_c
    return L, ok


def _sigma_points(m: np.ndarray, L: np.ndarray, c: _Constants) -> np.ndarray:
    """(b, 2n+1, n) sigma points m, m + L_{:,i}, m - L_{:,i} for the scaled factor L = sqrt(c) chol(P)."""
    B, n = m.shape
    cols = np.swapaxes(L, -1, -2)  # row i = sqrt(c) chol(P)[:, i]
    X = np.empty((B, 2 * n + 1, n))
    X[:, 0] = m
    np.add(m[:, None, :], cols, out=X[:, 1 : n + 1])
    np.subtract(m[:, None, :], cols, out=X[:, n + 1 :])
    return c.ops.normalize_state(X)


def _ut_covariance(D: np.ndarray, Wc: np.ndarray) -> np.ndarray:
    """sum_i Wc_i d_i d_i^T for (b, 2n+1, k) residuals: Wc_i = w for i >= 1, so one product.

    = w D_{1:}^T D_{1:} + Wc_0 d_0 d_0^T (no weighted copy of D), symmetrised.
    """
    D1 = D[:, 1:]
    C = np.swapaxes(D1, -1, -2) @ D1
    C *= Wc[1]
    d0 = D[:, 0]
    C += Wc[0] * (d0[:, :, None] * d0[:, None, :])
    return symmetrize(C)


def _ut_cross(Dx: np.ndarray, Dz: np.ndarray, Wc: np.ndarray) -> np.ndarray:
    """sum_i Wc_i dx_i dz_i^T: (b, 2n+1, n), (b, 2n+1, m) -> (b, n, m)."""
    C = np.swapaxes(Dx[:, 1:], -1, -2) @ Dz[:, 1:]
    C *= Wc[1]
    C += Wc[0] * (Dx[:, 0, :, None] * Dz[:, 0, None, :])
    return C


def _predict(m: np.ndarray, L: np.ndarray, u: np.ndarray, c: _Constants) -> tuple[np.ndarray, np.ndarray]:
    """Predict from the sigma points X_i of (m, L):

        X'_i = f(X_i, u_{k-1})
        m^- = sum_i Wm_i X'_i                                          (circular for angles)
        P^- = inflation^2 sum_i Wc_i (X'_i - m^-)(X'_i - m^-)^T + Q    (residuals wrapped)

    Args: m (b, n), L (b, n, n) = sqrt(c) chol(P), u (b, du). Returns m^- (b, n), P^- (b, n, n).
    """
    X = _sigma_points(m, L, c)
    N = X.shape[1]
    Xf = c.ops.scenario.f(X, np.broadcast_to(u[:, None, :], (u.shape[0], N, u.shape[1])))  # (b, 2n+1, n)
    m_pred = c.ops.state_mean(Xf, c.Wm)
    D = c.ops.state_residual(Xf, m_pred[:, None, :])
    P_ut = _ut_covariance(D, c.Wc)
    if c.inflation != 1.0:
        P_ut *= c.inflation**2
    P_pred = P_ut + c.Q  # symmetric: a symmetrised sum + Q
    return m_pred, P_pred


def _update(m: np.ndarray, P: np.ndarray, L: np.ndarray, y: np.ndarray, c: _Constants) -> tuple[np.ndarray, np.ndarray]:
    """Update from sigma points X_i of (m^-, P^-) (redrawn, as filterpy does):

        Z_i = h(X_i),  z = sum_i Wm_i Z_i                  (circular for angles)
        S = sum_i Wc_i (Z_i - z)(Z_i - z)^T + R
        C = sum_i Wc_i (X_i - m^-)(Z_i - z)^T
        K = C S^{-1}                                       (solved, never inverted)
        m = m^- + K (y_k - z)                              (innovation and state angles wrapped)
        P = P^- - K S K^T = P^- - C S^{-1} C^T

    Args: m (b, n), P (b, n, n), L (b, n, n) = sqrt(c) chol(P), y (b, dy). Returns m, P.
    """
    ops, n = c.ops, m.shape[1]
    X = _sigma_points(m, L, c)
    Z = ops.scenario.h(X)  # (b, 2n+1, dy)
    z = ops.obs_mean(Z, c.Wm)
    Dz = ops.obs_residual(Z, z[:, None, :])
    S = _ut_covariance(Dz, c.Wc) + c.R
    if ops.plain_state:
        # X_i - m^- = +-L_{:,i} and X_0 - m^- = 0 exactly: C = w L (Dz_+ - Dz_-)
        C = L @ (Dz[:, 1 : n + 1] - Dz[:, n + 1 :])
        C *= c.Wc[1]
    else:
        C = _ut_cross(ops.state_residual(X, m[:, None, :]), Dz, c.Wc)  # (b, n, dy)
    Kt = psd_solve(S, np.swapaxes(C, -1, -2))  # (b, dy, n) = K^T
    r = ops.obs_residual(y, z)
    m_post = ops.normalize_state(m + np.einsum("bmn,bm->bn", Kt, r))
    P_post = symmetrize(P - C @ Kt)
    return m_post, P_post


def _update_linear(m: np.ndarray, P: np.ndarray, y: np.ndarray, c: _Constants) -> tuple[np.ndarray, np.ndarray]:
    """The unscented update of h(x) = H x in closed form (see the class docstring):

    S = H P H^T + R,  K^T = S^{-1} (P H^T)^T,  m = m^- + K (y - H m^-),  P = P^- - (P H^T) K^T.
    """
    if c.H_is_identity:
        PHt, S, z = P, P + c.R, m
    else:
        H = c.H
        PHt = P @ H.T  # (b, n, dy)
        S = symmetrize(H @ PHt) + c.R
        z = m @ H.T
    Kt = psd_solve(S, np.swapaxes(PHt, -1, -2))  # (b, dy, n) = K^T
    m_post = m + np.einsum("bmn,bm->bn", Kt, y - z)
    P_post = symmetrize(P - PHt @ Kt)
    return m_post, P_post


# ---- scheduler kernels: the maths above in the (outputs..., ok) convention of filters/scheduler.py ----
def _predict_kernel(m: np.ndarray, L: np.ndarray, u: np.ndarray, c: _Constants):
    """Predict, then factor P^- for the update's sigma points."""
    m_pred, P_pred = _predict(m, L, u, c)
    return (m_pred, P_pred, *_factor(P_pred, c))


def _predict_kernel_linear(m: np.ndarray, P: np.ndarray, u: np.ndarray, c: _Constants):
    """Predict from the posterior (m, P), factored here; P^- is not factored (no redraw)."""
    L, ok = _factor(P, c)
    return (*_predict(m, L, u, c), ok)


def _update_kernel(m: np.ndarray, P: np.ndarray, L: np.ndarray, y: np.ndarray, c: _Constants):
    """Update, then factor P for the next prediction's sigma points."""
    m_post, P_post = _update(m, P, L, y, c)
    return (m_post, P_post, *_factor(P_post, c))


def _update_kernel_linear(m: np.ndarray, P: np.ndarray, y: np.ndarray, c: _Constants):
    return (*_update_linear(m, P, y, c), None)


def _step_kernel_linear(m: np.ndarray, P: np.ndarray, u: np.ndarray, y: np.ndarray, c: _Constants):
    """Predict and update in one pass over a block (linear observation, no stream skipped)."""
    m_pred, P_pred, ok = _predict_kernel_linear(m, P, u, c)
    return (*_update_linear(m_pred, P_pred, y, c), ok)


class UnscentedKalmanFilter(ClassicalFilter):
    r"""Unscented Kalman filter (Merwe scaled sigma points).

    Sigma points of (m, P), with L L^T = P (Cholesky) and c = n + lambda:

        X_0 = m,  X_i = m + sqrt(c) L_{:,i},  X_{n+i} = m - sqrt(c) L_{:,i}    (angles wrapped)

    Predict (k >= 1):

        X'_i = f(X_i, u_{k-1})
        m^- = sum_i Wm_i X'_i                              (circular for angles)
        P^- = sum_i Wc_i (X'_i - m^-)(X'_i - m^-)^T + Q    (residuals wrapped)

    Update, from sigma points X_i of (m^-, P^-) (redrawn, as filterpy does):

        Z_i = h(X_i),  z = sum_i Wm_i Z_i                  (circular for angles)
        S = sum_i Wc_i (Z_i - z)(Z_i - z)^T + R
        C = sum_i Wc_i (X_i - m^-)(Z_i - z)^T
        K = C S^{-1}                                       (solved, never inverted)
        m = m^- + K (y_k - z)                              (innovation and state angles wrapped)
        P = P^- - K S K^T = P^- - C S^{-1} C^T

    Linear observations. When the scenario declares h(x) = H x (``obs_matrix``; Lorenz 96 and the
    planar quadrotor) and has no angles, the update's unscented transform is exact and, in exact
    arithmetic, gives z = H m^-, S = H P^- H^T + R and C = P^- H^T: with Z_i - z = H (X_i - m^-),
    X_0 = m^- and sum_{i>=1} Wc_i (X_i - m^-)(X_i - m^-)^T = P^- (the sigma points' defining
    property). The filter then uses these closed forms (``linear_update``, default on): the same
    update without the redrawn sigma points, their h and the second Cholesky factorisation, and
    with less round-off (no sums with Wm_0 ~ -1e6). The tests check both paths against each other
    and against filterpy.

    Every covariance is symmetrised and Cholesky-factored when it is made (the factor serves the
    next sigma points), with jitter as a fallback; a stream whose P^- or P cannot be factored even
    so, or whose mean or covariance goes non-finite, is flagged in ``diverged`` at that step.
    S is solved, not Cholesky-factored: with alpha = 1e-3 the weight Wc_0 is about -1e6, and a
    strongly curved h (bearings at short range) can make S indefinite; filterpy then carries on
    with it (P grows), and so does this filter.

    Covariance inflation (not in the paper; both off by default, the paper's filters):

        P^- = inflation^2 sum_i Wc_i d_i d_i^T + q_inflation Q

    ``inflation`` multiplies the spread of the unscented prediction (multiplicative inflation, as
    the EnKF's ``inflation`` multiplies its anomalies); ``q_inflation`` multiplies the process noise
    the filter assumes (additive inflation). Both compensate for model error and sampling error.
    """

    method = "ukf"
    HyperParams = UKFHyperParams

    def __init__(self, scenario, seed: int = 0, hyperparams=None, **options) -> None:
        super().__init__(scenario, seed=seed, hyperparams=hyperparams, **options)
        hp = self.hp
        self.Wm, self.Wc, c = merwe_weights(scenario.dx, hp.alpha, hp.beta, hp.kappa)
        self._sqrt_c = float(np.sqrt(c))
        self.jitter = JitterPolicy(relative=hp.jitter, tries=hp.jitter_tries)
        self._H, self._H_is_identity = self._linear_observation(scenario) if hp.linear_update else (None, False)
        c = self._c = _Constants(
            self.ops,
            self.Wm,
            self.Wc,
            self._sqrt_c,
            self.jitter,
            self.Q,
            self.R,
            hp.inflation,
            self._H,
            self._H_is_identity,
        )
        # the kernels, bound once (a step at B = 1 costs ~190 us: per-call partials would show)
        self._kernels = {
            fn.__name__: partial(fn, c=c)
            for fn in (
                _predict_kernel,
                _predict_kernel_linear,
                _update_kernel,
                _update_kernel_linear,
                _step_kernel_linear,
            )
        }

    def _linear_observation(self, scenario) -> tuple[np.ndarray | None, bool]:
        """(H, H == I) when the closed-form update applies, else (None, False)."""
        H = scenario.obs_matrix()
        if H is None or not (self.ops.plain_state and self.ops.plain_obs):
            return None, False
        H = np.asarray(H, dtype=np.float64)
        n, m = scenario.dx, scenario.dy
        if H.shape != (m, n) or not np.all(np.isfinite(H)):
            raise EstimatorError(
                f"{self.method}: scenario {scenario.name!r} obs_matrix must be finite ({m}, {n}), got {H.shape}"
            )
        return H, m == n and np.array_equal(H, np.eye(n))

    def _init_state(self, B: int) -> None:
        n = self.scenario.dx
        self._m = np.array(self._init_mean, dtype=np.float64)  # (B, n): m0 or the given initial means
        self._P = self._initial_cov(B)
        # The factor of P for the next sigma points; the linear update needs none, so then predict
        # factors the posterior itself.
        if self._H is not None:
            self._L = None
        elif self._init_cov is None:
            self._L = np.broadcast_to(self._factor0, (B, n, n)).copy()
        else:
            self._L = self._sqrt_c * cholesky(self._P, self.jitter)[0]

    @property
    def _factor0(self) -> np.ndarray:
        """sqrt(c) chol(P0) (jitter where P0 is singular)."""
        L, _ = cholesky(self.P0[None], self.jitter)
        return self._sqrt_c * L[0]

    def _stream_elements(self) -> int:
        n = self.scenario.dx
        return (2 * n + 1) * max(n, self.scenario.dy)

    # The maths is the module-level _predict / _update / _update_linear; these hooks schedule it.
    def _predict(self, u: np.ndarray) -> np.ndarray | None:
        if self._H is not None:
            self._m, self._P, ok = self._blockwise(self._kernels["_predict_kernel_linear"], self._m, self._P, u)
            return ok
        self._m, self._P, self._L, ok = self._blockwise(self._kernels["_predict_kernel"], self._m, self._L, u)
        return ok

    def _predict_update(self, u: np.ndarray, y: np.ndarray, skip: np.ndarray | None) -> np.ndarray | None:
        if self._H is None or self._k == 0 or skip is not None:
            return super()._predict_update(u, y, skip)
        # Linear observation, no stream skipping: predict and update each block in one pass, so
        # (m, P) stay in cache between the two and the batch is assembled once a step, not twice.
        self._m, self._P, ok = self._blockwise(self._kernels["_step_kernel_linear"], self._m, self._P, u, y)
        return ok

    def _update(self, y: np.ndarray, skip: np.ndarray | None) -> np.ndarray | None:
        if self._H is not None:
            m_post, P_post, ok = self._blockwise(self._kernels["_update_kernel_linear"], self._m, self._P, y)
        else:
            m_post, P_post, L_post, ok = self._blockwise(self._kernels["_update_kernel"], self._m, self._P, self._L, y)
            self._L = self._keep(skip, self._L, L_post)
        self._m = self._keep(skip, self._m, m_post)
        self._P = self._keep(skip, self._P, P_post)
        if ok is not None and skip is not None:
            ok = ok | skip
        return ok

    def _estimate(self) -> tuple[np.ndarray, np.ndarray]:
        return self._m, self._P

    def _park(self, mask: np.ndarray) -> None:
        self._m = np.where(mask[:, None], self.m0, self._m)
        self._P = np.where(mask[:, None, None], self.P0, self._P)
        if self._L is not None:
            self._L = np.where(mask[:, None, None], self._factor0, self._L)
