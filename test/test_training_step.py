"""A training step whose loss is finite but whose gradient is not is skipped (weights and optimiser
moments kept) and counted; an epoch that skipped every step is an error (training.step)."""

from __future__ import annotations

import pytest
import torch

from neural_estimator.training.recipe import TrainingError
from neural_estimator.training.step import check_skipped, guarded_step


def _model_and_optimizer():
    torch.manual_seed(0)
    model = torch.nn.Linear(2, 1)
    return model, torch.optim.AdamW(model.parameters(), lr=1e-2)


def _runaway_loss(model: torch.nn.Module) -> torch.Tensor:
    """A guarded loss, as a hybrid's: the runaway branch (exp overflows to inf) is replaced by 0, so
    the value is finite, while the backward pass multiplies 0 by inf (a NaN gradient)."""
    out = torch.exp(model(torch.tensor([[1e3, 1e3]])))
    return torch.where(torch.isfinite(out), out, torch.zeros_like(out)).sum()


def test_a_finite_gradient_steps():
    model, opt = _model_and_optimizer()
    before = [p.detach().clone() for p in model.parameters()]
    loss = model(torch.ones(4, 2)).square().mean()
    assert guarded_step(loss, model, opt, grad_clip=1.0) is True
    assert any(not torch.equal(b, p) for b, p in zip(before, model.parameters(), strict=True))


def test_a_non_finite_gradient_is_skipped_and_the_weights_kept():
    model, opt = _model_and_optimizer()
    guarded_step(model(torch.ones(4, 2)).square().mean(), model, opt, grad_clip=1.0)  # moments exist
    weights = [p.detach().clone() for p in model.parameters()]
    moments = {k: v.clone() for k, v in opt.state[model.weight].items() if torch.is_tensor(v)}
    loss = _runaway_loss(model)
    assert torch.isfinite(loss)  # the loss is fine; only its gradient is not
    assert guarded_step(loss, model, opt, grad_clip=1.0) is False
    for w, p in zip(weights, model.parameters(), strict=True):
        assert torch.equal(w, p) and p.grad is None
    for k, v in moments.items():
        assert torch.equal(v, opt.state[model.weight][k])
    # the run goes on: the next finite step is taken from the kept weights
    assert guarded_step(model(torch.ones(4, 2)).square().mean(), model, opt, grad_clip=1.0) is True
    assert all(torch.isfinite(p).all() for p in model.parameters())


def test_an_epoch_that_skipped_every_step_is_an_error():
    check_skipped(0, 315, 3, "resume")
    check_skipped(314, 315, 3, "resume")  # one step taken: the run goes on (the history counts them)
    with pytest.raises(TrainingError, match="every step of epoch 3 had a non-finite gradient"):
        check_skipped(315, 315, 3, "resume")
