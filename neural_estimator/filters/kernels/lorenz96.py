"""Compiled (numba) kernels of Lorenz 96 (:class:`neural_estimator.scenarios.lorenz96.Lorenz96`).

The transition (the same RK4, in the same order of operations as ``Lorenz96.f``, bit-equal, tested)
per state and over (J, P) rows with the states innermost; the PF's predict (f fused with the keyed
process noise of :mod:`.rng`). h = I uses the PF's generic linear likelihood
(:func:`.pf.linear_log_likelihood`). Lorenz 96 also runs the compiled EKF and EnKF
(:mod:`.ekf`, :mod:`.enkf`), whose predict steps hold its field: :func:`bind` hands them the
model's constants.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from neural_estimator.filters.kernels.model import CompiledModel, in_place_rows
from neural_estimator.filters.kernels.rng import _add_noise, _seed_state


# ---- Lorenz 96 ------------------------------------------------------------------------------------
@nb.njit(inline="always")
def _l96_field(x, out, forcing):
    """dX_j/dt = (X_{j+1} - X_{j-2}) X_{j-1} - X_j + F on the ring, in Lorenz96._field's order
    (the three wrapped ends apart, so the main loop has no index arithmetic modulo J)."""
    n = x.shape[0]
    out[0] = (x[1] - x[n - 2]) * x[n - 1] - x[0] + forcing
    out[1] = (x[2] - x[n - 1]) * x[0] - x[1] + forcing
    for j in range(2, n - 1):
        out[j] = (x[j + 1] - x[j - 2]) * x[j - 1] - x[j] + forcing
    out[n - 1] = (x[0] - x[n - 3]) * x[n - 2] - x[n - 1] + forcing


@nb.njit(inline="always")
def _l96_rk4(x, forcing, h, substeps, K, A, M):
    """``substeps`` RK4 steps of length h on x in place, in rk4()'s order of operations."""
    n = x.shape[0]
    half = 0.5 * h
    sixth = h / 6.0
    for _ in range(substeps):
        _l96_field(x, K, forcing)  # k1
        for j in range(n):
            A[j] = K[j]
            M[j] = x[j] + K[j] * half
        _l96_field(M, K, forcing)  # k2
        for j in range(n):
            A[j] += K[j] * 2.0
            M[j] = x[j] + K[j] * half
        _l96_field(M, K, forcing)  # k3
        for j in range(n):
            A[j] += K[j] * 2.0
            M[j] = x[j] + K[j] * h
        _l96_field(M, K, forcing)  # k4
        for j in range(n):
            A[j] += K[j]
            A[j] *= sixth
            x[j] += A[j]


@nb.njit(nogil=True, cache=True)
def lorenz96_transition(X, forcing, h, substeps):
    """X (..., N, J) <- f(X): Lorenz 96 RK4 in place (no noise); for the tests and the reference."""
    flat = X.reshape(-1, X.shape[-1])
    n = flat.shape[1]
    K, A, M = np.empty(n), np.empty(n), np.empty(n)
    for i in range(flat.shape[0]):
        _l96_rk4(flat[i], forcing, h, substeps, K, A, M)


@nb.njit(inline="always")
def _l96_field_rows(x, out, forcing, m):
    """:func:`_l96_field` on the first m columns of (J, P) rows: the same operations per state,
    with the states innermost so the loops vectorise."""
    n = x.shape[0]
    for j in range(n):
        jp, jm1, jm2 = (j + 1) % n, (j - 1) % n, (j - 2) % n
        for i in range(m):
            out[j, i] = (x[jp, i] - x[jm2, i]) * x[jm1, i] - x[j, i] + forcing


@nb.njit(inline="always")
def _l96_rk4_rows(X, forcing, h, substeps, x, K, A, M):
    """:func:`_l96_rk4` on the m states X (m, J) (m <= P) in place, through (J, P) scratch rows."""
    m, n = X.shape
    half = 0.5 * h
    sixth = h / 6.0
    for i in range(m):
        for j in range(n):
            x[j, i] = X[i, j]
    for _ in range(substeps):
        _l96_field_rows(x, K, forcing, m)  # k1
        for j in range(n):
            for i in range(m):
                A[j, i] = K[j, i]
                M[j, i] = x[j, i] + K[j, i] * half
        _l96_field_rows(M, K, forcing, m)  # k2
        for j in range(n):
            for i in range(m):
                A[j, i] += K[j, i] * 2.0
                M[j, i] = x[j, i] + K[j, i] * half
        _l96_field_rows(M, K, forcing, m)  # k3
        for j in range(n):
            for i in range(m):
                A[j, i] += K[j, i] * 2.0
                M[j, i] = x[j, i] + K[j, i] * h
        _l96_field_rows(M, K, forcing, m)  # k4
        for j in range(n):
            for i in range(m):
                A[j, i] += K[j, i]
                A[j, i] *= sixth
                x[j, i] += A[j, i]
    for i in range(m):
        for j in range(n):
            X[i, j] = x[j, i]


@nb.njit(nogil=True, cache=True)
def lorenz96_predict(X, forcing, h, substeps, L, sd, seed, k, phase, first_stream):
    """X (b, N, J) <- f(X) + w per particle: RK4 over each stream's particles as (J, N) rows
    (vectorised across particles), then the noise particle by particle."""
    b, N, n = X.shape
    s = np.empty(4, dtype=np.uint64)
    z = np.empty(n)
    x, K, A, M = np.empty((n, N)), np.empty((n, N)), np.empty((n, N)), np.empty((n, N))
    for r in range(b):
        _l96_rk4_rows(X[r], forcing, h, substeps, x, K, A, M)
        _seed_state(s, seed, k, phase, first_stream + r)
        for i in range(N):
            _add_noise(X[r, i], s, L, sd, z)


def bind(scenario) -> CompiledModel:
    """The kernels of one Lorenz 96 instance, its constants (forcing, RK4 step, substeps) bound."""
    cfg = scenario.config
    args = (float(cfg.forcing), float(cfg.dt) / int(cfg.substeps), int(cfg.substeps))
    return CompiledModel(
        predict=lambda X, u, L, sd, key: lorenz96_predict(X, *args, L, sd, *key),
        transition=in_place_rows(lorenz96_transition, *args),
        ekf_model=args,
        enkf_model=args,
    )
