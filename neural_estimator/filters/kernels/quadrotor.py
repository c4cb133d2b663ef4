"""Compiled (numba) kernels of the planar quadrotor (:class:`neural_estimator.scenarios.quadrotor.PlanarQuadrotor`).

The PF's predict: ``PlanarQuadrotor.f``'s Euler step fused with the keyed noise of :mod:`.rng`. Its
h is linear: the PF's generic kernel (:func:`.pf.linear_log_likelihood`).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from neural_estimator.filters.kernels.model import CompiledModel
from neural_estimator.filters.kernels.rng import _add_noise, _seed_state


@nb.njit(nogil=True, cache=True)
def quadrotor_predict(X, u, tau, g, mass, arm, inertia, keep, L, sd, seed, k, phase, first_stream):
    """X (b, P, 6) <- f(X, u_b) + w per particle: ``PlanarQuadrotor.f``'s Euler step, term for term
    (phi unwrapped, as there), with stream b's control u (b, 2)."""
    b, P, n = X.shape
    s = np.empty(4, dtype=np.uint64)
    z = np.empty(n)
    for r in range(b):
        _seed_state(s, seed, k, phase, first_stream + r)
        thrust = (u[r, 0] + u[r, 1]) / mass
        torque = (u[r, 0] - u[r, 1]) * arm * tau / inertia
        for i in range(P):
            x = X[r, i]
            px, pz, phi, vx, vz, rate = x[0], x[1], x[2], x[3], x[4], x[5]
            c, sn = math.cos(phi), math.sin(phi)
            x[0] = px + (vx * c - vz * sn) * tau
            x[1] = pz + (vx * sn + vz * c) * tau
            x[2] = phi + rate * tau
            x[3] = vx + (vz * rate - g * sn) * tau
            x[4] = vz + (-vx * rate - g * c + thrust) * tau
            x[5] = keep * rate + torque
            _add_noise(x, s, L, sd, z)


def bind(scenario) -> CompiledModel:
    """The kernels of one quadrotor instance, its constants (step, gravity, mass, arm, inertia,
    whether the rate integrates) bound."""
    cfg = scenario.config
    args = (float(cfg.dt), float(cfg.g), float(cfg.mass), float(cfg.arm), float(cfg.inertia))
    keep = 1.0 if cfg.integrate_phi_rate else 0.0
    return CompiledModel(
        predict=lambda X, u, L, sd, key: quadrotor_predict(X, np.ascontiguousarray(u), *args, keep, L, sd, *key)
    )
