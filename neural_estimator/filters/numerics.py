"""Numerics shared by the classical filters: batched, float64, no Python loops over the batch.

Shapes follow one convention everywhere: (B, n) means, (B, n, n) covariances, (B, N, n) sigma
points / ensemble members / particles, (B, N) particle weights.

- :func:`symmetrize`: (A + A^T) / 2, applied to every covariance a filter stores.
- :func:`cholesky`: lower Cholesky factor of a stack of matrices that reports failures per
  matrix instead of raising for the whole stack, and retries a failed matrix with a growing
  diagonal jitter before giving up on it.
- :func:`psd_solve`: X = S^{-1} B for symmetric (normally positive definite) S, by solving (never
  inverting).
- :func:`normalize_log_weights`, :func:`effective_sample_size`, :func:`systematic_resample`:
  particle weights kept in log space, normalised by log-sum-exp.
- :class:`ScenarioOps`: residuals, means and state normalisation that respect angles, with a
  plain-arithmetic fast path for scenarios without angles.

The batched Cholesky and solve call numpy's ``_umath_linalg`` gufuncs directly (the functions
behind ``np.linalg.cholesky`` / ``np.linalg.solve``) with floating-point errors silenced: a failed
matrix then comes back as NaN instead of raising for the whole stack. Where that private module is
missing the public functions are used, with a per-matrix loop only after a failure.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from neural_estimator.scenarios import Scenario

try:  # the gufuncs behind np.linalg.cholesky / np.linalg.solve (NaN on failure when errors are off)
    from numpy.linalg import _umath_linalg

    _CHOL_LO = _umath_linalg.cholesky_lo
    _SOLVE = _umath_linalg.solve
except (ImportError, AttributeError):  # pragma: no cover - depends on the numpy build
    _CHOL_LO = None
    _SOLVE = None


def symmetrize(A: np.ndarray) -> np.ndarray:
    """(A + A^T) / 2 over the last two axes."""
    return 0.5 * (A + np.swapaxes(A, -1, -2))


@dataclass(frozen=True)
class JitterPolicy:
    """How :func:`cholesky` retries a matrix whose factorisation fails.

    Attempt t = 0, 1, ..., ``tries`` - 1 factors A + eps_t I with
    eps_t = ``relative`` * 10^t * max(mean(diag A), ``floor``).
    """

    relative: float = 1e-9  # first jitter relative to the mean diagonal
    tries: int = 6  # retries, each ten times the previous jitter (1e-9 ... 1e-4 by default)
    floor: float = 1e-12  # lower bound of the diagonal scale (all-zero matrices)


def _chol_stack(A: np.ndarray) -> np.ndarray:
    """Lower Cholesky factors of a (K, n, n) stack; NaN matrices where the factorisation fails."""
    if _CHOL_LO is not None:
        with np.errstate(invalid="ignore", over="ignore", divide="ignore", under="ignore"):
            return _CHOL_LO(A, signature="d->d")
    try:  # pragma: no cover - fallback for numpy builds without _umath_linalg
        return np.linalg.cholesky(A)
    except np.linalg.LinAlgError:  # pragma: no cover
        out = np.full_like(A, np.nan)
        for i in range(A.shape[0]):
            try:
                out[i] = np.linalg.cholesky(A[i])
            except np.linalg.LinAlgError:
                pass
        return out


def cholesky(A: np.ndarray, jitter: JitterPolicy = JitterPolicy()) -> tuple[np.ndarray, np.ndarray | None]:
    """Lower Cholesky factors L (L L^T = A) of a stack of symmetric matrices, failures per matrix.

    The whole stack is factored in one call. Only matrices whose factorisation failed are retried,
    with A + eps I and eps growing tenfold per attempt (see :class:`JitterPolicy`).

    Args:
        A: (..., n, n) symmetric matrices (finite).
        jitter: the retry policy.

    Returns:
        (L, ok): L (..., n, n) lower-triangular, NaN for a matrix that failed every attempt;
        ok (...,) bool, or None when every matrix factored at the first attempt (the common case,
        so callers can skip all masking).
    """
    A = np.asarray(A, dtype=np.float64)
    n = A.shape[-1]
    lead = A.shape[:-2]
    flat = A.reshape((-1, n, n))
    L = _chol_stack(flat)
    good = np.isfinite(L[:, np.arange(n), np.arange(n)]).all(axis=-1)  # a failure is all-NaN
    if good.all():
        return L.reshape(A.shape), None
    bad = np.flatnonzero(~good)
    sub = flat[bad]
    scale = np.maximum(np.abs(np.einsum("kii->k", sub)) / n, jitter.floor)
    eye = np.eye(n)
    for t in range(jitter.tries):
        eps = jitter.relative * 10.0**t * scale
        Lt = _chol_stack(sub + eps[:, None, None] * eye)
        fixed = np.isfinite(Lt[:, np.arange(n), np.arange(n)]).all(axis=-1)
        L[bad[fixed]] = Lt[fixed]
        bad, sub, scale = bad[~fixed], sub[~fixed], scale[~fixed]
        if bad.size == 0:
            break
    ok = np.isfinite(L[:, np.arange(n), np.arange(n)]).all(axis=-1)
    return L.reshape(A.shape), ok.reshape(lead)


def psd_solve(S: np.ndarray, B: np.ndarray) -> np.ndarray:
    """X = S^{-1} B for a stack of symmetric (normally positive definite) S, by a linear solve.

    No explicit inverse. S is not required to factor by Cholesky: the scaled unscented transform
    with a tiny alpha (Wc_0 ~ -1/alpha^2) can return an indefinite innovation covariance, which
    filterpy uses as it is, and so do the filters here. A singular S gives NaN for its rows only
    (never an exception for the whole batch); the caller flags those streams as diverged.

    Args:
        S: (K, m, m).
        B: (K, m, k) right-hand sides.

    Returns:
        (K, m, k).
    """
    if S.shape[-1] == 1:
        with np.errstate(invalid="ignore", divide="ignore"):
            return B / S
    if _SOLVE is not None:
        with np.errstate(invalid="ignore", over="ignore", divide="ignore", under="ignore"):
            return _SOLVE(S, B, signature="dd->d")
    try:  # pragma: no cover - fallback for numpy builds without _umath_linalg
        return np.linalg.solve(S, B)
    except np.linalg.LinAlgError:  # pragma: no cover
        out = np.full(np.broadcast_shapes(S.shape[:-2], B.shape[:-2]) + B.shape[-2:], np.nan)
        for i in range(out.shape[0]):
            try:
                out[i] = np.linalg.solve(S[i], B[i])
            except np.linalg.LinAlgError:
                pass
        return out


def sqrt_factor(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """A constant square root for drawing noise: (L, d) with L L^T = cov.

    ``d`` is the vector of standard deviations when ``cov`` is diagonal (then noise is drawn as
    z * d, cheaper than z @ L^T), else None. Singular covariances are allowed (psd square root).
    """
    from neural_estimator.scenarios import psd_sqrt

    cov = np.asarray(cov, dtype=np.float64)
    L = psd_sqrt(cov)
    if np.count_nonzero(cov - np.diag(np.diag(cov))) == 0:
        return L, np.sqrt(np.clip(np.diag(cov), 0.0, None))
    return L, None


def gaussian(rng: np.random.Generator, shape: tuple[int, ...], L: np.ndarray, d: np.ndarray | None) -> np.ndarray:
    """Zero-mean Gaussian draws of covariance L L^T: (*shape, n) from one standard-normal block."""
    z = rng.standard_normal(shape + (L.shape[0],))
    if d is not None:
        z *= d
        return z
    return z @ L.T


# ---- particle weights --------------------------------------------------------------------------
LOG_W_FLOOR = -600.0  # relative log-weight below which a normalised weight is exactly zero


def normalize_log_weights(logw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normalise log-weights over the last axis by log-sum-exp.

    w_i = exp(l_i - m) / sum_j exp(l_j - m) with m = max_j l_j, so the largest weight is computed
    without overflow and at least one term of the sum is 1.

    Returns:
        (normalised log-weights, weights), both (..., N). Rows whose log-weights are all -inf or
        contain NaN come back NaN (the caller flags them as diverged).
    """
    m = logw.max(axis=-1, keepdims=True)
    with np.errstate(invalid="ignore"):
        d = logw - m
        # Relative weights below e^-600 (~1e-261) are set to exactly 0 rather than left to
        # underflow into subnormal numbers, which slow every later product with them ~50x on
        # x86 (the PF's weighted mean and covariance); they could not change any sum anyway.
        w = np.exp(np.where(d > LOG_W_FLOOR, d, -np.inf))
        s = w.sum(axis=-1, keepdims=True)
        w /= s
        return d - np.log(s), w


