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

The schedule (:func:`copy_offsets`, :func:`restart_of`, :func:`copy_schedule`) is plain integers,
and this module imports torch only inside the functions that step a model, so the torch-free
ONNX Runtime serving of a bounded-context graph (:mod:`neural_estimator.serving.onnx_runtime`)
follows the very same rule.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # annotations only: torch is imported where a model is stepped
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


def copy_schedule(t: int, length: int, copies: int) -> tuple[tuple[int, ...], int]:
    """(the copies that restart at step t, the copy served at t): copy k restarts at o_k + j L
    (j >= 0), and the served copy is the one whose last restart is s(t) (:func:`restart_of`).
    The offsets are distinct (K <= L), so exactly one copy is served."""
    chosen, restarts, served = restart_of(t, length, copies), [], 0
    for k, o in enumerate(copy_offsets(length, copies)):
        if t < o:
            continue
        if (t - o) % length == 0:
            restarts.append(k)
        if o + ((t - o) // length) * length == chosen:
            served = k
    return tuple(restarts), served


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


class BatchedCopies:
    """The K restarted copies of a recurrent model stepped as one batch of K x B streams.

    Copy k holds rows k B .. (k + 1) B - 1 of every state tensor (along that tensor's batch
    dimension, found by comparing ``init_state(1)`` with ``init_state(2)``); the input is repeated
    K times. A copy restarts (its rows set to a fresh state) at o_k + j L; a copy not started yet
    is stepped too, from the fresh state, and its output is never read before its first restart
    resets it. One batched step costs a fraction of K batch-B steps (the model's fixed cost per
    operation is paid once), with the same arithmetic per row up to float32 round-off.
    """

    def __init__(self, model: nn.Module, length: int, copies: int, batch: int, device, dtype) -> None:
        self.model, self.length, self.copies, self.batch = model, int(length), int(copies), int(batch)
        from neural_estimator.models.onnx_step import state_batch_dims

        self.offsets = copy_offsets(self.length, self.copies)
        self.dims = state_batch_dims(model, device, dtype)
        self.fresh = _tensors(model.init_state(self.batch, device=device, dtype=dtype))
        self.state = model.init_state(self.copies * self.batch, device=device, dtype=dtype)

    def step(self, z_t: torch.Tensor, t: int, step_fn) -> tuple[int, Any]:
        """Restart the copies due at step t, run ``step_fn(z, state) -> (*outputs, state)`` on all
        K x B rows, and return (k, outputs): the copy whose estimate is served at t (restarted at
        s(t)) and the outputs of every row (the caller takes copy k's rows, :meth:`rows`)."""
        restarts, served = copy_schedule(t, self.length, self.copies)
        for k in restarts:
            self._restart(k)
        *outs, self.state = step_fn(z_t.repeat(self.copies, 1), self.state)
        return served, outs

    def rows(self, k: int) -> slice:
        return slice(k * self.batch, (k + 1) * self.batch)

    def _restart(self, k: int) -> None:
        import torch

        states = []
        for s, fresh, d in zip(_tensors(self.state), self.fresh, self.dims):
            s = s.clone()
            s.narrow(d, k * self.batch, self.batch).copy_(fresh)
            states.append(s)
        self.state = states[0] if torch.is_tensor(self.state) else type(self.state)(states)


def _tensors(state: Any) -> list[torch.Tensor]:
    """A model state (one tensor or a tuple of tensors) as a list."""
    import torch

    return [state] if torch.is_tensor(state) else list(state)
