"""Filterformer: one causal attention over the observation prefix and a geometric-attention head.

References:
    Horvath, Kratsios, Limmer, Yang (2025), "Transformers Can Solve Non-Linear and Non-Markovian
        Filtering Problems in Continuous Time For Conditionally Gaussian Signals",
        https://arxiv.org/abs/2310.19603 (the filterformer: an attention-based path embedding,
        an MLP, and a "geometric attention" read-out whose values are Gaussian measures).
    Press, Smith, Lewis (2022), https://arxiv.org/abs/2108.12409 (ALiBi, used here for time).

Glossary: B batch, T time, D = d_model (the paper's "encoding dim" 108), nh heads, hs = D / nh,
W attention window, K Gaussian components, n = d_out.

    z (B, T, d_in) -> input_proj -> dropout                     observation embedding e_t
    e = e + attn(ln_1(e))                                        ONE causal self-attention (path encoding)
    e = e + mlp(ln_2(e))                                         MLP
    w_t = softmax(readout(ln_f(e_t)))             (B, T, K)     geometric attention over K components
    mean_t = sum_k w_tk m_k                       (B, T, n)     the estimate x_hat_t
    cov_t  = sum_k w_tk diag(s_k^2)                              within-component spread
           + sum_k w_tk (m_k - mean_t)(m_k - mean_t)^T           between-component spread

Adaptation to causal discrete-time filtering (what differs from the paper's construction):

- The paper embeds a whole continuous-time observation path (time-augmented) by attention and maps
  it to a Gaussian law. Here the path is the discrete prefix z_{0..t} and the embedding is computed
  for every t at once: query t attends to keys s <= t only (causal mask), so x_hat_t depends on
  z_{0..t} alone and the model is a filter, not a smoother.
- Time enters through an ALiBi recency bias -m_h (t - s) instead of a time channel: the embedding
  is translation invariant in time, so it does not see absolute times it was never trained on and
  runs past the training length. The attention sees a sliding window of the last W steps
  (``window``) in both the parallel and the step form, so ``forward`` equals a loop of ``step``.
- The read-out keeps the paper's idea of attention whose values are K learned Gaussian measures
  N(m_k, diag(s_k^2)) and whose weights are a softmax of the encoding. The paper combines them in
  the 2-Wasserstein geometry; here they are combined as a mixture, and the head reports the
  mixture's first two moments: mean = the point estimate (trained with the other models' loss) and
  covariance = the law of total covariance above. Components are diagonal (n parameters each); the
  mixture covariance is full (the between-component term couples the states) and is symmetric
  positive semi-definite by construction (positive definite: s_k > 0). The estimate lies in the
  convex hull of the m_k, the architectural bias of a geometric-attention read-out.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

from neural_estimator.models.dropout import Dropout
from neural_estimator.models.layers import (
    advance_mask,
    alibi_slopes,
    window_alibi,
    window_attention,
    window_attention_step,
    window_cache,
)


@dataclass(frozen=True)
class FilterformerConfig:
    d_in: int
    d_out: int
    d_model: int = 108  # the paper's encoding dimension
    n_head: int = 4
    dropout: float = 0.1
    d_mlp: int = 216  # MLP hidden width (2 d_model keeps the total near the 100k budget)
    n_components: int = 32  # K Gaussian components of the geometric-attention head
    window: int = 256  # attention window W (steps a query sees, itself included), both forms


class PrefixAttention(nn.Module):
    """Causal multi-head self-attention over the prefix, ALiBi time bias, window of W steps."""

    def __init__(self, cfg: FilterformerConfig) -> None:
        super().__init__()
        assert cfg.d_model % cfg.n_head == 0
        self.n_head = cfg.n_head
        self.head_size = cfg.d_model // cfg.n_head
        self.window = cfg.window
        self.dropout = cfg.dropout
        self.qkv = nn.Linear(cfg.d_model, 3 * cfg.d_model)
        self.proj = nn.Linear(cfg.d_model, cfg.d_model)
        self.drop = Dropout(cfg.dropout)
        self.attention_path = "fused"  # or "math": torch's unfused path (layers.window_attention)

    def forward(self, x: Tensor, slopes: Tensor) -> Tensor:
        B, T, D = x.shape
        q, k, v = self.qkv(x).split(D, dim=2)  # 3 x (B, T, D)
        q, k, v = (t.view(B, T, self.n_head, self.head_size).transpose(1, 2) for t in (q, k, v))  # (B, nh, T, hs)
        p = self.dropout if self.training else 0.0
        y = window_attention(q, k, v, slopes, self.window, p, self.attention_path == "fused")  # (B, nh, T, hs)
        return self.drop(self.proj(y.transpose(1, 2).reshape(B, T, D)))

    def step(self, x: Tensor, kv_cache: Tensor, attn_bias: Tensor) -> tuple[Tensor, Tensor]:
        """x (B, D) -> (B, D); kv_cache (2, B, nh, W, hs). Functional calls: per step the cost is op count."""
        y, kv_cache = window_attention_step(F.linear(x, self.qkv.weight, self.qkv.bias), kv_cache, attn_bias)
        return F.linear(y, self.proj.weight, self.proj.bias), kv_cache


class GeometricAttentionHead(nn.Module):
    """Softmax weights over K learned Gaussians N(m_k, diag(s_k^2)); returns the mixture's moments."""

    def __init__(self, cfg: FilterformerConfig) -> None:
        super().__init__()
        K, n = cfg.n_components, cfg.d_out
        self.readout = nn.Linear(cfg.d_model, K)  # attention scores of the K components
        self.means = nn.Parameter(torch.randn(K, n))  # m_k; targets are normalised, so N(0, I) spreads them
        self.log_std = nn.Parameter(torch.full((K, n), -1.0))  # log s_k

    def weights(self, h: Tensor) -> Tensor:
        return torch.softmax(F.linear(h, self.readout.weight, self.readout.bias), dim=-1)  # (..., K)

    def mean(self, h: Tensor) -> Tensor:
        return self.weights(h) @ self.means  # (..., n)

    def moments(self, h: Tensor) -> tuple[Tensor, Tensor]:
        w = self.weights(h)  # (..., K)
        mean = w @ self.means  # (..., n)
        within = w @ torch.exp(2.0 * self.log_std)  # (..., n) diagonal of sum_k w_k diag(s_k^2)
        dev = self.means - mean.unsqueeze(-2)  # (..., K, n)
        between = (dev * w.unsqueeze(-1)).transpose(-1, -2) @ dev  # (..., n, n)
        cov = between + torch.diag_embed(within)
        return mean, 0.5 * (cov + cov.transpose(-1, -2))


