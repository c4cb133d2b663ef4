"""Compiled (numba) single-stream EKF on Lorenz 96: the live node's B = 1 step without numpy overhead.

At B = 1 the batched EKF spends most of a step on numpy's per-call cost: the dense tangent of RK4
(:func:`neural_estimator.scenarios._integrate.rk4_tangent`) is about 40 small array operations
(each ``np.roll`` alone costs 1-2 us), and the update another 20. These kernels run the very same
equations (:mod:`neural_estimator.filters.ekf`, Lorenz 96's ``f`` and ``jac_f``) in one compiled call
per phase and stream, in the same order of operations; the tests hold them equal to the batched path.

The EKF uses them at every batch (``ExtendedKalmanFilter.compiled_max_batch``), block by block of
streams on the filter's threads (the kernels release the GIL): at B = 1 the batched path cannot
amortise numpy's per-call cost, and at large batches the compiled loops still beat it.

Only Lorenz 96 has these kernels (the predict holds its field and Jacobian): the EKF takes them
where the scenario's kernels (:func:`neural_estimator.filters.kernels.compiled_model`) give
``ekf_model`` (the forcing, the RK4 step and the substeps).
"""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(cache=True)
def _field_jac(x, forcing, k, A):
    """dX_j/dt = (X_{j+1} - X_{j-2}) X_{j-1} - X_j + F into k; its dense Jacobian into A."""
    n = x.shape[0]
    A[:, :] = 0.0
    for j in range(n):
        xm1 = x[(j - 1) % n]
        k[j] = (x[(j + 1) % n] - x[(j - 2) % n]) * xm1 - x[j] + forcing
        A[j, (j + 1) % n] = xm1
        A[j, (j - 2) % n] = -xm1
        A[j, (j - 1) % n] = x[(j + 1) % n] - x[(j - 2) % n]
        A[j, j] = -1.0


@nb.njit(cache=True)
def _field_jac_times(x, B):
    """A(x) @ B for the field's Jacobian A(x) (four nonzeros a row: offsets +1, -2, -1, 0), in 4 n^2
    multiply-adds instead of the dense product's n^3."""
    n = x.shape[0]
    out = np.empty_like(B)
    for j in range(n):
        xm1 = x[(j - 1) % n]
        c = x[(j + 1) % n] - x[(j - 2) % n]
        rp1, rm2, rm1 = (j + 1) % n, (j - 2) % n, (j - 1) % n
        for i in range(B.shape[1]):
            out[j, i] = xm1 * B[rp1, i] - xm1 * B[rm2, i] + c * B[rm1, i] - B[j, i]
    return out


@nb.njit(cache=True)
def _predict_one(m, P, Q, inflation2, forcing, h, substeps):
    """m^- = f(m) by RK4, F its tangent, P^- = sym(inflation^2 F P F^T + Q); in place."""
    n = m.shape[0]
    eye = np.eye(n)
    k1, k2, k3, k4 = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    a1, a2, a3, a4 = np.empty((n, n)), np.empty((n, n)), np.empty((n, n)), np.empty((n, n))
    x = m.copy()
    phi = eye.copy()
    for s in range(substeps):
        _field_jac(x, forcing, k1, a1)
        x2 = x + 0.5 * h * k1
        _field_jac(x2, forcing, k2, a2)
        d2 = _field_jac_times(x2, eye + 0.5 * h * a1)
        x3 = x + 0.5 * h * k2
        _field_jac(x3, forcing, k3, a3)
        d3 = _field_jac_times(x3, eye + 0.5 * h * d2)
        x4 = x + h * k3
        _field_jac(x4, forcing, k4, a4)
        d4 = _field_jac_times(x4, eye + h * d3)
        x = x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        step = eye + (h / 6.0) * (a1 + 2.0 * d2 + 2.0 * d3 + d4)
        phi = step if s == 0 else step @ phi
    FPFt = phi @ P @ phi.T
    if inflation2 != 1.0:
        FPFt *= inflation2
    Pp = FPFt + Q
    m[:] = x
    P[:, :] = 0.5 * (Pp + Pp.T)


@nb.njit(nogil=True, cache=True)
def predict(M, P, Q, inflation2, forcing, h, substeps):
    """:func:`_predict_one` for every stream of M (B, n), P (B, n, n), in place."""
    for b in range(M.shape[0]):
        _predict_one(M[b], P[b], Q, inflation2, forcing, h, substeps)


@nb.njit(cache=True)
def _update_one(m, P, y, H, R, joseph):
    """Linear observation y = H x + v: r = y - H m, S = sym(H P H^T + R), K^T = S^{-1} H P,
    m += K r, P = sym((I - K H) P (I - K H)^T + K R K^T) (or P - P H^T K^T); in place."""
    n = m.shape[0]
    r = y - H @ m
    PHt = P @ H.T
    S = H @ PHt + R
    S = 0.5 * (S + S.T)
    Kt = np.linalg.solve(S, np.ascontiguousarray(PHt.T))
    m[:] = m + Kt.T @ r
    if joseph:
        K = np.ascontiguousarray(Kt.T)
        IKH = np.eye(n) - K @ H
        Pp = IKH @ P @ IKH.T + K @ R @ Kt
    else:
        Pp = P - PHt @ Kt
    P[:, :] = 0.5 * (Pp + Pp.T)


@nb.njit(nogil=True, cache=True)
def update(M, P, Y, skip, H, R, joseph):
    """:func:`_update_one` for every stream not in ``skip``; a singular S gives NaN (diverged)."""
    for b in range(M.shape[0]):
        if skip[b]:
            continue
        ok = True
        for v in Y[b]:
            ok = ok and np.isfinite(v)
        if not ok:
            continue
        try:
            _update_one(M[b], P[b], Y[b], H, R, joseph)
        except Exception:  # singular innovation covariance
            M[b, :] = np.nan
            P[b, :, :] = np.nan
