"""Dropout with a CPU keep-mask four times cheaper to draw than torch's, for the attention models.

On the CPU, torch draws a dropout mask one random number per element (``bernoulli_``: about 8 ns an
element here, 20 % of a GPT-2 or Filterformer training step, attention dropout included). Here one
64-bit draw serves four elements: the draw is cut into four 16-bit integers u, each uniform on
[-2^15, 2^15), and an element is dropped when u < -2^15 + d with d = round(p 2^16), so

    P(drop) = p' = d / 2^16   (|p' - p| <= 2^-17; p = 0.1 gives p' = 0.1000061)
    kept elements are scaled by 1 / (1 - p'), so E[mask] = 1 exactly, as in torch's dropout.

The mask comes from torch's default generator (``torch.randint``), so a seeded run repeats
exactly, on any thread count. On other devices (CUDA) :class:`Dropout` is torch's dropout: there
the fused kernels are faster than any mask built outside them.
"""

from __future__ import annotations

import math

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

_LANES = 4  # 16-bit lanes in one int64 draw
_CODES = 1 << 16


def dropped_fraction(p: float) -> float:
    """p', the drop probability :func:`keep_mask` realises for the requested p (p quantised to 2^-16)."""
    return round(p * _CODES) / _CODES


def keep_mask(shape: torch.Size | tuple[int, ...], p: float, device=None, dtype=None) -> Tensor:
    """A dropout keep-mask of ``shape``: 0 with probability p' (:func:`dropped_fraction`), else 1 / (1 - p').

    Args:
        shape: the mask's shape (that of the tensor it multiplies).
        p: drop probability, 0 <= p < 1.
        device, dtype: of the mask (float dtype; default torch's).
    """
    if not 0.0 <= p < 1.0:
        raise ValueError(f"dropout probability must be in [0, 1), got {p}")
    dropped = round(p * _CODES)
    n = math.prod(shape)
    if dropped == 0 or n == 0:
        return torch.ones(shape, device=device, dtype=dtype)
    draws = torch.randint(-(2**63), 2**63 - 1, (-(-n // _LANES),), dtype=torch.int64, device=device)
    lanes = draws.view(torch.int16)[:n].view(shape)  # each uniform on [-2^15, 2^15)
    keep = lanes >= dropped - _CODES // 2
    return keep.to(dtype or torch.get_default_dtype()).mul_(_CODES / (_CODES - dropped))


def dropout(x: Tensor, p: float, training: bool = True, fast: bool = True) -> Tensor:
    """``F.dropout(x, p, training)`` with :func:`keep_mask` on the CPU when ``fast``."""
    if not training or p == 0.0:
        return x
    if not fast or x.device.type != "cpu":
        return F.dropout(x, p, training=True)
    return x * keep_mask(x.shape, p, x.device, x.dtype)


class Dropout(nn.Module):
    """``nn.Dropout`` drawing its CPU mask with :func:`keep_mask` (no parameters or buffers, so a
    model's state dict is the same as with ``nn.Dropout``). ``fast = False`` is torch's dropout, kept
    as the benchmark's "before" path."""

    def __init__(self, p: float = 0.5) -> None:
        super().__init__()
        if not 0.0 <= p < 1.0:
            raise ValueError(f"dropout probability must be in [0, 1), got {p}")
        self.p = p
        self.fast = True

    def forward(self, x: Tensor) -> Tensor:
        return dropout(x, self.p, self.training, self.fast)

    def extra_repr(self) -> str:
        return f"p={self.p}"
