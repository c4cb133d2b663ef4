"""Compiled (numba) kernels of the N-link pendulum (:class:`neural_estimator.scenarios.nlink.NLinkPendulum`).

RK4 of the Euler-Lagrange equations over (N, P) rows (the N-link L D L^T solve in the numpy code's
order, sine and cosine by :func:`.trig._sincos`: a few ulp from ``NLinkPendulum.f``, tested), the
angles wrapped; the PF's predict (f fused with the keyed noise of :mod:`.rng`), the EnKF's member
transition, and the likelihood of h, the masses' positions.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from neural_estimator.filters.kernels.model import CompiledModel, in_place_rows
from neural_estimator.filters.kernels.rng import _add_noise, _seed_state
from neural_estimator.filters.kernels.trig import _sincos, _wrap


@nb.njit(inline="always")
def _nlink_accel(th, om, weights, neg_grav, c, s, om2, a, inv_d, acc, m):
    """NLinkPendulum._accel_components on the first m columns of (N, P) rows: w' into ``acc``.

    M w' = rhs with M_jk = W_jk cos(th_j - th_k), S_jk = W_jk sin(th_j - th_k),
    rhs_j = -sum_k S_jk w_k^2 - G_j sin th_j, solved by L D L^T without pivoting (M is SPD), in
    the numpy code's order; sin and cos by :func:`_sincos` (numpy's code uses tan(th / 2), so the
    two agree to a few ulp, not bit for bit). Components are rows and states columns, so every
    inner loop runs over states and vectorises. ``c, s, om2, inv_d`` (N, P) and ``a`` (N, N, P)
    are scratch.
    """
    n = th.shape[0]
    for j in range(n):
        gj = neg_grav[j]
        for i in range(m):
            sx, cx = _sincos(th[j, i])
            s[j, i] = sx
            c[j, i] = cx
            om2[j, i] = om[j, i] * om[j, i]
            acc[j, i] = sx * gj
    for j in range(n):
        for i in range(m):
            a[j, j, i] = weights[j, j]
        for k in range(j + 1, n):
            w = weights[j, k]
            for i in range(m):
                skew = (s[j, i] * c[k, i] - c[j, i] * s[k, i]) * w
                acc[j, i] -= skew * om2[k, i]
                acc[k, i] += skew * om2[j, i]
                a[j, k, i] = (c[j, i] * c[k, i] + s[j, i] * s[k, i]) * w
    for j in range(n):
        for i in range(m):
            inv_d[j, i] = 1.0 / a[j, j, i]
        for q in range(j + 1, n):
            for i in range(m):
                lij = a[j, q, i] * inv_d[j, i]
                a[q, j, i] = lij
                for k in range(q, n):
                    a[q, k, i] -= lij * a[j, k, i]
                acc[q, i] -= lij * acc[j, i]
    for j in range(n - 1, -1, -1):
        for i in range(m):
            v = acc[j, i] * inv_d[j, i]
            for k in range(j + 1, n):
                v -= a[k, j, i] * acc[k, i]
            acc[j, i] = v


# Floating-point freedoms for the N-link RK4: fused multiply-adds, reciprocals for divisions, and no
# care for the sign of zero (about 10 % faster; results stay within a few ulp of numpy's f, tested).
# No reassociation: sums keep the numpy code's order.
_NLINK_FASTMATH = {"contract", "arcp", "nsz"}


@nb.njit(inline="always")
def _nlink_scratch(n, P):
    """Twelve (N, P) rows and one (N, N, P) block of scratch for :func:`_nlink_rk4_rows` (separate
    arrays: views of one block would be typed non-contiguous, which stops the loops vectorising)."""
    return (
        (
            np.empty((n, P)),
            np.empty((n, P)),
            np.empty((n, P)),
            np.empty((n, P)),
            np.empty((n, P)),
            np.empty((n, P)),
            np.empty((n, P)),
            np.empty((n, P)),
            np.empty((n, P)),
            np.empty((n, P)),
            np.empty((n, P)),
            np.empty((n, P)),
        ),
        np.empty((n, n, P)),
    )


@nb.njit(inline="always")
def _nlink_rk4_rows(X, h, substeps, weights, neg_grav, rows, a):
    """``substeps`` RK4 steps on the m states X (m, 2N) (m <= P) in place, unwrapped, in
    NLinkPendulum._step_components' order; ``rows`` twelve (N, P) and ``a`` (N, N, P) scratch."""
    m, dx = X.shape
    n = dx // 2
    th, om, new_th, new_om, k_th, k_om, st_th, st_om, c, s, om2, inv_d = rows
    for i in range(m):
        for j in range(n):
            th[j, i] = X[i, j]
            om[j, i] = X[i, n + j]
    sixth, third = h / 6.0, h / 3.0
    for _ in range(substeps):
        _nlink_accel(th, om, weights, neg_grav, c, s, om2, a, inv_d, k_om, m)
        for j in range(n):
            for i in range(m):
                k_th[j, i] = om[j, i]
                new_th[j, i] = th[j, i] + sixth * k_th[j, i]
                new_om[j, i] = om[j, i] + sixth * k_om[j, i]
        for stage in range(3):
            to_stage = h if stage == 2 else 0.5 * h
            weight = sixth if stage == 2 else third
            for j in range(n):
                for i in range(m):
                    st_om[j, i] = om[j, i] + to_stage * k_om[j, i]
                    st_th[j, i] = th[j, i] + to_stage * k_th[j, i]
            _nlink_accel(st_th, st_om, weights, neg_grav, c, s, om2, a, inv_d, k_om, m)
            for j in range(n):
                for i in range(m):
                    k_th[j, i] = st_om[j, i]
                    new_th[j, i] += weight * k_th[j, i]
                    new_om[j, i] += weight * k_om[j, i]
        for j in range(n):
            for i in range(m):
                th[j, i] = new_th[j, i]
                om[j, i] = new_om[j, i]
    for i in range(m):
        for j in range(n):
            X[i, j] = th[j, i]
            X[i, n + j] = om[j, i]


