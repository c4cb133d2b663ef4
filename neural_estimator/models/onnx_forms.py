"""The batch-1 steps of Mamba, Mamba-2, GPT-2 and Filterformer as ONNX Runtime runs them fastest:
what :func:`~neural_estimator.models.onnx_step.export_step` traces for these four models.

At batch 1 an ONNX Runtime step costs a fixed ~0.3-1 us per operator, whatever its size, so the
graph's cost is its number of operators (and, for the attention caches, the bytes it copies), not
its FLOPs. The models' own ``step`` is written for a batch of B streams in mamba_ssm's state layout;
traced as it is, it leaves reshapes, unsqueezes and splits between the arithmetic. The forms here
compute the same step for one stream (the same products and sums, in float32; the tests hold them
equal to ``step``) with these changes, none of which touches a trained weight's value:

- **Row vectors and transposed states.** Every activation is a (1, n) row; the state of each SSM
  layer is held without the batch axis: the conv window as (K, C) (newest row last) and Mamba's SSM
  state as (N, E) (Mamba-2's: :class:`Mamba2StepForm`). Then the discretised update and the
  read-out are products of rows and the state with no reshape: with u, delta rows (1, E), b, c rows
  (1, N),

      S' = S * exp(delta * A^T) + b^T (delta * u)      (N, E): b^T (delta u) is a (N,1)(1,E) product
      y  = c S' + D * u                                  (1, E)

  S is mamba_ssm's (E, N) state transposed; the graph's state is its own (``OrtStep`` owns it). The
  conv's weighted sum of its window and its bias are one Gemm: [1 ... 1] (w * window) + bias.
- **Weight-only expressions precomputed** at export: A = -exp(A_log) (transposed); Mamba-2's
  per-head delta and decay repeated over each head's P channels, by repeating its dt rows of
  in_proj (and the bias dt_bias) P times, so the one in_proj Gemm also adds dt_bias and the step
  never expands heads to channels.
- **Fusable patterns.** RMSNorm as x / sqrt(mean(x^2) + eps) * w (Pow, ReduceMean, Add, Sqrt, Div,
  Mul: ONNX Runtime fuses it to one SimplifiedLayerNormalization), GPT-2's tanh GELU as
  0.5 x (1 + tanh(sqrt(2/pi) (x + 0.044715 x^3))) with Pow (fused to one FastGelu), SiLU as
  x * sigmoid(x) (fused to QuickGelu), a linear layer plus the residual (fused to one Gemm).
- **The attention window's cache as a ring buffer** (GPT-2, Filterformer). The model's cache is a
  shift register (every step copies the whole (2, nh, W, hs) cache one slot down, and the graph
  copied it twice more to slice and split it); here each layer's keys and values are written into
  slot t mod W of an (nh, W, hs) cache by one ScatterND (a copy of the cache and the write of the
  new entries; a Where over the cache measured as slow as the copies it replaced), and the ALiBi
  bias follows each slot's age, kept as state: age' = 0 on the slot written, age + 1 elsewhere
  (+inf on slots never written), bias = -m_h * age (so -inf there), the very products the model
  computes (``layers.window_alibi`` plus the mask). The softmax sums the same W terms in slot
  order instead of age order.

The states start at one constant per tensor (zeros; the ages +inf), as ``export_step`` records.
Each form keeps the trunk's ``head`` (so a covariance head's wrapper reads the same features) and
serves batch 1 only.
"""

from __future__ import annotations

import math

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

_GELU_C = math.sqrt(2.0 / math.pi)


def _const(t: Tensor) -> Tensor:
    return t.detach().clone().float().contiguous()


def rms_norm_fusable(x: Tensor, weight: Tensor, eps: float) -> Tensor:
    """x / sqrt(mean(x^2) + eps) * weight over the last axis, as ONNX Runtime's
    SimplifiedLayerNormalization fusion expects it (its exported pattern: Pow, ReduceMean, Add,
    Sqrt, Div, Mul)."""
    return x / torch.sqrt(x.pow(2).mean(-1, keepdim=True) + eps) * weight


