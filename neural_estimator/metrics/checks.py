"""The checks of what the metrics are given, and their one error."""

from __future__ import annotations

import numpy as np


class MetricsError(ValueError):
    """Inputs the metrics cannot be computed from (shapes, non-finite ground truth, bad spread)."""


def check_pair(x_true, x_hat) -> tuple[np.ndarray, np.ndarray]:
    """(x_true, x_hat) as float64 (N, T, dx) arrays of one shape, not empty."""
    x_true = np.asarray(x_true, dtype=np.float64)
    x_hat = np.asarray(x_hat, dtype=np.float64)
    if x_true.ndim != 3 or x_true.shape != x_hat.shape:
        raise MetricsError(f"x_true and x_hat must both be (N, T, dx); got {x_true.shape} and {x_hat.shape}")
    if 0 in x_true.shape:
        raise MetricsError(f"empty input of shape {x_true.shape}")
    return x_true, x_hat


def check_errors(e) -> np.ndarray:
    """Errors ``e`` as a float64 (N, T, dx) array."""
    e = np.asarray(e, dtype=np.float64)
    if e.ndim != 3:
        raise MetricsError(f"errors must be (N, T, dx), got shape {e.shape}")
    return e


def check_curve(rmse_t) -> np.ndarray:
    """An RMSE-time curve as a float64 (T,) array, T >= 1."""
    rmse_t = np.asarray(rmse_t, dtype=np.float64)
    if rmse_t.ndim != 1 or rmse_t.shape[0] == 0:
        raise MetricsError(f"rmse_t must be (T,) with T >= 1, got shape {rmse_t.shape}")
    return rmse_t
