"""The six neural architectures, one self-contained file each, behind one interface.

Every architecture ``name`` has a frozen config dataclass ``XxxConfig(d_in, d_out, **paper
hyperparameters)`` and an ``nn.Module`` ``XxxModel(cfg)`` with:

- ``model(z)``: z (B, T, d_in) -> (B, T, d_out), the parallel form (training, offline runs); causal.
- ``model.init_state(batch, device=None, dtype=None)``: the recurrent state or KV cache (a tensor or
  a tuple of tensors) for ``batch`` streams, in the parameters' device and dtype by default.
- ``model.step(z_t, state) -> (y_t, state)``: z_t (B, d_in) -> (B, d_out), one time step. O(1) per
  step for the recurrent models (GRU, LSTM, Mamba, Mamba-2) and O(W) for the attention models
  (GPT-2, Filterformer: a KV cache over a sliding window of W steps that the parallel form uses
  too). In eval mode a loop of ``step`` equals ``forward`` on sequences of any length.

Filterformer also has ``forward_with_cov(z) -> (mean, cov)`` and ``step_with_cov(z_t, state) ->
(mean, cov, state)`` with cov (..., d_out, d_out).
"""

from __future__ import annotations

from typing import Any

import torch.nn as nn

from neural_estimator.methods import table
from neural_estimator.models.filterformer import FilterformerConfig, FilterformerModel
from neural_estimator.models.gpt2 import GPT2Config, GPT2Model
from neural_estimator.models.gru import GRUConfig, GRUModel
from neural_estimator.models.lstm import LSTMConfig, LSTMModel
from neural_estimator.models.mamba import MambaConfig, MambaModel
from neural_estimator.models.mamba2 import Mamba2Config, Mamba2Model

# The attention models' window hyperparameter (W: the steps a query sees), which bounds their
# context; the estimators' ``context`` option and ``TrainConfig.val_context`` set it.
# (Each method's spec in the table of methods holds it: ``table.spec(name).window_key``.)
ATTENTION_WINDOW = {s.name: s.window_key for s in table.methods(family=None, context="window")}

# {name: (config class, model class)}: the networks of the table of methods, by their specs' architecture
ARCHITECTURES: dict[str, tuple[type, type[nn.Module]]] = {
    s.name: (table.resolve(s.architecture[0]), table.resolve(s.architecture[1]))
    for s in table.methods(family=None)
    if s.architecture is not None
}


def build_model(name: str, d_in: int, d_out: int, **overrides: Any) -> nn.Module:
    """Build architecture ``name`` with the paper's hyperparameters, changed by ``overrides``.

    Raises:
        KeyError: unknown architecture, or an override that is not a field of its config.
    """
    if name not in ARCHITECTURES:
        raise KeyError(f"unknown architecture {name!r}; choose one of: {', '.join(ARCHITECTURES)}")
    config_cls, model_cls = ARCHITECTURES[name]
    fields = set(config_cls.__dataclass_fields__)
    unknown = sorted(set(overrides) - fields)
    if unknown:
        raise KeyError(f"{name}: unknown hyperparameter(s) {unknown}; valid: {sorted(fields - {'d_in', 'd_out'})}")
    return model_cls(config_cls(d_in=d_in, d_out=d_out, **overrides))


def count_parameters(model: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


__all__ = [
    "ARCHITECTURES",
    "build_model",
    "count_parameters",
    "GRUConfig",
    "GRUModel",
    "LSTMConfig",
    "LSTMModel",
    "GPT2Config",
    "GPT2Model",
    "FilterformerConfig",
    "FilterformerModel",
    "MambaConfig",
    "MambaModel",
    "Mamba2Config",
    "Mamba2Model",
]