def gelu_tanh_fusable(x: Tensor) -> Tensor:
    """GELU's tanh form 0.5 x (1 + tanh(sqrt(2/pi) (x + 0.044715 x^3))) (``F.gelu(x,
    approximate="tanh")``), in the operator order ONNX Runtime's FastGelu fusion matches."""
    return (x * 0.5) * (torch.tanh((x + x.pow(3) * 0.044715) * _GELU_C) + 1.0)


class _StepForm(nn.Module):
    """What a form shares: batch 1 only, the trunk's ``head``, no parallel form."""

    head: nn.Module

    def step(self, z_t: Tensor, state: tuple[Tensor, ...]) -> tuple[Tensor, tuple[Tensor, ...]]:
        h, new = self.step_features(z_t, state)
        return self.head(h), new

    def features(self, z: Tensor) -> Tensor:
        raise NotImplementedError(
            "an ONNX step form has the batch-1 step only (the model's forward is the parallel form)"
        )

    @staticmethod
    def _one_stream(batch: int) -> None:
        if int(batch) != 1:
            raise ValueError(f"an ONNX step form steps one stream (batch 1), got {batch}")


class _SSMForm(_StepForm):
    """The SSM stack around a mixer (``ssm_stack.SSMEstimator``): input_proj, n_layer x [h +
    mixer(RMSNorm(h))], RMSNorm, head, with the per-layer constants in ``self.layers``."""

    def __init__(self, model: nn.Module) -> None:
        super().__init__()
        self.d, self.eps = int(model.cfg.d_model), float(model.cfg.norm_eps)
        self._dims(model.backbone.layers[0].mixer)
        self.input_proj = model.input_proj
        self.register_buffer("norm_f", _const(model.backbone.norm_f.weight))
        self.head = model.head
        self.layers = nn.ModuleList(self._layer(block) for block in model.backbone.layers)
        self.register_buffer("taps", torch.ones(1, self.K))  # sums the conv window's K weighted rows

    def _conv(self, p: nn.Module, conv: Tensor, x: Tensor) -> tuple[Tensor, Tensor]:
        """The causal depthwise conv's step: the window (K, C) shifted one row with x (1, C) as the
        newest, and silu(sum_k w_k * row_k + bias) (1, C); the sum and the bias as one Gemm
        ([1 ... 1] (w * window) + bias) instead of a ReduceSum and an Add."""
        conv = torch.cat((conv[1:], x), dim=0)
        return conv, F.silu(torch.addmm(p.conv_b, self.taps, conv * p.conv_w))

    def _dims(self, mixer: nn.Module) -> None:
        raise NotImplementedError

    def _layer(self, block: nn.Module) -> nn.Module:
        raise NotImplementedError

    def _mixer(self, p: nn.Module, h: Tensor, conv: Tensor, ssm: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        raise NotImplementedError

    def step_features(self, z_t: Tensor, state: tuple[Tensor, ...]) -> tuple[Tensor, tuple[Tensor, ...]]:
        h = self.input_proj(z_t)  # (1, d)
        new: list[Tensor] = []
        for i, p in enumerate(self.layers):
            h, conv, ssm = self._mixer(p, h, state[2 * i], state[2 * i + 1])
            new += [conv, ssm]
        return rms_norm_fusable(h, self.norm_f, self.eps), tuple(new)


def _params(**tensors: Tensor) -> nn.Module:
    """A module holding ``tensors`` as buffers (the graph's initializers, named after them)."""
    m = nn.Module()
    for name, t in tensors.items():
        m.register_buffer(name, _const(t))
    return m


class MambaStepForm(_SSMForm):
    """Mamba's step (``MambaMixer.step`` in each layer) in the graph's form; state per layer: the
    conv window (K, E) and the SSM state (N, E), zeros."""

    def _dims(self, mixer: nn.Module) -> None:
        self.E, self.N, self.R, self.K = mixer.d_inner, mixer.d_state, mixer.dt_rank, mixer.d_conv

    def _layer(self, block: nn.Module) -> nn.Module:
        m = block.mixer
        return _params(
            norm=block.norm.weight,
            in_proj=m.in_proj.weight,  # (2E, d): x, then the gate g
            conv_w=m.conv1d.weight[:, 0].t(),  # (K, E): tap k on row k, the newest input last
            conv_b=m.conv1d.bias.view(1, -1),
            x_proj=m.x_proj.weight,  # (R + 2N, E)
            dt_w=m.dt_proj.weight,
            dt_b=m.dt_proj.bias,
            A_t=-torch.exp(m.A_log.detach()).t(),  # (N, E)
            D=m.D.view(1, -1),
            out_proj=m.out_proj.weight,
        )

    def init_state(self, batch: int = 1, device=None, dtype=None) -> tuple[Tensor, ...]:
        self._one_stream(batch)
        dev, dt = device or self.norm_f.device, dtype or torch.float32
        state: list[Tensor] = []
        for _ in self.layers:
            state += [
                torch.zeros(self.K, self.E, device=dev, dtype=dt),
                torch.zeros(self.N, self.E, device=dev, dtype=dt),
            ]
        return tuple(state)

    def _mixer(self, p: nn.Module, h: Tensor, conv: Tensor, ssm: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        x, g = F.linear(rms_norm_fusable(h, p.norm, self.eps), p.in_proj).split(self.E, dim=-1)  # (1, E) each
        conv, u = self._conv(p, conv, x)  # (K, E), (1, E)
        dt, b, c = F.linear(u, p.x_proj).split([self.R, self.N, self.N], dim=-1)
        delta = F.softplus(F.linear(dt, p.dt_w, p.dt_b))  # (1, E)
        ssm = ssm * torch.exp(delta * p.A_t) + b.t() @ (delta * u)  # (N, E)
        y = c @ ssm + p.D * u  # (1, E)
        return h + F.linear(y * F.silu(g), p.out_proj), conv, ssm


class Mamba2StepForm(_SSMForm):
    """Mamba-2's step (``Mamba2Mixer.step`` in each layer) in the graph's form; state per layer: the
    conv window (K, E + 2N) and the SSM state transposed, (N, E) (mamba_ssm's (H, P, N) as its E = H P
    channels by N, then transposed; zeros). Each head's step size is spread over its P channels by
    one product with a 0/1 matrix (softplus, slow in ONNX Runtime, runs on the H heads only), so
    that the decay, the input's outer product and the read-out are row-vector broadcasts and two
    Gemms, with no reshape between them:

        delta = softplus(dt) R  (1, E),   R[h, e] = 1 where channel e is in head h
        S' = exp(delta * A) * S + b^T (delta * x)     (N, E)
        y  = c S' + D * x                              (1, E)"""

    def _dims(self, mixer: nn.Module) -> None:
        self.E, self.N, self.K = mixer.d_inner, mixer.d_state, mixer.d_conv
        self.H, self.P = mixer.nheads, mixer.headdim

    def _layer(self, block: nn.Module) -> nn.Module:
        m = block.mixer
        E, N, P = self.E, self.N, self.P
        w = m.in_proj.weight  # (2E + 2N + H, d): [g, x, b, c, dt]
        spread = torch.repeat_interleave(torch.eye(self.H, dtype=w.dtype), P, dim=1)  # (H, E)
        return _params(
            norm=block.norm.weight,
            in_proj=w,
            in_bias=torch.cat((w.new_zeros(2 * E + 2 * N), m.dt_bias.detach())),  # dt_bias on the dt rows
            conv_w=m.conv1d.weight[:, 0].t(),  # (K, E + 2N)
            conv_b=m.conv1d.bias.view(1, -1),
            spread=spread,
            A=(-torch.exp(m.A_log.detach())).repeat_interleave(P).view(1, -1),  # (1, E): each head's A
            D=m.D.detach().repeat_interleave(P).view(1, -1),  # (1, E): each head's D on its P channels
            gate_norm=m.norm.weight,
            out_proj=m.out_proj.weight,
        )

    def init_state(self, batch: int = 1, device=None, dtype=None) -> tuple[Tensor, ...]:
        self._one_stream(batch)
        dev, dt = device or self.norm_f.device, dtype or torch.float32
        C = self.E + 2 * self.N
        state: list[Tensor] = []
        for _ in self.layers:
            state += [
                torch.zeros(self.K, C, device=dev, dtype=dt),
                torch.zeros(self.N, self.E, device=dev, dtype=dt),
            ]
        return tuple(state)

    def _mixer(self, p: nn.Module, h: Tensor, conv: Tensor, ssm: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        E, N, H = self.E, self.N, self.H
        g, xbc, dt = F.linear(rms_norm_fusable(h, p.norm, self.eps), p.in_proj, p.in_bias).split(
            [E, E + 2 * N, H], dim=-1
        )  # (1, E), (1, E + 2N), (1, H): dt + dt_bias
        conv, xbc = self._conv(p, conv, xbc)  # (K, E + 2N), (1, E + 2N)
        x, b, c = xbc.split([E, N, N], dim=-1)
        delta = F.softplus(dt) @ p.spread  # (1, E): each head's step size on its channels
        ssm = torch.addmm(ssm * torch.exp(delta * p.A), b.t(), delta * x)  # (N, E)
        y = torch.addmm(p.D * x, c, ssm)  # (1, E)
        y = rms_norm_fusable(y * F.silu(g), p.gate_norm, self.eps)  # the gated RMSNorm, norm after gate
        return h + F.linear(y, p.out_proj), conv, ssm


class _ScatterND(torch.autograd.Function):
    """``data`` with ``updates`` written at ``indices`` (ONNX ScatterND: indices (..., k) int64 index
    data's first k axes; updates (..., *data.shape[k:])). Exported as the one ScatterND operator (a
    copy of ``data`` and the write of the updates), which torch's indexed writes export as several."""

    @staticmethod
    def forward(ctx, data: Tensor, indices: Tensor, updates: Tensor) -> Tensor:  # noqa: ARG004 - autograd's signature
        out = data.clone()
        out[tuple(indices.unbind(-1))] = updates
        return out

    @staticmethod
    def symbolic(g, data, indices, updates):
        return g.op("ScatterND", data, indices, updates)


class _RingForm(_StepForm):
    """An attention model's step over a ring buffer of the last W keys and values. State: the slots'
    ages (W,) (+inf: never written), then per attention layer its keys and its values, (nh, W, hs)
    each (zeros). The slot written is the oldest, the first of the largest age (ArgMax): slot
    t mod W at step t, as the model's shift register drops its oldest entry."""

    def __init__(self, model: nn.Module, window: int, n_head: int, d_model: int, n_layers: int) -> None:
        super().__init__()
        self.W, self.nh, self.D, self.n_layers = int(window), int(n_head), int(d_model), int(n_layers)
        self.hs = self.D // self.nh
        self.register_buffer("neg_slopes", -_const(model.slopes).view(-1, 1, 1))  # (nh, 1, 1): -m_h
        heads = torch.zeros(self.nh, 1, 2, dtype=torch.long)
        heads[:, 0, 0] = torch.arange(self.nh)
        self.register_buffer("heads", heads)  # (nh, 1, 2): [h, 0]
        self.register_buffer("slot_axis", torch.tensor([0, 1], dtype=torch.long))  # t goes to [.., t]

    def init_state(self, batch: int = 1, device=None, dtype=None) -> tuple[Tensor, ...]:
        self._one_stream(batch)
        dev, dt = device or self.heads.device, dtype or torch.float32
        cache = (self.nh, self.W, self.hs)
        state = [torch.full((self.W,), float("inf"), device=dev, dtype=dt)]
        for _ in range(self.n_layers):
            state += [torch.zeros(cache, device=dev, dtype=dt), torch.zeros(cache, device=dev, dtype=dt)]
        return tuple(state)

    def _advance(self, state: tuple[Tensor, ...]) -> tuple[Tensor, Tensor, list[Tensor]]:
        """This step's [head, slot] write indices (nh, 1, 2), the ALiBi bias of the slots once the
        slot is written (nh, 1, W), and the new ages."""
        age = state[0]
        slot = age.argmax(0, keepdim=True).view(1, 1)  # the oldest slot (the first never written at first)
        age = _ScatterND.apply(age + 1.0, slot, torch.zeros_like(age[:1]))  # steps since each slot was written
        bias = self.neg_slopes * age  # (nh, 1, W): -m_h * age, -inf on slots never written
        where = self.heads + slot * self.slot_axis  # (nh, 1, 2)
        return where, bias, [age]

    def _attend(self, qkv: Tensor, k_cache: Tensor, v_cache: Tensor, where: Tensor, bias: Tensor):
        """``layers.window_attention_step`` over the ring: qkv (1, 3D) -> the heads' outputs (1, D)
        and the new keys and values."""
        q, k, v = qkv.view(3 * self.nh, 1, self.hs).split(self.nh, dim=0)  # (nh, 1, hs) each
        k_cache = _ScatterND.apply(k_cache, where, k)  # (nh, W, hs)
        v_cache = _ScatterND.apply(v_cache, where, v)
        scores = (q @ k_cache.transpose(-1, -2)) * (1.0 / math.sqrt(self.hs)) + bias  # (nh, 1, W)
        y = torch.softmax(scores, dim=-1) @ v_cache  # (nh, 1, hs)
        return y.reshape(1, self.D), k_cache, v_cache


class GPT2StepForm(_RingForm):
    """GPT-2's step (``GPT2Model.step``) in the graph's form (the ring buffer of :class:`_RingForm`)."""

    def __init__(self, model: nn.Module) -> None:
        cfg = model.cfg
        super().__init__(model, cfg.decode_chunk, cfg.n_head, cfg.n_embd, cfg.n_layer)
        self.input_proj, self.head, self.ln_f = model.input_proj, model.head, model.ln_f
        self.blocks = model.blocks

    def step_features(self, z_t: Tensor, state: tuple[Tensor, ...]) -> tuple[Tensor, tuple[Tensor, ...]]:
        where, bias, new = self._advance(state)
        h = self.input_proj(z_t)  # (1, D)
        for i, block in enumerate(self.blocks):
            attn, mlp = block.attn, block.mlp
            y, k_cache, v_cache = self._attend(
                attn.c_attn(block.ln_1(h)), state[1 + 2 * i], state[2 + 2 * i], where, bias
            )
            h = h + attn.c_proj(y)
            h = h + mlp.c_proj(gelu_tanh_fusable(mlp.c_fc(block.ln_2(h))))
            new += [k_cache, v_cache]
        return self.ln_f(h), tuple(new)


class FilterformerStepForm(_RingForm):
    """Filterformer's step (``FilterformerModel.step`` / ``step_with_cov``) in the graph's form (the
    ring buffer of :class:`_RingForm`, its one attention layer); the geometric-attention head as the
    model's."""

    def __init__(self, model: nn.Module) -> None:
        cfg = model.cfg
        super().__init__(model, cfg.window, cfg.n_head, cfg.d_model, 1)
        self.input_proj, self.ln_1, self.attn = model.input_proj, model.ln_1, model.attn
        self.ln_2, self.mlp, self.ln_f, self.head = model.ln_2, model.mlp, model.ln_f, model.head

    def step_features(self, z_t: Tensor, state: tuple[Tensor, ...]) -> tuple[Tensor, tuple[Tensor, ...]]:
        where, bias, new = self._advance(state)
        e = self.input_proj(z_t)  # (1, D)
        y, k_cache, v_cache = self._attend(self.attn.qkv(self.ln_1(e)), state[1], state[2], where, bias)
        e = e + self.attn.proj(y)
        fc1, fc2 = self.mlp[0], self.mlp[2]
        e = e + fc2(F.gelu(fc1(self.ln_2(e))))
        return self.ln_f(e), (*new, k_cache, v_cache)

    def step(self, z_t: Tensor, state: tuple[Tensor, ...]) -> tuple[Tensor, tuple[Tensor, ...]]:
        h, new = self.step_features(z_t, state)
        return self.head.mean(h), new

    def step_with_cov(self, z_t: Tensor, state: tuple[Tensor, ...]) -> tuple[Tensor, Tensor, tuple[Tensor, ...]]:
        h, new = self.step_features(z_t, state)
        mean, cov = self.head.moments(h)
        return mean, cov, new

    def mean_of(self, h: Tensor) -> Tensor:
        return self.head.mean(h)
