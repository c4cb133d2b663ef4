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

A model is built for a system: ``build_model(name, scenario, **hp)`` takes the scenario the model
will estimate (a :class:`~neural_estimator.scenarios.Scenario`, recorded data's
``DataScenario``, or :class:`SystemDims` where only the dimensions are known) and sizes the network
from it, ``d_in = dy + du`` (z_k = [y_k, u_{k-1}]) and ``d_out = dx``. The six architectures see
nothing of the scenario beyond these dimensions; an architecture that uses the system's equations
(a KalmanNet-style hybrid, with ``scenario.torch_dynamics()``) gets them through the same call.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import torch.nn as nn

from neural_estimator.methods import table
from neural_estimator.models.filterformer import FilterformerConfig, FilterformerModel
from neural_estimator.models.gpt2 import GPT2Config, GPT2Model
from neural_estimator.models.gru import GRUConfig, GRUModel
from neural_estimator.models.kalmannet import KalmanNetConfig, KalmanNetModel
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


class System(Protocol):
    """What :func:`build_model` reads of a scenario: its state, observation and control dimensions."""

    @property
    def dx(self) -> int: ...

    @property
    def dy(self) -> int: ...

    @property
    def du(self) -> int: ...


@dataclass(frozen=True)
class SystemDims:
    """A system known only by its dimensions (dx states, dy observations, du controls): a
    checkpoint card whose scenario cannot be rebuilt here, a benchmark, a test of the networks."""

    dx: int
    dy: int
    du: int = 0


def model_dims(scenario: System) -> tuple[int, int]:
    """(d_in, d_out) = (dy + du, dx) of a model for ``scenario``: it reads z_k = [y_k, u_{k-1}] and
    returns x_hat_k."""
    return int(scenario.dy) + int(scenario.du), int(scenario.dx)


def build_model(name: str, scenario: System, **hp: Any) -> nn.Module:
    """Build architecture ``name`` for ``scenario`` with the paper's hyperparameters, changed by ``hp``.

    ``d_in`` and ``d_out`` come from the scenario (:func:`model_dims`), never from ``hp``.

    A hybrid (family "hybrid" in the table of methods: KalmanNet) uses the system's equations, so
    its model class also takes ``scenario`` itself, ``model_cls(cfg, scenario)``.

    Raises:
        KeyError: unknown architecture, or a hyperparameter that is not a field of its config.
        ValueError: a hybrid for a system without a differentiable f and h (``SystemDims``, recorded
            data without a model): a one-line message.
    """
    if name not in ARCHITECTURES:
        raise KeyError(f"unknown architecture {name!r}; choose one of: {', '.join(ARCHITECTURES)}")
    config_cls, model_cls = ARCHITECTURES[name]
    fields = set(config_cls.__dataclass_fields__) - {"d_in", "d_out"}
    unknown = sorted(set(hp) - fields)
    if unknown:
        raise KeyError(
            f"{name}: unknown hyperparameter(s) {unknown}; valid: {sorted(fields)} "
            "(d_in and d_out come from the scenario)"
        )
    d_in, d_out = model_dims(scenario)
    cfg = config_cls(d_in=d_in, d_out=d_out, **hp)
    return model_cls(cfg, scenario) if table.has(name, family="hybrid") else model_cls(cfg)


def count_parameters(model: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


__all__ = [
    "ARCHITECTURES",
    "System",
    "SystemDims",
    "build_model",
    "count_parameters",
    "model_dims",
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
    "KalmanNetConfig",
    "KalmanNetModel",
]
