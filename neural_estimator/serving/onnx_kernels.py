"""The arithmetic around an exported network step, compiled: one call before the graph, one after.

At 12-50 us a graph step, the ten numpy calls that normalised the input and denormalised the
output (about 1 us each) were a third of a GRU's node step. Each kernel here does the same float64
arithmetic element by element in one call, so the results are the numpy expressions' to the bit
(a test holds them equal):

    z = float32(([y, u] - mu_z) / sigma_z), with the y part 0 when y has a NaN or inf (skipped)
    x = float64(m) * sigma_x + mu_x
    P = float64(C) * (sigma_x sigma_x^T)
"""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(nogil=True, cache=True)
def normalize_into(y: np.ndarray, u: np.ndarray, in_mean: np.ndarray, in_std: np.ndarray, z: np.ndarray) -> bool:
    """Write the normalised [y_k, u_{k-1}] of one stream into z (1, dy + du); True when y is not finite.

    ``u`` has shape (1, du) (du may be 0); the caller has checked that it is finite.
    """
    dy, du = y.shape[1], u.shape[1]
    skipped = False
    for j in range(dy):
        if not np.isfinite(y[0, j]):
            skipped = True
    for j in range(dy):
        z[0, j] = 0.0 if skipped else (y[0, j] - in_mean[j]) / in_std[j]
    for j in range(du):
        z[0, dy + j] = (u[0, j] - in_mean[dy + j]) / in_std[dy + j]
    return skipped


@nb.njit(nogil=True, cache=True)
def denormalize(mean: np.ndarray, out_std: np.ndarray, out_mean: np.ndarray) -> tuple[np.ndarray, bool]:
    """x = float64(mean) * sigma_x + mu_x for one stream (1, dx); and whether every x is finite."""
    dx = mean.shape[1]
    x = np.empty((1, dx))
    finite = True
    for j in range(dx):
        v = np.float64(mean[0, j]) * out_std[j] + out_mean[j]
        x[0, j] = v
        if not np.isfinite(v):
            finite = False
    return x, finite


@nb.njit(nogil=True, cache=True)
def denormalize_covariance(cov: np.ndarray, scale: np.ndarray) -> tuple[np.ndarray, bool]:
    """P = float64(C) * (sigma_x sigma_x^T) for one stream (1, dx, dx); and whether P is finite."""
    dx = cov.shape[1]
    p = np.empty((1, dx, dx))
    finite = True
    for i in range(dx):
        for j in range(dx):
            v = np.float64(cov[0, i, j]) * scale[i, j]
            p[0, i, j] = v
            if not np.isfinite(v):
                finite = False
    return p, finite
