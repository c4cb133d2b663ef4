"""LSTM estimator: a linear input projection, a stacked LSTM, a linear head.

References:
    Hochreiter, Schmidhuber (1997), "Long Short-Term Memory", Neural Computation 9(8).
    PyTorch ``torch.nn.LSTM`` (the fused cell used by both forms below).

Glossary: B batch, T time, H hidden size, L layers.

    z (B, T, d_in) -> input_proj -> LSTM (L layers, dropout between layers) -> head -> x_hat (B, T, d_out)

The input projection to width H makes every layer an H -> H LSTM, so the parameter count barely
depends on the scenario's d_in (97,315 on Lorenz 96 against the paper's budget of about 100k).
Dropout acts between the LSTM layers during training only. The step state is (h, c), each
(L, B, H): O(1) per step, and ``forward`` equals a loop of ``step`` because both run the same cell.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor


@dataclass(frozen=True)
class LSTMConfig:
    d_in: int
    d_out: int
    hidden: int = 75
    layers: int = 2
    dropout: float = 0.1


class LSTMModel(nn.Module):
    """LSTM estimator: ``forward(z) (B, T, d_in) -> (B, T, d_out)``; ``step`` with state (h, c)."""

    def __init__(self, cfg: LSTMConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.input_proj = nn.Linear(cfg.d_in, cfg.hidden)
        self.rnn = nn.LSTM(
            cfg.hidden,
            cfg.hidden,
            num_layers=cfg.layers,
            batch_first=True,
            dropout=cfg.dropout if cfg.layers > 1 else 0.0,
        )
        self.head = nn.Linear(cfg.hidden, cfg.d_out)

    def forward(self, z: Tensor) -> Tensor:
        h, _ = self.rnn(self.input_proj(z))  # (B, T, H)
        return self.head(h)  # (B, T, d_out)

    def init_state(self, batch: int, device=None, dtype=None) -> tuple[Tensor, Tensor]:
        p = self.head.weight
        h = torch.zeros(
            self.cfg.layers,
            batch,
            self.cfg.hidden,
            device=p.device if device is None else device,
            dtype=p.dtype if dtype is None else dtype,
        )  # (L, B, H)
        return h, torch.zeros_like(h)

    def step(self, z_t: Tensor, state: tuple[Tensor, Tensor]) -> tuple[Tensor, tuple[Tensor, Tensor]]:
        """One step, eval mode (no dropout between layers): one fused ``lstm_cell`` per layer, the
        arithmetic of ``nn.LSTM`` on a length-1 sequence at a third of its time at batch 1 (the module
        call checks and flattens its weights at every call)."""
        h, new = self.step_features(z_t, state)
        return F.linear(h, self.head.weight, self.head.bias), new  # (B, d_out), ((L, B, H), (L, B, H))

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
        h, _ = self.rnn(self.input_proj(z))
        return h

    def step_features(self, z_t: Tensor, state: tuple[Tensor, Tensor]) -> tuple[Tensor, tuple[Tensor, Tensor]]:
        """(B, H) features of one step and the new state, the arithmetic of :meth:`step`, whose
        estimate is ``head`` of them."""
        x = F.linear(z_t, self.input_proj.weight, self.input_proj.bias)  # (B, H); no module-call overhead
        h0, c0 = state
        hs, cs = [], []
        for layer, weights in enumerate(self._cell_weights()):
            x, c = torch.lstm_cell(x, (h0[layer], c0[layer]), *weights)  # (B, H), (B, H)
            hs.append(x)
            cs.append(c)
        return x, (torch.stack(hs), torch.stack(cs))
