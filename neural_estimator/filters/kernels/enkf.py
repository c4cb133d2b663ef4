"""Compiled (numba) EnKF step on Lorenz 96 for a few streams: the live node's B = 1 step without
numpy's per-call cost.

At B = 1 the batched EnKF (:mod:`neural_estimator.filters.enkf`) spends most of a step on numpy's
per-call overhead: about 40 array operations on (1, N, n) arrays, each 1-5 us whatever its size.
These kernels run the same equations, in the same order of operations where it is cheap to keep
it, in one compiled call per phase:

- predict: Lorenz 96's RK4 (:mod:`.lorenz96`, the batched path's compiled transition, bit for
  bit), plus the process noise;
- update: anomalies, C = A^T B / (N - 1), C_zz, S = C_zz + R (with the localisation tapers when
  set), K^T = S^{-1} C^T (Cholesky), the perturbed observations; then the
  ensemble mean and covariance.

Random numbers are numpy's, bit for bit (:mod:`.rng`'s SFC64 normals): the block's generator state
is derived from the key (seed, step, phase, block) as ``SFC64(SeedSequence(seed, spawn_key=key))``
does (:mod:`neural_estimator.filters.seeding`), and the standard normals follow numpy's
``Generator.standard_normal``. The tests hold the draws equal to numpy's and the filter equal to
the batched path.

Only Lorenz 96 has these kernels (its predict holds Lorenz 96's RK4): the EnKF takes them where the
scenario's kernels (:func:`neural_estimator.filters.kernels.compiled_model`) give ``enkf_model``.

The member means, the anomalies, the RK4 and the noise are bit for bit the batched path's. The
matrix products go to BLAS through numba (scipy's build) instead of numpy's stacked matmul, and S is
solved by Cholesky instead of numpy's LU, so the last bits may differ: the estimates agree to
rounding (measured 4e-15 of the largest |x|, 2e-14 of the largest covariance entry, no growth over
300 steps; the tests hold 1e-12).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from neural_estimator.filters.kernels.lorenz96 import _l96_rk4, _l96_rk4_rows
from neural_estimator.filters.kernels.rng import _sfc64_fill_normals
from neural_estimator.filters.seeding import sfc64_state


# ---- the filter ------------------------------------------------------------------------------------
@nb.njit(nogil=True, cache=True)
def predict(X, forcing, h, substeps, sd_Q, pool, hc, k, phase, block):
    """X (b, N, n) <- f(X) + w, w = z * sd_Q with z the block's standard normals, member by member
    (z fills (b, N, n) in C order, as the batched path's draw). In place.

    RK4 in the batched path's order of operations, bit for bit: for small rings (n <= 16) with the
    members innermost (:func:`_l96_rk4_rows`, twice as fast there), else member by member."""
    b, N, n = X.shape
    s = sfc64_state(pool, hc, k, phase, block)
    if n <= 16:
        x, K2, A2, M2 = np.empty((n, N)), np.empty((n, N)), np.empty((n, N)), np.empty((n, N))
        for r in range(b):
            _l96_rk4_rows(X[r], forcing, h, substeps, x, K2, A2, M2)
    else:
        K, A, M = np.empty(n), np.empty(n), np.empty(n)
        for r in range(b):
            for i in range(N):
                _l96_rk4(X[r, i], forcing, h, substeps, K, A, M)
    z = np.empty(N * n)
    for r in range(b):
        _sfc64_fill_normals(s, z)
        for i in range(N):
            for j in range(n):
                X[r, i, j] += z[i * n + j] * sd_Q[j]


@nb.njit(inline="always")
def _member_mean(X, out):
    """out = X.mean(axis=0) for X (N, n): summed member after member, then divided by N (numpy's
    reduction over a non-contiguous axis)."""
    N, n = X.shape
    for j in range(n):
        out[j] = X[0, j]
    for i in range(1, N):
        for j in range(n):
            out[j] += X[i, j]
    for j in range(n):
        out[j] /= N


@nb.njit(inline="always")
def _spd_solve(S, C, K):
    """K = S^{-1} C^T for symmetric positive definite S (n, n) and C (p, n), into K (n, p), by the
    Cholesky factor S = U^T U (U over S's upper triangle) and two triangular solves for all p
    right-hand sides at once. Every inner loop runs along a row, so the compiler vectorises it:
    twice as fast as LAPACK's LU solve through numba at n = 40. False when a pivot is not positive
    (S not positive definite, or NaN)."""
    n = S.shape[0]
    p = C.shape[0]
    for j in range(n):
        d = S[j, j]
        if not d > 0.0:
            return False
        d = math.sqrt(d)
        S[j, j] = d
        for c in range(j + 1, n):
            S[j, c] /= d
        for i in range(j + 1, n):
            v = S[j, i]
            for c in range(i, n):
                S[i, c] -= v * S[j, c]
    for a in range(n):  # forward: U^T W = C^T
        for c in range(p):
            K[a, c] = C[c, a]
        for m in range(a):
            v = S[m, a]
            for c in range(p):
                K[a, c] -= v * K[m, c]
        d = S[a, a]
        for c in range(p):
            K[a, c] /= d
    for a in range(n - 1, -1, -1):  # back: U K = W
        for m in range(a + 1, n):
            v = S[a, m]
            for c in range(p):
                K[a, c] -= v * K[m, c]
        d = S[a, a]
        for c in range(p):
            K[a, c] /= d
    return True


@nb.njit(nogil=True, cache=True)
def update(X, Y, skip, R, sd_R, inflation, rho_xy, rho_yy, localize, pool, hc, k, phase, block):
    """The perturbed-observations update of every stream of X (b, N, n) not in ``skip``, H = I
    (filters/enkf.py's ``_update``), in place; the draws of skipped streams are drawn and unused,
    so every stream keeps its numbers. An S that is not positive definite gives NaN members
    (flagged as diverged); with R positive definite (the caller's condition) S always is."""
    b, N, n = X.shape
    s = sfc64_state(pool, hc, k, phase, block)
    xbar, zbar = np.empty(n), np.empty(n)
    A, Bz = np.empty((N, n)), np.empty((N, n))
    E = np.empty((N, n))
    Kt = np.empty((n, n))
    z = np.empty(N * n)
    for r in range(b):
        _sfc64_fill_normals(s, z)  # the draws first: a skipped or failing stream still consumes its own
        for i in range(N):
            for j in range(n):
                E[i, j] = z[i * n + j] * sd_R[j]
        if skip[r]:
            continue
        Xr, y = X[r], Y[r]
        _member_mean(Xr, xbar)
        for i in range(N):
            for j in range(n):
                A[i, j] = Xr[i, j] - xbar[j]
        if inflation != 1.0:
            for i in range(N):
                for j in range(n):
                    A[i, j] = A[i, j] * inflation
                    Xr[i, j] = xbar[j] + A[i, j]
        _member_mean(Xr, zbar)  # Z = h(X) = X
        for i in range(N):
            for j in range(n):
                Bz[i, j] = Xr[i, j] - zbar[j]
        C = np.dot(A.T, Bz) / (N - 1.0)  # (n, dy)
        S = np.dot(Bz.T, Bz) / (N - 1.0)  # C_zz
        S = 0.5 * (S + S.T)
        if localize:
            C = C * rho_xy
            S = S * rho_yy
        S = S + R
        if not _spd_solve(S, C, Kt):  # Kt (dy, n) = K^T = S^{-1} C^T
            Xr[:, :] = math.nan  # S not positive definite: NaN members, flagged as diverged
            continue
        # X_i += (y + e_i - z_i) K^T, z_i = x_i (the forecast member)
        for i in range(N):
            for j in range(n):
                E[i, j] = (y[j] + E[i, j]) - Xr[i, j]
        D = np.dot(E, Kt)
        for i in range(N):
            for c in range(n):
                Xr[i, c] += D[i, c]


@nb.njit(nogil=True, cache=True)
def estimate(X, mean, cov):
    """The ensemble mean (b, n) and covariance sym(A^T A / (N - 1)) (b, n, n) of X (b, N, n)."""
    b, N, n = X.shape
    A = np.empty((N, n))
    for r in range(b):
        _member_mean(X[r], mean[r])
        for i in range(N):
            for j in range(n):
                A[i, j] = X[r, i, j] - mean[r, j]
        C = np.dot(A.T, A) / (N - 1.0)
        cov[r] = 0.5 * (C + C.T)


@nb.njit(nogil=True, cache=True)
def step(X, Y, k, forcing, h, substeps, sd_Q, R, sd_R, inflation, rho_xy, rho_yy, localize, pool, hc, phases, block):
    """One filter step of every stream of X (b, N, n) in place (ClassicalFilter's cycle, fused):
    predict (k >= 1), update the streams whose y_k (b, dy) is finite, then the estimate.

    ``phases`` = (predict, update) phase numbers of the keys; ``block``: the index of this block of
    streams (its draws are the batched path's draws of that block). Returns (mean (b, n), cov (b, n, n),
    skipped (b,), bad (b,)): bad where the mean or the covariance has a non-finite sum (the
    caller's divergence test)."""
    b, N, n = X.shape
    if k > 0:
        predict(X, forcing, h, substeps, sd_Q, pool, hc, k, phases[0], block)
    skip = np.zeros(b, dtype=np.bool_)
    for r in range(b):
        for j in range(Y.shape[1]):
            if not np.isfinite(Y[r, j]):
                skip[r] = True
    update(X, Y, skip, R, sd_R, inflation, rho_xy, rho_yy, localize, pool, hc, k, phases[1], block)
    mean, cov = np.empty((b, n)), np.empty((b, n, n))
    estimate(X, mean, cov)
    bad = np.zeros(b, dtype=np.bool_)
    for r in range(b):
        bad[r] = not (np.isfinite(mean[r].sum()) and np.isfinite(cov[r].sum()))
    return mean, cov, skip, bad
