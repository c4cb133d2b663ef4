"""Compiled (numba) kernels of the ballistic re-entry (:class:`neural_estimator.scenarios.ballistic.Ballistic`).

RK4 of the drag dynamics in ``rk4()``'s order of operations (bit-equal to ``Ballistic.f`` where
numpy's exp is libm's, tested), the PF's predict (fused with the keyed noise of :mod:`.rng`), the
EnKF's member transition, and the likelihood of h, the range.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from neural_estimator.filters.kernels.model import CompiledModel, in_place_rows
from neural_estimator.filters.kernels.rng import _add_noise, _seed_state


@nb.njit(inline="always")
def _ballistic_field(a, v, c, g, kk):
    """(a', v') = (-v, g - c v^2 E(a)), E(a) = exp(-k a) above ground, 1 below (c' = 0)."""
    e = math.exp(-kk * a) if a > 0.0 else 1.0
    return -v, g - c * v * v * e


@nb.njit(nogil=True, cache=True)
def ballistic_predict(X, g, kk, h, substeps, L, sd, seed, k, phase, first_stream):
    """X (b, P, 3) <- f(X) + w per particle: RK4 in rk4()'s order of operations, then the noise."""
    b, P, n = X.shape
    s = np.empty(4, dtype=np.uint64)
    z = np.empty(n)
    half, sixth = 0.5 * h, h / 6.0
    for r in range(b):
        _seed_state(s, seed, k, phase, first_stream + r)
        for i in range(P):
            x = X[r, i]
            _ballistic_rk4(x, g, kk, h, half, sixth, substeps)
            _add_noise(x, s, L, sd, z)


@nb.njit(inline="always")
def _ballistic_rk4(x, g, kk, h, half, sixth, substeps):
    a, v, c = x[0], x[1], x[2]
    for _ in range(substeps):
        a1, v1 = _ballistic_field(a, v, c, g, kk)
        a2, v2 = _ballistic_field(a + half * a1, v + half * v1, c, g, kk)
        a3, v3 = _ballistic_field(a + half * a2, v + half * v2, c, g, kk)
        a4, v4 = _ballistic_field(a + h * a3, v + h * v3, c, g, kk)
        a = a + sixth * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
        v = v + sixth * (v1 + 2.0 * v2 + 2.0 * v3 + v4)
    x[0], x[1] = a, v


@nb.njit(nogil=True, cache=True)
def ballistic_transition(X, g, kk, h, substeps):
    """X (M, 3) <- f(X) (no noise): the EnKF's members (and the tests)."""
    for i in range(X.shape[0]):
        _ballistic_rk4(X[i], g, kk, h, 0.5 * h, h / 6.0, substeps)


@nb.njit(nogil=True, cache=True)
def ballistic_log_likelihood(X, r0, a_ref, y, inv_sd, logw):
    """logw (b, P) += -((y - sqrt(r0^2 + (a - a_ref)^2)) / sd)^2 / 2."""
    b, P, _ = X.shape
    r02 = r0 * r0
    for r in range(b):
        yr = y[r, 0]
        for i in range(P):
            d = X[r, i, 0] - a_ref
            e = (yr - math.sqrt(r02 + d * d)) * inv_sd[0]
            logw[r, i] += -0.5 * e * e


def bind(scenario) -> CompiledModel:
    """The kernels of one ballistic instance, its constants (g, k, RK4 step, substeps, radar) bound."""
    cfg = scenario.config
    args = (float(cfg.g), float(cfg.k), float(cfg.dt) / int(cfg.substeps), int(cfg.substeps))
    r0, a_ref = float(cfg.r0), float(cfg.a_ref)
    return CompiledModel(
        predict=lambda X, u, L, sd, key: ballistic_predict(X, *args, L, sd, *key),
        log_likelihood=lambda X, y, inv_sd, logw: ballistic_log_likelihood(X, r0, a_ref, y, inv_sd, logw),
        transition=in_place_rows(ballistic_transition, *args),
    )
