"""One optimiser step of a training run: the loss checked, the gradient clipped, and a step whose
gradient is not finite skipped rather than taken.

Why skip: a loss can be finite while its gradient is not. A hybrid's estimate is guarded (a
runaway component is replaced or clamped, :mod:`neural_estimator.models.kalmannet`), so its loss
stays finite, but the backward pass still multiplies through the runaway branch (0 x inf = NaN in
the derivative of exp or of a square root at 0). ``clip_grad_norm_`` then returns a NaN norm, scales
every gradient by it, and one AdamW step turns every weight into NaN: the model answers the guard's
training mean from then on and the run is lost without an error (seen on the quadrotor, the
ballistic and the bearings hybrids). Skipping the step keeps the weights and the optimiser's
moments as they were, as mixed-precision loss scaling does with an overflowed step; the run counts
the skipped steps per epoch (the history's ``skipped_steps``), and an epoch that skipped every step
is an error, not a silent stall.
"""

from __future__ import annotations

import math

import torch

from neural_estimator.training.recipe import TrainingError


def guarded_step(
    loss: torch.Tensor, model: torch.nn.Module, optimizer: torch.optim.Optimizer, grad_clip: float
) -> bool:
    """Backward ``loss``, clip the gradient's total norm to ``grad_clip`` and step; False (no step,
    gradients cleared) where the gradient's norm is not finite. The loss must be finite (the caller
    checks it, with the place it happened for the message)."""
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    norm = torch.nn.utils.clip_grad_norm_(model.parameters(), grad_clip)
    if not math.isfinite(float(norm)):
        optimizer.zero_grad(set_to_none=True)
        return False
    optimizer.step()
    return True


def check_skipped(skipped: int, attempted: int, epoch: int, resume_dir) -> None:
    """A TrainingError where every step of an epoch was skipped (the run diverged: no step can be
    taken from its weights), else nothing."""
    if attempted and skipped >= attempted:
        raise TrainingError(
            f"every step of epoch {epoch} had a non-finite gradient; the run diverged (a lower --lr may help; "
            f"the last good state is in {resume_dir})"
        )


__all__ = ["check_skipped", "guarded_step"]
