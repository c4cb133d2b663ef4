"""Causal sliding-window attention with ALiBi, shared by the two attention models (gpt2, filterformer).

References:
    Press, Smith, Lewis (2022), "Train Short, Test Long: Attention with Linear Biases Enables Input
    Length Extrapolation", https://arxiv.org/abs/2108.12409 (ALiBi, head slopes in section 3).

Both forms of the attention use one rule, so that a loop of steps equals the parallel form:

    query at t attends to keys s with 0 <= t - s < W          (W = the window, in steps)
    score(t, s) = q_t . k_s / sqrt(hs) - m_h (t - s)           (m_h = ALiBi slope of head h)

- :func:`window_attention` is the parallel form over a whole sequence. When T <= W the window never
  binds and one (T, T) causal score matrix is used; when T > W the queries are cut into blocks of W
  and each block looks at its own keys and the block before it, so memory is O(T W), not O(T^2).
- :func:`window_attention_step` is the recurrent form: the cache holds the last W keys and values
  as a shift register, newest last, with an additive mask that is -inf on slots not yet filled.
  Each step costs O(W), independent of how long the stream has run.

Shapes: B batch, nh heads, T time, hs head size, W window.
"""

from __future__ import annotations

import functools
import math

import torch
import torch.nn.functional as F
from torch import Tensor

from neural_estimator.models.dropout import keep_mask


def alibi_slopes(n_heads: int) -> Tensor:
    """ALiBi head slopes m_h (Press et al., section 3): the geometric sequence 2^(-8 h / n), h = 1..n.

    For a head count that is not a power of two, the slopes of the next lower power of two are
    followed by every other slope of the next higher one, as in the paper's reference code.
    """

    def power_of_two(n: int) -> list[float]:
        start = 2.0 ** (-8.0 / n)
        return [start ** (i + 1) for i in range(n)]

    if math.log2(n_heads).is_integer():
        slopes = power_of_two(n_heads)
    else:
        lower = 2 ** math.floor(math.log2(n_heads))
        slopes = power_of_two(lower) + power_of_two(2 * lower)[0::2][: n_heads - lower]
    return torch.tensor(slopes, dtype=torch.float32)  # (nh,)


def _bias(slopes: Tensor, dist: Tensor, allowed: Tensor) -> Tensor:
    """Additive score bias -m_h * dist where ``allowed``, -inf elsewhere; (nh, *dist.shape)."""
    bias = -slopes.view(-1, *([1] * dist.dim())) * dist.to(slopes.dtype)
    return bias.masked_fill(~allowed, float("-inf"))


def _cacheable() -> bool:
    """Whether a bias may come from :func:`_window_bias`'s cache: not while torch traces a graph
    (an ONNX export or ``torch.jit.trace``), where a cached tensor would enter as a constant made
    outside the trace."""
    return not (torch.jit.is_tracing() or torch.onnx.is_in_onnx_export())


@functools.lru_cache(maxsize=32)
def _window_bias(slopes: tuple[float, ...], dtype: torch.dtype, device: torch.device, T: int, window: int) -> Tensor:
    """The additive ALiBi/window bias of :func:`window_attention` for a length-T sequence: (nh, T, T)
    when T <= W, else the blocked (nh, nb, W, 2W). It depends on the slopes, T and W only, so it is
    made once per (slopes, T, W, dtype, device) and reused by every layer and every call (rebuilt in
    each layer on each call, it was about half of GPT-2's forward at B = 1). Read-only: callers
    never write into it. At most 32 kept (a few MB each at the paper's sizes)."""
    return _make_window_bias(torch.tensor(slopes, dtype=dtype, device=device), T, window)


