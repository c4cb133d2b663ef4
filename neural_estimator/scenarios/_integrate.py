"""Fixed-step Runge-Kutta 4 for the continuous-time scenarios, with and without tangents.

The tangent version carries the state-transition matrix Phi = d x(t + h) / d x(t) through the
same stages as the state (forward-mode differentiation of the discrete RK4 map), so the Jacobian
is exact for the map that :func:`rk4` computes, not an approximation of the flow's Jacobian.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

Field = Callable[[np.ndarray], np.ndarray]
FieldWithJacobian = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


def rk4(field: Field, x: np.ndarray, h: float, substeps: int) -> np.ndarray:
    """Advance ``x`` by ``substeps`` classical RK4 steps of length ``h``.

    Args:
        field: batched vector field (..., n) -> (..., n).
        x: (..., n) state, real or complex (complex-step differentiation passes through).
        h: step length.
        substeps: number of steps.

    Returns:
        (..., n) state after ``substeps * h``.
    """
    for _ in range(substeps):
        k1 = field(x)
        k2 = field(x + 0.5 * h * k1)
        k3 = field(x + 0.5 * h * k2)
        k4 = field(x + h * k3)
        x = x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
    return x


def rk4_tangent(field_jac: FieldWithJacobian, x: np.ndarray, h: float, substeps: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`rk4` and the Jacobian of its result with respect to ``x``.

    With A(x) = d field / d x, one RK4 step differentiates stage by stage:
    K1 = A(x1), K2 = A(x2)(I + h/2 K1), K3 = A(x3)(I + h/2 K2), K4 = A(x4)(I + h K3),
    Phi_step = I + h/6 (K1 + 2 K2 + 2 K3 + K4), and the substeps compose by matrix products.

    Args:
        field_jac: batched (..., n) -> ((..., n) field, (..., n, n) its Jacobian).
        x: (..., n) state.
        h: step length.
        substeps: number of steps.

    Returns:
        ((..., n) state, (..., n, n) Jacobian).
    """
    n = x.shape[-1]
    eye = np.eye(n)
    phi = None
    for _ in range(substeps):
        k1, a1 = field_jac(x)
        k2, a2 = field_jac(x + 0.5 * h * k1)
        d2 = a2 @ (eye + 0.5 * h * a1)
        k3, a3 = field_jac(x + 0.5 * h * k2)
        d3 = a3 @ (eye + 0.5 * h * d2)
        k4, a4 = field_jac(x + h * k3)
        d4 = a4 @ (eye + h * d3)
        x = x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        step = eye + (h / 6.0) * (a1 + 2.0 * d2 + 2.0 * d3 + d4)
        phi = step if phi is None else step @ phi
    return x, phi


def by_component_blocks(x: np.ndarray, block: int, step: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """``step`` on the states of ``x`` (..., n), at most ``block`` at a time, component-major.

    Each block is handed to ``step`` as contiguous (n, m) rows (one transpose in) and its (n, m)
    result transposed back. With the component index first, each numpy operation of an
    integrator is one long loop over the block's states instead of m short rows of n numbers.
    """
    n = x.shape[-1]
    flat = x.reshape(-1, n)
    out = np.empty_like(flat)
    for lo in range(0, flat.shape[0], block):
        out[lo : lo + block] = step(np.ascontiguousarray(flat[lo : lo + block].T)).T
    return out.reshape(x.shape)
