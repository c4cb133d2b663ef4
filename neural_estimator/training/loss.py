"""The training loss: the state error in normalised units (angles wrapped), the sampling-weighted
squared error of a batch of windows, and the per-component weights of ``loss_units``."""

from __future__ import annotations

import math

import numpy as np
import torch


def state_error(pred: torch.Tensor, target: torch.Tensor, angle_mask: torch.Tensor) -> torch.Tensor:
    """pred - target (..., dx) in normalised units, angular components wrapped to [-pi, pi).

    Angular components are in radians (mean 0, std 1 in the normaliser), so the wrap acts on
    radians; its gradient is 1 almost everywhere.
    """
    e = pred - target
    if not bool(angle_mask.any()):
        return e
    wrapped = torch.remainder(e + math.pi, 2.0 * math.pi) - math.pi
    return torch.where(angle_mask, wrapped, e)


def weighted_loss(
    pred: torch.Tensor,
    target: torch.Tensor,
    weights: torch.Tensor,
    angle_mask: torch.Tensor,
    component_weights: torch.Tensor | None = None,
) -> torch.Tensor:
    """L = sum_{b,t,d} w_bt c_d e_btd^2 / (sum_d c_d sum_{b,t} w_bt); pred, target (B, L, dx), weights (B, L).

    ``component_weights`` c (dx,): None is c = 1 (every normalised component alike); see
    :func:`component_weights`.
    """
    e = state_error(pred, target, angle_mask)
    if component_weights is None:
        return (weights.unsqueeze(-1) * e.square()).sum() / (weights.sum() * e.shape[-1])
    return (weights.unsqueeze(-1) * component_weights * e.square()).sum() / (weights.sum() * component_weights.sum())


def component_weights(loss_units: str, state_std: np.ndarray, device) -> torch.Tensor | None:
    """Per-component loss weights c_d for ``TrainConfig.loss_units``.

    "normalised": None (c = 1). "state": c_d = sigma_d^2 / mean(sigma^2), so that c_d e_d^2 with e the
    normalised error is the squared error in the state's own units up to one constant factor: the
    loss then weighs the components as RMSE does (a component with a large spread, such as an
    altitude in km, counts more than one with a tiny spread, such as a drag coefficient).
    """
    if loss_units == "normalised":
        return None
    s2 = np.square(np.asarray(state_std, dtype=np.float64))
    return torch.as_tensor(s2 / s2.mean(), dtype=torch.float32, device=device)
