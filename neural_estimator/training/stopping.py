"""When a training run stops, beside the paper's early stopping: the learning-rate reductions of a
history, the zoo's convergence rule and the plateau rule for long CPU runs."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from neural_estimator.training.recipe import TrainingError


def lr_reductions(history: list[dict[str, Any]], initial_lr: float) -> int:
    """How many times the learning rate went down over a run's history (ReduceLROnPlateau steps)."""
    lrs = [initial_lr] + [h["lr"] for h in history]
    return sum(b < a for a, b in zip(lrs, lrs[1:]))


def converged(stopped: str | None, history: list[dict[str, Any]], initial_lr: float) -> bool:
    """The zoo's convergence rule: early stopping triggered, or the learning rate reduced >= 3 times."""
    return bool(stopped and stopped.startswith("early stopping")) or lr_reductions(history, initial_lr) >= 3


def plateau_rule(
    initial_lr: float, epochs: int = 10, tol: float = 0.01, min_reductions: int = 3
) -> Callable[[list[dict[str, Any]]], str | None]:
    """A stated stopping budget for long CPU runs, cheaper than the paper's 30-epoch early stopping:
    stop once the learning rate has been reduced at least ``min_reductions`` times and the last
    ``epochs`` epochs did not lower the validation loss by ``tol`` (relative) against the ``epochs``
    before them: min(v over the last N) > (1 - tol) * min(v over the N before), N = ``epochs``.

    Window against window, not against the best so far: a curve whose first epoch was a lucky low
    and which is still coming down from a later high (the bearings Mamba: 0.52 at epoch 1, above it
    until epoch 14, 0.41 at epoch 28) is improving, not flat. Replayed on the first full-recipe
    histories (N = 10, tol = 1 %), the rule stops no run at a validation loss more than 1.1 %
    above the run's final best, and saves 0.5-0.7 h of CPU on the Lorenz 96 SSMs and the N-link
    Mamba-2.

    Returns ``stop_when(history) -> reason or None`` for :func:`train`. A run it stops is converged
    by the zoo's rule (learning rate reduced >= 3 times) when ``min_reductions >= 3``.
    """
    if epochs < 1 or not 0.0 <= tol < 1.0 or min_reductions < 0:
        raise TrainingError(
            f"plateau rule needs epochs >= 1, 0 <= tol < 1, min_reductions >= 0; got {epochs}, {tol}, {min_reductions}"
        )

    def stop_when(history: list[dict[str, Any]]) -> str | None:
        if len(history) < 2 * epochs:
            return None
        k = lr_reductions(history, initial_lr)
        if k < min_reductions:
            return None
        before = min(h["val_loss"] for h in history[-2 * epochs : -epochs])
        recent = min(h["val_loss"] for h in history[-epochs:])
        if recent > (1.0 - tol) * before:
            return (
                f"plateau: the best validation loss of the last {epochs} epochs ({recent:.4g}) is not "
                f"{100 * tol:g} % below that of the {epochs} before ({before:.4g}), after {k} learning-rate reductions"
            )
        return None

    return stop_when
