"""GPT-2 with ALiBi instead of learned positions, as a causal state estimator.

References:
    Radford et al. (2019), "Language Models are Unsupervised Multitask Learners" (GPT-2: pre-norm
        blocks, GELU MLP of width 4 d, final LayerNorm).
    Press, Smith, Lewis (2022), "Train Short, Test Long", https://arxiv.org/abs/2108.12409 (ALiBi).
    karpathy/nanoGPT ``model.py`` for the block layout and parameter names (c_attn, c_proj, c_fc).

Glossary: B batch, T time, d_in inputs z_t, D = n_embd, nh heads, hs = D / nh, W attention window.

    z (B, T, d_in) -> input_proj -> dropout -> n_layer x Block -> ln_f -> head -> x_hat (B, T, d_out)
    Block: h = h + attn(ln_1(h)); h = h + mlp(ln_2(h))

There is no position table: ALiBi adds -m_h (t - s) to the score of query t and key s, so the model
is translation invariant in time and runs on sequences longer than it was trained on. The paper's
"positions = 128" is the length of the learned table it replaces; it is kept in the config for the
record and is not used. The paper's "decode chunk length = 256" is the attention window W: every
query sees its own step and the W-1 steps before it, in the parallel form (blocked in chunks of W
when T > W) and in the step form (a KV cache of the last W steps), so ``forward`` equals a loop of
``step`` on sequences of any length (see :mod:`neural_estimator.models.layers`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

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
class GPT2Config:
    d_in: int
    d_out: int
    n_layer: int = 2
    n_head: int = 4
    n_embd: int = 60
    dropout: float = 0.1
    positions: int = 128  # paper's learned-position table size; unused with ALiBi (kept for the record)
    decode_chunk: int = 256  # attention window W (steps a query sees, itself included), both forms


class CausalSelfAttention(nn.Module):
    """Multi-head causal self-attention with ALiBi over a sliding window of W steps."""

    def __init__(self, cfg: GPT2Config) -> None:
        super().__init__()
        assert cfg.n_embd % cfg.n_head == 0
        self.n_head = cfg.n_head
        self.head_size = cfg.n_embd // cfg.n_head
        self.window = cfg.decode_chunk
        self.dropout = cfg.dropout
        self.c_attn = nn.Linear(cfg.n_embd, 3 * cfg.n_embd)  # q, k, v for all heads
        self.c_proj = nn.Linear(cfg.n_embd, cfg.n_embd)
        self.resid_drop = Dropout(cfg.dropout)
        self.attention_path = "fused"  # or "math": torch's unfused path (layers.window_attention)

    def forward(self, x: Tensor, slopes: Tensor) -> Tensor:
        B, T, D = x.shape
        q, k, v = self.c_attn(x).split(D, dim=2)  # 3 x (B, T, D)
        q, k, v = (t.view(B, T, self.n_head, self.head_size).transpose(1, 2) for t in (q, k, v))  # (B, nh, T, hs)
        p = self.dropout if self.training else 0.0
        y = window_attention(q, k, v, slopes, self.window, p, self.attention_path == "fused")  # (B, nh, T, hs)
        y = y.transpose(1, 2).reshape(B, T, D)
        return self.resid_drop(self.c_proj(y))

    def step(self, x: Tensor, kv_cache: Tensor, attn_bias: Tensor) -> tuple[Tensor, Tensor]:
        """x (B, D) -> (B, D); kv_cache (2, B, nh, W, hs). Functional calls: per step the cost is op count."""
        y, kv_cache = window_attention_step(F.linear(x, self.c_attn.weight, self.c_attn.bias), kv_cache, attn_bias)
        return F.linear(y, self.c_proj.weight, self.c_proj.bias), kv_cache


class MLP(nn.Module):
    def __init__(self, cfg: GPT2Config) -> None:
        super().__init__()
        self.c_fc = nn.Linear(cfg.n_embd, 4 * cfg.n_embd)
        self.c_proj = nn.Linear(4 * cfg.n_embd, cfg.n_embd)
        self.drop = Dropout(cfg.dropout)

    def forward(self, x: Tensor) -> Tensor:
        return self.drop(self.c_proj(F.gelu(self.c_fc(x), approximate="tanh")))

    def step(self, x: Tensor) -> Tensor:
        h = F.gelu(F.linear(x, self.c_fc.weight, self.c_fc.bias), approximate="tanh")
        return F.linear(h, self.c_proj.weight, self.c_proj.bias)


class Block(nn.Module):
    def __init__(self, cfg: GPT2Config) -> None:
        super().__init__()
        self.ln_1 = nn.LayerNorm(cfg.n_embd)
        self.attn = CausalSelfAttention(cfg)
        self.ln_2 = nn.LayerNorm(cfg.n_embd)
        self.mlp = MLP(cfg)

    def forward(self, x: Tensor, slopes: Tensor) -> Tensor:
        x = x + self.attn(self.ln_1(x), slopes)
        return x + self.mlp(self.ln_2(x))

    def step(self, x: Tensor, kv_cache: Tensor, attn_bias: Tensor) -> tuple[Tensor, Tensor]:
        ln_1, ln_2 = self.ln_1, self.ln_2
        a, kv_cache = self.attn.step(
            F.layer_norm(x, ln_1.normalized_shape, ln_1.weight, ln_1.bias, ln_1.eps), kv_cache, attn_bias
        )
        x = x + a
        return x + self.mlp.step(F.layer_norm(x, ln_2.normalized_shape, ln_2.weight, ln_2.bias, ln_2.eps)), kv_cache


class GPT2Model(nn.Module):
    """GPT-2 estimator: ``forward(z) (B, T, d_in) -> (B, T, d_out)``, ``step(z_t, state)``.

    The step state is ``(mask, kv_0, kv_1, ...)``: the (W,) slot mask shared by all layers (see
    :func:`~neural_estimator.models.layers.window_cache`) and each layer's (2, B, nh, W, hs) keys and
    values. Per step cost is O(W), independent of the stream's length.
    """

    def __init__(self, cfg: GPT2Config) -> None:
        super().__init__()
        self.cfg = cfg
        self.input_proj = nn.Linear(cfg.d_in, cfg.n_embd)
        self.drop = Dropout(cfg.dropout)
        self.blocks = nn.ModuleList(Block(cfg) for _ in range(cfg.n_layer))
        self.ln_f = nn.LayerNorm(cfg.n_embd)
        self.head = nn.Linear(cfg.n_embd, cfg.d_out)
        slopes = alibi_slopes(cfg.n_head)
        self.register_buffer("slopes", slopes, persistent=False)  # (nh,)
        self.register_buffer("slot_alibi", window_alibi(slopes, cfg.decode_chunk), persistent=False)  # (nh, 1, W)
        self.apply(self._init_weights)
        for name, p in self.named_parameters():
            if name.endswith("c_proj.weight"):  # GPT-2's scaled init of the residual projections
                nn.init.normal_(p, mean=0.0, std=0.02 / (2 * cfg.n_layer) ** 0.5)

    def set_window(self, window: int) -> None:
        """Serve (and train) with attention window W = ``window`` instead of the config's: no weight
        depends on W, so this is the same model seeing at most ``window`` steps (what the estimators'
        ``context`` option does for the attention models). Reset any step state afterwards."""
        if int(window) < 1:
            raise ValueError(f"attention window must be >= 1, got {window}")
        self.cfg = replace(self.cfg, decode_chunk=int(window))
        for block in self.blocks:
            block.attn.window = self.cfg.decode_chunk
        self.slot_alibi = window_alibi(self.slopes, self.cfg.decode_chunk)

    @staticmethod
    def _init_weights(module: nn.Module) -> None:
        if isinstance(module, nn.Linear):
            nn.init.normal_(module.weight, mean=0.0, std=0.02)
            nn.init.zeros_(module.bias)

    def forward(self, z: Tensor) -> Tensor:
        return self.head(self.features(z))  # (B, T, d_out)

    def init_state(self, batch: int, device=None, dtype=None) -> tuple[Tensor, ...]:
        p = self.head.weight
        device = p.device if device is None else device
        dtype = p.dtype if dtype is None else dtype
        cfg = self.cfg
        caches = [
            window_cache(batch, cfg.n_head, cfg.n_embd // cfg.n_head, cfg.decode_chunk, device, dtype)
            for _ in range(cfg.n_layer)
        ]
        return (caches[0][1], *(kv for kv, _ in caches))

    def step(self, z_t: Tensor, state: tuple[Tensor, ...]) -> tuple[Tensor, tuple[Tensor, ...]]:
        h, new = self.step_features(z_t, state)
        return F.linear(h, self.head.weight, self.head.bias), new  # (B, d_out)

    def onnx_form(self) -> nn.Module:
        """This model's batch-1 step in the form its ONNX graph is traced from (same arithmetic over
        a ring buffer of the window: :class:`~neural_estimator.models.onnx_forms.GPT2StepForm`)."""
        from neural_estimator.models.onnx_forms import GPT2StepForm

        return GPT2StepForm(self)

    # ---- the trunk's last hidden features (the covariance head's input, neural_estimator.serving.uncertainty) --
    def features(self, z: Tensor) -> Tensor:
        """(B, T, D): what ``head`` maps to the estimate, ``forward(z) == head(features(z))``."""
        h = self.drop(self.input_proj(z))  # (B, T, D)
        for block in self.blocks:
            h = block(h, self.slopes)
        return self.ln_f(h)

    def step_features(self, z_t: Tensor, state: tuple[Tensor, ...]) -> tuple[Tensor, tuple[Tensor, ...]]:
        """(B, D) features of one step and the new state: ``step`` is ``head`` of them."""
        mask = advance_mask(state[0])  # (W,)
        attn_bias = self.slot_alibi + mask  # (nh, 1, W)
        h = F.linear(z_t, self.input_proj.weight, self.input_proj.bias)  # (B, D)
        new: list[Tensor] = [mask]
        for block, kv in zip(self.blocks, state[1:]):
            h, kv = block.step(h, kv, attn_bias)
            new.append(kv)
        ln_f = self.ln_f
        return F.layer_norm(h, ln_f.normalized_shape, ln_f.weight, ln_f.bias, ln_f.eps), tuple(new)
