"""The model around a selective-SSM mixer, shared by Mamba and Mamba-2.

mamba_ssm's MixerModel without the token embedding, plus this project's input projection and head:

    z (B, T, d_in) -> input_proj -> [h + mixer(RMSNorm(h))] x n_layer -> RMSNorm (norm_f) -> head

Module names follow mamba_ssm (``backbone.layers.i.{norm, mixer.*}``, ``backbone.norm_f``) so
state_dicts move between the two. Only the mixer differs between the architectures: it is passed in
as a class taking the config and offering ``forward(x, reference)``, ``step(x_t, conv, ssm)`` and
``init_state(batch, device, dtype)``.
"""

from __future__ import annotations

import math

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor


def rms_norm(x: Tensor, weight: Tensor, eps: float) -> Tensor:
    """x / sqrt(mean(x^2) + eps) * weight over the last axis."""
    return F.rms_norm(x, weight.shape, weight, eps)


class RMSNorm(nn.Module):
    """mamba_ssm's RMSNorm (parameter ``weight``, no bias)."""

    def __init__(self, d: int, eps: float = 1e-5) -> None:
        super().__init__()
        self.eps = eps
        self.weight = nn.Parameter(torch.ones(d))

    def forward(self, x: Tensor) -> Tensor:
        return rms_norm(x, self.weight, self.eps)


class Block(nn.Module):
    """Pre-norm residual block: h + mixer(norm(h)) (mamba_ssm's Block without an MLP)."""

    def __init__(self, cfg, mixer_cls: type[nn.Module]) -> None:
        super().__init__()
        self.norm = RMSNorm(cfg.d_model, eps=cfg.norm_eps)
        self.mixer = mixer_cls(cfg)

    def forward(self, h: Tensor, reference: bool = False) -> Tensor:
        return h + self.mixer(self.norm(h), reference)

    def step(self, h: Tensor, conv_state: Tensor, ssm_state: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        y, conv_state, ssm_state = self.mixer.step(rms_norm(h, self.norm.weight, self.norm.eps), conv_state, ssm_state)
        return h + y, conv_state, ssm_state


class Backbone(nn.Module):
    """mamba_ssm's MixerModel without the token embedding: ``layers`` and ``norm_f``."""

    def __init__(self, cfg, mixer_cls: type[nn.Module]) -> None:
        super().__init__()
        self.layers = nn.ModuleList(Block(cfg, mixer_cls) for _ in range(cfg.n_layer))
        self.norm_f = RMSNorm(cfg.d_model, eps=cfg.norm_eps)


class SSMEstimator(nn.Module):
    """``forward(z) (B, T, d_in) -> (B, T, d_out)``, ``step(z_t, state)``.

    The step state is ``(conv_0, ssm_0, conv_1, ssm_1, ...)``: per layer the mixer's conv window and
    SSM state, in mamba_ssm's layout.
    """

    def __init__(self, cfg, mixer_cls: type[nn.Module]) -> None:
        super().__init__()
        self.cfg = cfg
        self.input_proj = nn.Linear(cfg.d_in, cfg.d_model)
        self.backbone = Backbone(cfg, mixer_cls)
        self.head = nn.Linear(cfg.d_model, cfg.d_out)
        # mamba_ssm's _init_weights: prenorm residual outputs scaled by 1/sqrt(n_layer)
        for layer in self.backbone.layers:
            nn.init.kaiming_uniform_(layer.mixer.out_proj.weight, a=math.sqrt(5))
            with torch.no_grad():
                layer.mixer.out_proj.weight /= math.sqrt(cfg.n_layer)

    def forward(self, z: Tensor, reference: bool = False) -> Tensor:
        """z (B, T, d_in) -> (B, T, d_out); ``reference=True`` runs the sequential reference scan."""
        return self.head(self.features(z, reference))

    def init_state(self, batch: int, device=None, dtype=None) -> tuple[Tensor, ...]:
        p = self.head.weight
        device = p.device if device is None else device
        dtype = p.dtype if dtype is None else dtype
        state: list[Tensor] = []
        for layer in self.backbone.layers:
            state += layer.mixer.init_state(batch, device, dtype)
        return tuple(state)

    def step(self, z_t: Tensor, state: tuple[Tensor, ...]) -> tuple[Tensor, tuple[Tensor, ...]]:
        h, new = self.step_features(z_t, state)
        return F.linear(h, self.head.weight, self.head.bias), new  # (B, d_out)

    # ---- the trunk's last hidden features (the covariance head's input, neural_estimator.serving.uncertainty) --
    def features(self, z: Tensor, reference: bool = False) -> Tensor:
        """(B, T, d): what ``head`` maps to the estimate, ``forward(z) == head(features(z))``."""
        h = self.input_proj(z)  # (B, T, d)
        for layer in self.backbone.layers:
            h = layer(h, reference)
        return self.backbone.norm_f(h)

    def step_features(self, z_t: Tensor, state: tuple[Tensor, ...]) -> tuple[Tensor, tuple[Tensor, ...]]:
        """(B, d) features of one step and the new state: ``step`` is ``head`` of them."""
        h = F.linear(z_t, self.input_proj.weight, self.input_proj.bias)  # (B, d)
        new: list[Tensor] = []
        for i, layer in enumerate(self.backbone.layers):
            h, conv, ssm = layer.step(h, state[2 * i], state[2 * i + 1])
            new += [conv, ssm]
        norm_f = self.backbone.norm_f
        return rms_norm(h, norm_f.weight, norm_f.eps), tuple(new)