class FilterformerModel(nn.Module):
    """Filterformer estimator: ``forward(z) -> mean``, ``forward_with_cov(z) -> (mean, cov)``, ``step``.

    The step state is ``(mask, kv)``: the (W,) slot mask and the (2, B, nh, W, hs) keys and values
    of the single attention layer (see :mod:`neural_estimator.models.layers`).
    """

    def __init__(self, cfg: FilterformerConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.input_proj = nn.Linear(cfg.d_in, cfg.d_model)
        self.drop = Dropout(cfg.dropout)
        self.ln_1 = nn.LayerNorm(cfg.d_model)
        self.attn = PrefixAttention(cfg)
        self.ln_2 = nn.LayerNorm(cfg.d_model)
        self.mlp = nn.Sequential(
            nn.Linear(cfg.d_model, cfg.d_mlp), nn.GELU(), nn.Linear(cfg.d_mlp, cfg.d_model), Dropout(cfg.dropout)
        )
        self.ln_f = nn.LayerNorm(cfg.d_model)
        self.head = GeometricAttentionHead(cfg)
        slopes = alibi_slopes(cfg.n_head)
        self.register_buffer("slopes", slopes, persistent=False)  # (nh,)
        self.register_buffer("slot_alibi", window_alibi(slopes, cfg.window), persistent=False)  # (nh, 1, W)

    def set_window(self, window: int) -> None:
        """Serve (and train) with attention window W = ``window`` instead of the config's (no weight
        depends on W; see :meth:`neural_estimator.models.gpt2.GPT2Model.set_window`). Reset any step
        state afterwards."""
        if int(window) < 1:
            raise ValueError(f"attention window must be >= 1, got {window}")
        self.cfg = replace(self.cfg, window=int(window))
        self.attn.window = self.cfg.window
        self.slot_alibi = window_alibi(self.slopes, self.cfg.window)

    def encode(self, z: Tensor) -> Tensor:
        e = self.drop(self.input_proj(z))  # (B, T, D)
        e = e + self.attn(self.ln_1(e), self.slopes)
        e = e + self.mlp(self.ln_2(e))
        return self.ln_f(e)  # (B, T, D)

    def forward(self, z: Tensor) -> Tensor:
        return self.head.mean(self.encode(z))  # (B, T, d_out)

    def forward_with_cov(self, z: Tensor) -> tuple[Tensor, Tensor]:
        """(mean (B, T, n), cov (B, T, n, n)) of the head's Gaussian mixture."""
        return self.head.moments(self.encode(z))

    def init_state(self, batch: int, device=None, dtype=None) -> tuple[Tensor, Tensor]:
        p = self.input_proj.weight
        device = p.device if device is None else device
        dtype = p.dtype if dtype is None else dtype
        cfg = self.cfg
        kv, mask = window_cache(batch, cfg.n_head, cfg.d_model // cfg.n_head, cfg.window, device, dtype)
        return mask, kv

    def _encode_step(self, z_t: Tensor, state: tuple[Tensor, Tensor]) -> tuple[Tensor, tuple[Tensor, Tensor]]:
        mask = advance_mask(state[0])  # (W,)
        e = F.linear(z_t, self.input_proj.weight, self.input_proj.bias)  # (B, D)
        ln_1, ln_2, ln_f = self.ln_1, self.ln_2, self.ln_f
        fc1, fc2 = self.mlp[0], self.mlp[2]
        a, kv = self.attn.step(
            F.layer_norm(e, ln_1.normalized_shape, ln_1.weight, ln_1.bias, ln_1.eps), state[1], self.slot_alibi + mask
        )
        e = e + a
        m = F.layer_norm(e, ln_2.normalized_shape, ln_2.weight, ln_2.bias, ln_2.eps)
        e = e + F.linear(F.gelu(F.linear(m, fc1.weight, fc1.bias)), fc2.weight, fc2.bias)
        return F.layer_norm(e, ln_f.normalized_shape, ln_f.weight, ln_f.bias, ln_f.eps), (mask, kv)

    def onnx_form(self) -> nn.Module:
        """This model's batch-1 step in the form its ONNX graph is traced from (same arithmetic over
        a ring buffer of the window: :class:`~neural_estimator.models.onnx_forms.FilterformerStepForm`)."""
        from neural_estimator.models.onnx_forms import FilterformerStepForm

        return FilterformerStepForm(self)

    def step(self, z_t: Tensor, state: tuple[Tensor, Tensor]) -> tuple[Tensor, tuple[Tensor, Tensor]]:
        h, state = self._encode_step(z_t, state)
        return self.head.mean(h), state  # (B, d_out)

    def step_with_cov(self, z_t: Tensor, state: tuple[Tensor, Tensor]) -> tuple[Tensor, Tensor, tuple[Tensor, Tensor]]:
        """One step returning (mean (B, n), cov (B, n, n), state)."""
        h, state = self._encode_step(z_t, state)
        mean, cov = self.head.moments(h)
        return mean, cov, state

    # ---- the trunk's last hidden features (the covariance head's input, neural_estimator.serving.uncertainty) --
    def features(self, z: Tensor) -> Tensor:
        """(B, T, D): the encoding the geometric-attention head reads, ``forward(z) == head.mean(features(z))``."""
        return self.encode(z)

    def step_features(self, z_t: Tensor, state: tuple[Tensor, Tensor]) -> tuple[Tensor, tuple[Tensor, Tensor]]:
        """(B, D) features of one step and the new state."""
        return self._encode_step(z_t, state)

    def mean_of(self, h: Tensor) -> Tensor:
        """The estimate from features (the geometric-attention head's mean)."""
        return self.head.mean(h)