def effective_sample_size(w: np.ndarray) -> np.ndarray:
    """ESS = 1 / sum_i w_i^2 of normalised weights (..., N) -> (...)."""
    return 1.0 / np.einsum("...n,...n->...", w, w)


def systematic_resample(w: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Systematic resampling of every row of a (K, N) weight matrix at once.

    Positions p_i = (u + i) / N for i = 0..N-1 with one offset u ~ U[0, 1) per row; index i goes to
    the first j with p_i < c_j, c the cumulative weights (filterpy.monte_carlo.systematic_resample,
    vectorised: each row's cumulative sum is shifted by its row number so one searchsorted serves
    the whole batch).

    Args:
        w: (K, N) normalised weights.
        u: (K,) uniform offsets in [0, 1).

    Returns:
        (K, N) int indices into each row.
    """
    K, N = w.shape
    c = np.cumsum(w, axis=1)
    c[:, -1] = 1.0  # guard against round-off: the last position must find a particle
    rows = np.arange(K, dtype=np.float64)[:, None]
    pos = (u[:, None] + np.arange(N)) / N + rows
    idx = np.searchsorted((c + rows).ravel(), pos.ravel(), side="right").reshape(K, N)
    idx -= (np.arange(K) * N)[:, None]
    np.clip(idx, 0, N - 1, out=idx)
    return idx


# ---- angle-aware arithmetic --------------------------------------------------------------------
class ScenarioOps:
    """Residuals, means and normalisation of one scenario, with plain fast paths.

    Scenarios without angular components (and not overriding the base-class methods) use plain
    subtraction and weighted sums through matmul; the others go through the scenario's own
    ``state_residual`` / ``obs_residual`` / ``state_mean`` / ``obs_mean`` / ``normalize_state``.
    """

    def __init__(self, scenario: Scenario) -> None:
        cls = type(scenario)
        self.scenario = scenario
        self.plain_state = (
            not scenario.angle_states
            and cls.state_residual is Scenario.state_residual
            and cls.state_mean is Scenario.state_mean
            and cls.normalize_state is Scenario.normalize_state
        )
        self.plain_obs = (
            not scenario.angle_obs and cls.obs_residual is Scenario.obs_residual and cls.obs_mean is Scenario.obs_mean
        )

    def state_residual(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return a - b if self.plain_state else self.scenario.state_residual(a, b)

    def obs_residual(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return a - b if self.plain_obs else self.scenario.obs_residual(a, b)

    def normalize_state(self, x: np.ndarray) -> np.ndarray:
        return x if self.plain_state else self.scenario.normalize_state(x)

    def state_mean(self, points: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
        """Mean over the member axis of (B, N, n) points; weights None, (N,) or (B, N)."""
        if not self.plain_state:
            return self.scenario.state_mean(points, weights)
        return _plain_mean(points, weights)

    def obs_mean(self, points: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
        """Mean over the member axis of (B, N, m) predicted observations."""
        if not self.plain_obs:
            return self.scenario.obs_mean(points, weights)
        return _plain_mean(points, weights)


def _plain_mean(points: np.ndarray, weights: np.ndarray | None) -> np.ndarray:
    if weights is None:
        return points.mean(axis=-2)
    if weights.ndim == 1:
        return weights @ points  # (N,) @ (B, N, n) -> (B, n)
    return (weights[..., None, :] @ points)[..., 0, :]


def weighted_covariance(D: np.ndarray, weights: np.ndarray | None, denom: float = 1.0) -> np.ndarray:
    """sum_i w_i d_i d_i^T over the member axis of (B, N, n) residuals D.

    ``weights`` None means equal weights 1/denom (the EnKF's 1/(N-1)); (N,) or (B, N) weights
    may be negative (UKF). The result is symmetrised.
    """
    Dt = np.swapaxes(D, -1, -2)
    if weights is None:
        C = (Dt @ D) / denom
    elif weights.ndim == 1:
        C = (Dt * weights) @ D
    else:
        C = (Dt * weights[..., None, :]) @ D
    return symmetrize(C)


def weighted_cross_covariance(
    Dx: np.ndarray, Dz: np.ndarray, weights: np.ndarray | None, denom: float = 1.0
) -> np.ndarray:
    """sum_i w_i dx_i dz_i^T: (B, N, n), (B, N, m) -> (B, n, m)."""
    Dt = np.swapaxes(Dx, -1, -2)
    if weights is None:
        return (Dt @ Dz) / denom
    if weights.ndim == 1:
        return (Dt * weights) @ Dz
    return (Dt * weights[..., None, :]) @ Dz
