"""Bounded context: a recurrent model run so that no estimate sees more than L steps of input.

The paper trains on length-L windows (L = 100) and evaluates over 500 steps run continuously. A
recurrent model whose state drifts once it has run longer than any window it was trained on (the
N-link SSMs, see docs/training.md) is accurate inside L steps of context and not beyond. Bounded context
runs K copies of the model; copy k starts from a zero state at step o_k = round(k L / K) and restarts
every L steps after (o_k + j L); the estimate at step t is that of the copy whose last restart is the
oldest, i.e. whose context is the longest:

    s(t) = 0                                         for t < L (copy 0, no restart yet)
    s(t) = min_k ( o_k + floor((t - o_k) / L) L )    over the copies with o_k <= t,

so every estimate after step L sees between L - ceil(L / K) + 1 and L steps, never more than the
training windows. K times the compute. (The paper's GPT-2 has a bounded context by construction: its
attention window.) This departs from the paper's continuous evaluation, so it is an option, off by
default: ``context`` and ``context_copies`` of :class:`~neural_estimator.serving.neural.NeuralEstimator`.
"""

from __future__ import annotations

import torch
from torch import nn


def copy_offsets(length: int, copies: int) -> list[int]:
    """o_k = round(k L / K), k = 0..K-1: the first restart of each copy."""
    return [int(round(k * length / copies)) for k in range(copies)]


def restart_of(t: int, length: int, copies: int) -> int:
    """s(t): the restart step of the copy whose context at step t is the longest (at most ``length``)."""
    if t < length:
        return 0
    return min(o + ((t - o) // length) * length for o in copy_offsets(length, copies) if o <= t)


def bounded_forward(model: nn.Module, z: torch.Tensor, length: int, copies: int) -> torch.Tensor:
    """Outputs (B, T, d_out) of ``model`` over z (B, T, d_in) with the context bounded: the output at
    step t is the model's output at t on the window z[:, s(t) : t + 1] alone (a zero state at s(t))."""
    T = z.shape[1]
    groups: dict[int, list[int]] = {}
    for t in range(T):
        groups.setdefault(restart_of(t, length, copies), []).append(t)
    out = None
    for start, steps in groups.items():
        y = model(z[:, start : steps[-1] + 1])  # (B, n, d_out)
        if out is None:
            out = y.new_empty(z.shape[0], T, y.shape[-1])
        out[:, steps] = y[:, [t - start for t in steps]]
    return out
