"""The attention models' CPU dropout: the keep-mask's law, the module, and attention with dropout."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn as nn

from neural_estimator.models import SystemDims, build_model
from neural_estimator.models.dropout import Dropout, dropped_fraction, keep_mask
from neural_estimator.models.layers import alibi_slopes, window_attention


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tiny tensors: one intra-op thread


@pytest.mark.parametrize("p", [0.1, 0.5, 0.03])
def test_keep_mask_law(p):
    """Each of the four 16-bit lanes of a draw drops with probability p' (within 5 sigma), kept
    elements are scaled by 1 / (1 - p'), and the mask's mean is 1."""
    torch.manual_seed(0)
    n = 400_000
    mask = keep_mask((n,), p)
    q = dropped_fraction(p)
    assert abs(q - p) <= 2**-17
    scale = 1.0 / (1.0 - q)
    values = torch.unique(mask)
    torch.testing.assert_close(values, torch.tensor([0.0, scale]), rtol=1e-6, atol=0)
    sigma = math.sqrt(q * (1 - q) / (n / 4))
    for lane in range(4):
        dropped = (mask.view(-1, 4)[:, lane] == 0).double().mean().item()
        assert abs(dropped - q) < 5 * sigma, (lane, dropped, q)
    assert abs(mask.double().mean().item() - 1.0) < 5 * sigma * scale


def test_keep_mask_is_seeded_and_shaped():
    torch.manual_seed(5)
    a = keep_mask((3, 7, 5), 0.2, dtype=torch.float64)
    b = keep_mask((3, 7, 5), 0.2, dtype=torch.float64)
    torch.manual_seed(5)
    a2 = keep_mask((3, 7, 5), 0.2, dtype=torch.float64)
    assert a.shape == (3, 7, 5) and a.dtype == torch.float64
    assert torch.equal(a, a2) and not torch.equal(a, b)
    assert torch.equal(keep_mask((4,), 0.0), torch.ones(4))
    assert keep_mask((0, 3), 0.5).shape == (0, 3)
    for bad in (-0.1, 1.0, 1.5):
        with pytest.raises(ValueError, match="dropout probability"):
            keep_mask((4,), bad)
        with pytest.raises(ValueError, match="dropout probability"):
            Dropout(bad)


def test_dropout_module_is_x_times_its_mask_in_training_and_identity_in_eval():
    drop = Dropout(0.3)
    x = torch.randn(6, 9, 4, dtype=torch.float64, requires_grad=True)
    torch.manual_seed(11)
    y = drop(x)
    torch.manual_seed(11)
    mask = keep_mask(x.shape, 0.3, dtype=torch.float64)
    torch.testing.assert_close(y, x * mask, rtol=0, atol=0)
    y.sum().backward()
    torch.testing.assert_close(x.grad, mask, rtol=0, atol=0)
    drop.eval()
    assert drop(x) is x
    assert Dropout(0.0)(x) is x
    assert "p=0.3" in repr(drop)
    assert not list(drop.parameters()) and not list(drop.buffers()) and drop.state_dict() == {}


def test_dropout_module_fast_off_is_torchs_dropout():
    drop, ref = Dropout(0.25), nn.Dropout(0.25)
    drop.fast = False
    x = torch.randn(50, 8)
    torch.manual_seed(3)
    y = drop(x)
    torch.manual_seed(3)
    torch.testing.assert_close(y, ref(x), rtol=0, atol=0)


@pytest.mark.parametrize("T,W", [(12, 16), (40, 16)])  # one block, and the blocked form
def test_attention_with_dropout_equals_the_math_path_when_nothing_is_dropped(T, W):
    """A p below 2^-17 takes the written-out dropout path and drops nothing (p' = 0): value and
    gradients equal torch's math path without dropout, float64."""
    torch.manual_seed(2)
    B, nh, hs = 3, 4, 6
    base = [torch.randn(B, nh, T, hs, dtype=torch.float64) for _ in range(3)]
    slopes = alibi_slopes(nh).double()
    out = {}
    for p, fused in ((1e-9, True), (0.0, False)):
        q, k, v = (t.clone().requires_grad_() for t in base)
        y = window_attention(q, k, v, slopes, W, p, fused=fused)
        (y * torch.linspace(-1, 1, hs, dtype=torch.float64)).sum().backward()
        out[p] = (y.detach(), q.grad, k.grad, v.grad)
    for a, b in zip(out[1e-9], out[0.0]):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12)


@pytest.mark.slow
@pytest.mark.parametrize("T,W", [(12, 16), (40, 16)])
def test_attention_dropout_is_unbiased(T, W):
    """Dropout acts on the attention weights: one draw differs from the no-dropout output, and the
    mean over draws converges to it (the output is linear in the mask, whose mean is 1)."""
    torch.manual_seed(4)
    B, nh, hs = 2, 4, 5
    q, k, v = (torch.randn(B, nh, T, hs, dtype=torch.float64) for _ in range(3))
    slopes = alibi_slopes(nh).double()
    clean = window_attention(q, k, v, slopes, W, 0.0)
    draws = torch.stack([window_attention(q, k, v, slopes, W, 0.5) for _ in range(2000)])
    assert (draws[0] - clean).abs().max() > 0.05
    stderr = draws.std(0) / math.sqrt(draws.shape[0])
    assert ((draws.mean(0) - clean).abs() <= 5 * stderr + 1e-12).double().mean() > 0.999


@pytest.mark.parametrize("name", ["gpt2", "filterformer"])
def test_attention_models_train_with_the_fast_dropout_and_evaluate_without_it(name):
    torch.manual_seed(6)
    model = build_model(name, SystemDims(dx=2, dy=3)).double()
    assert any(isinstance(m, Dropout) for m in model.modules())
    assert not any(isinstance(m, nn.Dropout) for m in model.modules())
    z = torch.randn(2, 30, 3, dtype=torch.float64)
    a, b = model(z), model(z)
    assert not torch.allclose(a, b)  # training: masks drawn afresh
    model.eval()
    torch.testing.assert_close(model(z), model(z), rtol=0, atol=0)
