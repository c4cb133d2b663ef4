"""GRU estimator: a linear input projection, a stacked GRU, a linear head.

References:
    Cho et al. (2014), "Learning Phrase Representations using RNN Encoder-Decoder for Statistical
        Machine Translation", https://arxiv.org/abs/1406.1078 (the gated recurrent unit).
    PyTorch ``torch.nn.GRU`` (the cuDNN/oneDNN fused cell used by both forms below).

Glossary: B batch, T time, H hidden size, L layers.

    z (B, T, d_in) -> input_proj -> GRU (L layers, dropout between layers) -> head -> x_hat (B, T, d_out)

The input projection to width H makes every layer an H -> H GRU, so the parameter count barely
depends on the scenario's d_in (the paper's budget of about 100k: 94,645 on Lorenz 96). Dropout
acts between the GRU layers during training only. The step state is the (L, B, H) hidden state:
O(1) per step, and ``forward`` equals a loop of ``step`` because both run the same cell.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor


@dataclass(frozen=True)
class GRUConfig:
    d_in: int
    d_out: int
    hidden: int = 85
    layers: int = 2
    dropout: float = 0.1


class GRUModel(nn.Module):
    """GRU estimator: ``forward(z) (B, T, d_in) -> (B, T, d_out)``; ``step`` with state h (L, B, H)."""

    def __init__(self, cfg: GRUConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.input_proj = nn.Linear(cfg.d_in, cfg.hidden)
        self.rnn = nn.GRU(
            cfg.hidden,
            cfg.hidden,
            num_layers=cfg.layers,
            batch_first=True,
            dropout=cfg.dropout if cfg.layers > 1 else 0.0,
        )
        self.head = nn.Linear(cfg.hidden, cfg.d_out)

    def forward(self, z: Tensor) -> Tensor:
        return self.head(self.features(z))  # (B, T, d_out)

    def init_state(self, batch: int, device=None, dtype=None) -> Tensor:
        p = self.head.weight
        return torch.zeros(
            self.cfg.layers,
            batch,
            self.cfg.hidden,
            device=p.device if device is None else device,
            dtype=p.dtype if dtype is None else dtype,
        )  # (L, B, H)

    def step(self, z_t: Tensor, state: Tensor) -> tuple[Tensor, Tensor]:
        """One step, eval mode (no dropout between layers): one fused ``gru_cell`` per layer, the
        arithmetic of ``nn.GRU`` on a length-1 sequence at a third less time at batch 1 (the module
        call checks and flattens its weights at every call)."""
        h, new = self.step_features(z_t, state)
        return F.linear(h, self.head.weight, self.head.bias), new  # (B, d_out), (L, B, H)

    def _cell_weights(self) -> list[tuple[Tensor, Tensor, Tensor, Tensor]]:
        r = self.rnn
        return [
            (
                getattr(r, f"weight_ih_l{k}"),
                getattr(r, f"weight_hh_l{k}"),
                getattr(r, f"bias_ih_l{k}"),
                getattr(r, f"bias_hh_l{k}"),
            )
            for k in range(self.cfg.layers)
        ]

    # ---- the trunk's last hidden features (the covariance head's input, neural_estimator.serving.uncertainty) --
    def features(self, z: Tensor) -> Tensor:
        """(B, T, H): what ``head`` maps to the estimate, ``forward(z) == head(features(z))``."""
        h, _ = self.rnn(self.input_proj(z))  # (B, T, H)
        return h

    def step_features(self, z_t: Tensor, state: Tensor) -> tuple[Tensor, Tensor]:
        """(B, H) features of one step and the new state, the arithmetic of :meth:`step`, whose
        estimate is ``head`` of them."""
        x = F.linear(z_t, self.input_proj.weight, self.input_proj.bias)  # (B, H); no module-call overhead
        hs = []
        for layer, weights in enumerate(self._cell_weights()):
            x = torch.gru_cell(x, state[layer], *weights)  # (B, H)
            hs.append(x)
        return x, torch.stack(hs)  # (B, H), (L, B, H)