def _make_window_bias(slopes: Tensor, T: int, window: int) -> Tensor:
    """The bias of :func:`_window_bias`, computed (see there)."""
    device = slopes.device
    if T <= window:
        t = torch.arange(T, device=device)
        dist = t[:, None] - t[None, :]  # (T, T) query minus key position
        return _bias(slopes, dist, dist >= 0)  # (nh, T, T)
    W = window
    nb = -(-T // W)
    a = torch.arange(W, device=device)
    j = torch.arange(2 * W, device=device)
    dist = (a[:, None] + W) - j[None, :]  # (W, 2W): query iW+a minus key (i-1)W+j
    allowed = (dist >= 0) & (dist < W)
    allowed = allowed.expand(nb, W, 2 * W).clone()  # (nb, W, 2W)
    allowed[0, :, :W] = False  # block 0 has no previous block (the zero padding of the operands)
    return _bias(slopes, dist.expand(nb, W, 2 * W), allowed)  # (nh, nb, W, 2W)


def window_bias(slopes: Tensor, T: int, window: int) -> Tensor:
    """The bias of :func:`window_attention` for a length-T sequence, from the cache where it may be
    (:func:`_cacheable`). Cached on the CPU only: the key reads the slopes' values, which on a GPU
    would be a device synchronisation per layer, and there the few small kernels that build the
    bias are not what a step waits for. Slopes that require a gradient are never cached (ALiBi's are
    fixed)."""
    if slopes.device.type == "cpu" and _cacheable() and not slopes.requires_grad:
        return _window_bias(tuple(slopes.tolist()), slopes.dtype, slopes.device, T, window)
    return _make_window_bias(slopes, T, window)


def window_attention(
    q: Tensor, k: Tensor, v: Tensor, slopes: Tensor, window: int, dropout_p: float = 0.0, fused: bool = True
) -> Tensor:
    """Parallel causal sliding-window ALiBi attention.

    Args:
        q, k, v: (B, nh, T, hs).
        slopes: (nh,) ALiBi slopes, same dtype and device as q.
        window: W >= 1, the number of keys (the query's own included) each query may see.
        dropout_p: attention dropout probability (pass 0.0 in eval mode).
        fused: pass 4-D operands and mask to ``scaled_dot_product_attention``, which lets torch take
            its fused CPU kernel (flash attention: scores never materialised); False passes the 3-D
            mask (and, blocked, 5-D operands) of the earlier code, which torch can only
            run on its unfused math path. Same result to float rounding; False is kept as the
            benchmark's "before" and the tests' reference. The fused kernel has no dropout, so with
            attention dropout on the CPU (a training step) ``fused`` takes :func:`_attention_dropout`
            instead (the math path without torch's per-element mask draws and softmax guards). The
            fused kernel's gain is in evaluation, validation and replay (one thread, Lorenz 96
            sizes, 500 x 500 steps: GPT-2 9.2k -> 33k steps/s, Filterformer 12.9k -> 40k;
            bench_training.py's val steps/s).

    Returns:
        (B, nh, T, hs) attention output.
    """
    B, nh, T, hs = q.shape
    bias = window_bias(slopes, T, window)  # (nh, T, T), or blocked (nh, nb, W, 2W) when T > W
    if T <= window:
        # A 4-D mask: torch's fused CPU (flash) kernel takes 2-D or 4-D masks only, and falls back
        # to the unfused math path (scores materialised, 3.5x slower here) for any other shape.
        if not fused:
            return F.scaled_dot_product_attention(q, k, v, attn_mask=bias, dropout_p=dropout_p)
        return _attention(q, k, v, bias[None], dropout_p)

    # Blocked form: query block i (positions iW..iW+W-1) sees key blocks i-1 and i.
    W = window
    nb = -(-T // W)
    pad = nb * W - T
    if pad:
        q, k, v = (F.pad(x, (0, 0, 0, pad)) for x in (q, k, v))
    qb = q.view(B, nh, nb, W, hs)  # (B, nh, nb, W, hs)
    kb = k.view(B, nh, nb, W, hs)
    vb = v.view(B, nh, nb, W, hs)
    k2 = torch.cat((F.pad(kb, (0, 0, 0, 0, 1, 0))[:, :, :-1], kb), dim=3)  # (B, nh, nb, 2W, hs)
    v2 = torch.cat((F.pad(vb, (0, 0, 0, 0, 1, 0))[:, :, :-1], vb), dim=3)
    if not fused:
        y = F.scaled_dot_product_attention(qb, k2, v2, attn_mask=bias, dropout_p=dropout_p)  # (B, nh, nb, W, hs)
        return y.reshape(B, nh, nb * W, hs)[:, :, :T]
    # Heads and blocks folded into one axis: 4-D operands and mask, for the fused kernel (above).
    y = _attention(
        qb.reshape(B, nh * nb, W, hs),
        k2.reshape(B, nh * nb, 2 * W, hs),
        v2.reshape(B, nh * nb, 2 * W, hs),
        bias.reshape(1, nh * nb, W, 2 * W),
        dropout_p,
    )  # (B, nh * nb, W, hs)
    return y.reshape(B, nh, nb * W, hs)[:, :, :T]


def _attention(q: Tensor, k: Tensor, v: Tensor, bias: Tensor, dropout_p: float) -> Tensor:
    """softmax(q k^T / sqrt(hs) + bias) v with 4-D operands: torch's fused kernel, or on the CPU with
    attention dropout :func:`_attention_dropout`."""
    if dropout_p > 0.0 and q.device.type == "cpu":
        return _attention_dropout(q, k, v, bias, dropout_p)
    return F.scaled_dot_product_attention(q, k, v, attn_mask=bias, dropout_p=dropout_p)


def _attention_dropout(q: Tensor, k: Tensor, v: Tensor, bias: Tensor, dropout_p: float) -> Tensor:
    """Attention with dropout on its weights, written out: (softmax(q k^T / sqrt(hs) + bias) * mask) v.

    What torch's math path computes, less two costs of its CPU training step (GPT-2, one thread:
    a fifth of the step): the mask is :func:`~neural_estimator.models.dropout.keep_mask` (four
    elements per random draw, not one), and the softmax is the plain one, not torch's guarded
    "safe" softmax for rows whose every key is masked (isneginf/all/where passes over the scores):
    no row here is, since each query sees at least its own key.

    Shapes: q (..., T, hs), k and v (..., S, hs), bias broadcastable to (..., T, S).
    """
    scores = torch.matmul(q, k.transpose(-2, -1)).mul_(q.shape[-1] ** -0.5) + bias  # (..., T, S)
    weights = torch.softmax(scores, dim=-1)
    return torch.matmul(weights * keep_mask(weights.shape, dropout_p, weights.device, weights.dtype), v)


def window_alibi(slopes: Tensor, window: int) -> Tensor:
    """ALiBi bias of the W cache slots, (nh, 1, W): -m_h * (W-1-slot); slot W-1 is the newest."""
    age = torch.arange(window - 1, -1, -1, dtype=slopes.dtype, device=slopes.device)  # (W,)
    return -slopes[:, None, None] * age  # (nh, 1, W)


def window_cache(
    batch: int, n_heads: int, head_size: int, window: int, device=None, dtype=None
) -> tuple[Tensor, Tensor]:
    """Empty KV cache for :func:`window_attention_step` (one per layer) and the slot mask.

    Returns:
        kv: (2, B, nh, W, hs) zeros, keys then values; slot W-1 is the newest.
        mask: (W,) 0 on filled slots, -inf on slots not filled yet (all of them at first). The mask
            is the same for every layer of a model, since all layers see the same positions.
    """
    kv = torch.zeros(2, batch, n_heads, window, head_size, device=device, dtype=dtype)
    mask = torch.full((window,), float("-inf"), device=device, dtype=dtype)
    return kv, mask


def advance_mask(mask: Tensor) -> Tensor:
    """The slot mask after one more step: every slot one step older, the newest slot filled."""
    return torch.cat((mask[1:], mask.new_zeros(1)))


def window_attention_step(qkv: Tensor, kv_cache: Tensor, attn_bias: Tensor) -> tuple[Tensor, Tensor]:
    """One step of causal sliding-window ALiBi attention.

    Args:
        qkv: (B, 3 nh hs) this step's query, key and value, concatenated in that order (the output
            of the fused q/k/v projection).
        kv_cache: (2, B, nh, W, hs) the previous W keys and values, newest last.
        attn_bias: (nh, 1, W) ``window_alibi + advance_mask(mask)``, i.e. the bias of the slots
            once this step's key sits in slot W-1.

    Returns:
        y: (B, nh hs) the heads' outputs side by side; the new kv_cache (the oldest slot dropped).
    """
    _, B, nh, W, hs = kv_cache.shape
    q, kv = qkv.view(B, 3, nh, 1, hs).split([1, 2], dim=1)  # (B, 1, nh, 1, hs), (B, 2, nh, 1, hs)
    kv_cache = torch.cat((kv_cache[:, :, :, 1:], kv.transpose(0, 1)), dim=3)  # (2, B, nh, W, hs)
    y = F.scaled_dot_product_attention(q[:, 0], kv_cache[0], kv_cache[1], attn_mask=attn_bias)  # (B, nh, 1, hs)
    return y.view(B, nh * hs), kv_cache
