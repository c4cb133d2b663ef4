"""Compiled (numba) kernels of bearings-only tracking (:class:`neural_estimator.scenarios.bearings.Bearings`).

The PF's predict (the constant-velocity transition fused with the keyed noise of :mod:`.rng`) and
the likelihood of h, the bearing, its innovation wrapped.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from neural_estimator.filters.kernels.model import CompiledModel
from neural_estimator.filters.kernels.rng import _add_noise, _seed_state
from neural_estimator.filters.kernels.trig import _wrap


@nb.njit(nogil=True, cache=True)
def bearings_predict(X, t, L, sd, seed, k, phase, first_stream):
    """X (b, P, 4) <- F X + w per particle, F the constant-velocity transition over t."""
    b, P, n = X.shape
    s = np.empty(4, dtype=np.uint64)
    z = np.empty(n)
    for r in range(b):
        _seed_state(s, seed, k, phase, first_stream + r)
        for i in range(P):
            x = X[r, i]
            x[0] = x[0] + t * x[2]
            x[1] = x[1] + t * x[3]
            _add_noise(x, s, L, sd, z)


@nb.njit(nogil=True, cache=True)
def bearings_log_likelihood(X, y, inv_sd, logw):
    """logw (b, P) += -(wrap(y - wrap(atan2(py, px))) / sd)^2 / 2."""
    b, P, _ = X.shape
    for r in range(b):
        yr = y[r, 0]
        for i in range(P):
            e = _wrap(yr - _wrap(math.atan2(X[r, i, 1], X[r, i, 0]))) * inv_sd[0]
            logw[r, i] += -0.5 * e * e


def bind(scenario) -> CompiledModel:
    """The kernels of one bearings instance, its time step bound."""
    t = float(scenario.config.dt)
    return CompiledModel(
        predict=lambda X, u, L, sd, key: bearings_predict(X, t, L, sd, *key),
        log_likelihood=bearings_log_likelihood,
    )
