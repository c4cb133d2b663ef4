"""Angle helpers shared by scenarios, filters and metrics.

Every angle in the project lives in (-pi, pi]. Differences of angles are wrapped into that interval
(innovations, estimation errors) and averages of angles are circular means.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def wrap_angle(a):
    """Map angles to (-pi, pi].

    ``pi - mod(pi - a, 2 pi)`` sends pi to pi and -pi to pi, so the interval is closed on the right
    as the paper's ``wrap`` is. Works on numpy arrays and scalars.
    """
    return np.pi - np.mod(np.pi - a, 2.0 * np.pi)


def wrap_components(d: np.ndarray, angle_idx: Sequence[int]) -> np.ndarray:
    """Return ``d`` with the components ``angle_idx`` of its last axis wrapped (copy if any)."""
    if not len(angle_idx):
        return d
    d = np.array(d, dtype=np.result_type(d, np.float64), copy=True)
    idx = list(angle_idx)
    d[..., idx] = wrap_angle(d[..., idx])
    return d


def weighted_mean(points: np.ndarray, weights: np.ndarray | None, angle_idx: Sequence[int], axis: int = -2):
    """Mean of ``points`` along ``axis`` (the member axis), circular for ``angle_idx`` components.

    Args:
        points: (..., N, n) sigma points, ensemble members or particles (``axis=-2``).
        weights: (..., N) weights summing to one, or None for equal weights. UKF mean weights may be
            negative; the circular mean then uses the same signed weights on (cos, sin).
        angle_idx: components of the last axis that are angles.
        axis: the member axis.

    Returns:
        (..., n) mean. Angular components are ``atan2(sum w sin, sum w cos)``.
    """
    if weights is None:
        mean = points.mean(axis=axis)
    else:
        w = np.expand_dims(weights, -1)
        mean = (w * points).sum(axis=axis)
    if len(angle_idx):
        idx = list(angle_idx)
        ang = points[..., idx]
        if weights is None:
            s, c = np.sin(ang).mean(axis=axis), np.cos(ang).mean(axis=axis)
        else:
            w = np.expand_dims(weights, -1)
            s, c = (w * np.sin(ang)).sum(axis=axis), (w * np.cos(ang)).sum(axis=axis)
        mean[..., idx] = np.arctan2(s, c)
    return mean