@nb.njit(nogil=True, cache=True, fastmath=_NLINK_FASTMATH)
def nlink_predict(X, h, substeps, weights, neg_grav, L, sd, seed, k, phase, first_stream):
    """X (b, P, 2N) <- wrap(wrap(f(X)) + w) per particle: RK4, angles wrapped, noise, wrapped again
    (the numpy path's ``normalize_state(f(X) + w)``, f itself wrapping)."""
    b, P, dx = X.shape
    n = dx // 2
    s = np.empty(4, dtype=np.uint64)
    z = np.empty(dx)
    rows, a = _nlink_scratch(n, P)
    for r in range(b):
        _nlink_rk4_rows(X[r], h, substeps, weights, neg_grav, rows, a)
        _seed_state(s, seed, k, phase, first_stream + r)
        for i in range(P):
            x = X[r, i]
            for j in range(n):
                x[j] = _wrap(x[j])
            _add_noise(x, s, L, sd, z)
            for j in range(n):
                x[j] = _wrap(x[j])


_NLINK_ROWS = 1024  # states per pass of nlink_transition


@nb.njit(nogil=True, cache=True, fastmath=_NLINK_FASTMATH)
def nlink_transition(X, h, substeps, weights, neg_grav):
    """X (M, 2N) <- f(X) (RK4 and wrapping, no noise): the EnKF's members (and the tests)."""
    M, dx = X.shape
    n = dx // 2
    rows, a = _nlink_scratch(n, _NLINK_ROWS)
    for lo in range(0, M, _NLINK_ROWS):
        _nlink_rk4_rows(X[lo : lo + _NLINK_ROWS], h, substeps, weights, neg_grav, rows, a)
    for i in range(M):
        for j in range(n):
            X[i, j] = _wrap(X[i, j])


@nb.njit(nogil=True, cache=True)
def nlink_log_likelihood(X, lengths, y, inv_sd, logw):
    """logw (b, P) += -|(y - h(x_i)) / sd|^2 / 2, h the masses' positions
    [x_1, z_1, ..., x_N, z_N], x_i = sum_{j<=i} R_j sin th_j, z_i = -sum_{j<=i} R_j cos th_j."""
    b, P, dx = X.shape
    n = dx // 2
    for r in range(b):
        yr = y[r]
        for i in range(P):
            x = X[r, i]
            px = 0.0
            pz = 0.0
            acc = 0.0
            for j in range(n):
                sx, cx = _sincos(x[j])
                px += lengths[j] * sx
                pz += lengths[j] * cx
                ex = (yr[2 * j] - px) * inv_sd[2 * j]
                ez = (yr[2 * j + 1] + pz) * inv_sd[2 * j + 1]
                acc += ex * ex + ez * ez
            logw[r, i] += -0.5 * acc


def bind(scenario) -> CompiledModel:
    """The kernels of one N-link instance, its constants (RK4 step, substeps, masses' weights,
    gravity terms, link lengths) bound."""
    cfg = scenario.config
    lengths, weights, grav = scenario._constants()
    args = (float(cfg.dt) / int(cfg.substeps), int(cfg.substeps), np.ascontiguousarray(weights), -grav)
    return CompiledModel(
        predict=lambda X, u, L, sd, key: nlink_predict(X, *args, L, sd, *key),
        log_likelihood=lambda X, y, inv_sd, logw: nlink_log_likelihood(X, lengths, y, inv_sd, logw),
        transition=in_place_rows(nlink_transition, *args),
    )
