"""Mamba-2 (state space duality) in pure PyTorch, state_dict-compatible with ``mamba_ssm``.

References:
    Dao, Gu (2024), "Transformers are SSMs: Generalized Models and Efficient Algorithms Through
        Structured State Space Duality", https://arxiv.org/abs/2405.21060 (section 6, the SSD
        algorithm: diagonal blocks as masked attention, low-rank off-diagonal blocks via chunk states).
    state-spaces/mamba ``mamba_ssm/modules/mamba2.py`` (parameter names, shapes, init, the in_proj
        layout [z, x, B, C, dt], ``step``), ``mamba_ssm/modules/ssd_minimal.py`` (the chunked
        algorithm), ``mamba_ssm/ops/triton/layernorm_gated.py`` (the gated RMSNorm, norm after gate),
        ``mamba_ssm/models/mixer_seq_simple.py`` (pre-norm residual blocks and the final norm).

Glossary: B batch, T time, d = d_model, E = expand * d (d_inner = d_ssm), P head dim,
H = E / P heads, N = d_state, K = d_conv, Q chunk length, c chunk index. One group (ngroups = 1):
all heads share b_t and c_t.

One mixer (``Mamba2Mixer``, the parameters and names of ``mamba_ssm.modules.mamba2.Mamba2``):

    g, xbc, dt = in_proj(h).split(E, E + 2N, H)          in_proj layout [z, x, B, C, dt]
    x, b, c    = silu(causal depthwise conv1d_K(xbc)).split(E, N, N)
    delta      = softplus(dt + dt_bias)                  (B, T, H)
    A          = -exp(A_log)                             (H,)  one scalar decay per head
    S_t        = exp(delta_t A) S_{t-1} + delta_t x_t b_t^T        (B, H, P, N)  S_{-1} = 0
    y_t        = S_t c_t + D x_t                         (B, H, P)
    out        = out_proj(rmsnorm(y * silu(g)) * norm.weight)   gated RMSNorm, norm after gate

The model: z (B, T, d_in) -> input_proj -> n_layer x [h = h + mixer(norm(h))] -> norm_f -> head,
with RMSNorm and no MLP, as ``mamba_ssm``'s MixerModel (``rms_norm=True``, ``ssm_cfg={"layer":
"Mamba2"}``); every ``backbone.layers.i.mixer`` loads into ``mamba_ssm.modules.mamba2.Mamba2`` and back.

Three forms of the recurrence, held equal by the tests:

- :func:`ssd_ref`: the obvious loop over t (slow; the reference).
- :func:`ssd_chunked`: the training path, the SSD algorithm. With the scalar decay per head the
  map x -> y is y = (L o C B^T) X, L_ts = exp(sum_{r=s+1..t} delta_r A) for s <= t, a masked
  attention. Cut into chunks of Q: inside a chunk it is computed as that quadratic form (matrix
  products); across chunks the state at each chunk's end is passed on through the chunks' total
  decays (the same masked form one level up, over the T/Q chunk boundaries). Every exponent is a
  sum of delta A <= 0 over a segment, so nothing overflows; the pairwise segment sums are masked
  cumulative sums, not differences of two long cumulative sums. On one CPU core at B=64, H=8,
  P=16, N=48, forward+backward takes 0.1 s at T=100 and 0.6 s at T=500, against 0.5 s and 2.9 s
  for a step-by-step loop.
- :func:`neural_estimator.models.cpu_scan.ssd_scan_fused`: the CPU training path, the recurrence
  as one fused numba loop per batch row (state (H, P, N) in L1 cache) with a hand-written
  backward; faster than :func:`ssd_chunked` on CPU (measured in benchmarks/bench_training.py).
  ``mixer.cpu_scan = "chunked"`` selects the torch SSD instead.
- ``Mamba2Model.step``: one time step with the conv state (B, E + 2N, K) and the SSM state
  (B, H, P, N); O(1) in the stream length.

When ``mamba_ssm`` imports and the tensors are on CUDA, the training path uses its fused
``mamba_chunk_scan_combined`` instead (optional; never required).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

from neural_estimator.models.ssm_stack import SSMEstimator, rms_norm

try:  # the fused CPU kernels need numba (a dependency; the torch SSD stands in if it is missing)
    from neural_estimator.models.cpu_scan import conv_silu_fused, ssd_scan_fused
except ImportError:
    conv_silu_fused = ssd_scan_fused = None

try:  # optional fused Triton/CUDA kernel; absent on CPU-only installs
    from mamba_ssm.ops.triton.ssd_combined import mamba_chunk_scan_combined as _cuda_chunk_scan
except (ImportError, OSError):
    _cuda_chunk_scan = None


@dataclass(frozen=True)
class Mamba2Config:
    d_in: int
    d_out: int
    d_model: int = 64
    d_state: int = 48
    d_conv: int = 4
    expand: int = 2
    headdim: int = 16
    n_layer: int = 3
    A_init_range: tuple[float, float] = (1.0, 16.0)  # A = -U(1, 16) per head, as mamba_ssm
    dt_min: float = 0.001  # softplus(dt_bias) starts log-uniform in [dt_min, dt_max]
    dt_max: float = 0.1
    dt_init_floor: float = 1e-4
    norm_eps: float = 1e-5
    chunk_size: int = 32  # longest SSD chunk of the training path (evened out over T); 32 is fastest on CPU
    use_cuda_kernels: bool = True  # use mamba_ssm's fused SSD when importable and on CUDA

    @property
    def d_inner(self) -> int:
        return self.expand * self.d_model

    @property
    def nheads(self) -> int:
        return self.d_inner // self.headdim


# ---- the SSD scan ------------------------------------------------------------------------------
def ssd_ref(x: Tensor, delta: Tensor, A: Tensor, B: Tensor, C: Tensor) -> tuple[Tensor, Tensor]:
    """Sequential scan (the reference): S_t = exp(delta_t A) S_{t-1} + delta_t x_t b_t^T, y_t = S_t c_t.

    Args:
        x: (B, T, H, P) inputs per head.
        delta: (B, T, H) positive step sizes.
        A: (H,) negative decay rates.
        B, C: (B, T, N) shared by all heads (one group).

    Returns:
        y (B, T, H, P) and the last state (B, H, P, N).
    """
    Bsz, T, H, P = x.shape
    S = x.new_zeros(Bsz, H, P, B.shape[-1])  # (B, H, P, N)
    ys = []
    for t in range(T):
        dA = torch.exp(delta[:, t] * A)  # (B, H)
        dBx = (delta[:, t, :, None] * x[:, t]).unsqueeze(-1) * B[:, t, None, None, :]  # (B, H, P, N)
        S = dA[:, :, None, None] * S + dBx
        ys.append(S @ C[:, t, None, :, None])  # (B, H, P, 1)
    return torch.stack(ys, dim=1).squeeze(-1), S


def segsum(a: Tensor) -> Tensor:
    """Segment sums of a (..., Q): out[..., t, s] = sum_{r=s+1..t} a_r for s <= t, -inf for s > t.

    Built as a masked cumulative sum down the rows (no difference of two large cumulative sums), so
    the result is accurate for long segments of large negative a.
    """
    Q = a.shape[-1]
    strict = torch.ones(Q, Q, dtype=torch.bool, device=a.device).tril(-1)  # r > s
    rows = a.unsqueeze(-1).expand(*a.shape, Q).masked_fill(~strict, 0.0)  # (..., Q_r, Q_s): a_r if r > s
    out = torch.cumsum(rows, dim=-2)  # (..., Q_t, Q_s): sum over s < r <= t
    causal = torch.ones(Q, Q, dtype=torch.bool, device=a.device).tril()  # s <= t
    return out.masked_fill(~causal, float("-inf"))


def ssd_chunked(
    x: Tensor, delta: Tensor, A: Tensor, B: Tensor, C: Tensor, chunk_size: int = 32
) -> tuple[Tensor, Tensor]:
    """Chunked SSD, equal to :func:`ssd_ref` (same arguments and returns).

    Chunks of Q <= chunk_size steps (the number of chunks is ceil(T / chunk_size) and Q evens them
    out, so a short sequence is one chunk). With a_t = delta_t A and X_t = delta_t x_t:

        y_diag[t]   = sum_{s <= t in chunk} exp(segsum(a)[t, s]) (c_t . b_s) X_s     intra-chunk
        state[c]    = sum_{s in chunk c} exp(sum_{r > s in c} a_r) X_s b_s^T          chunk's own input
        enter[c]    = sum_{c' < c} exp(sum of a over chunks c'+1 .. c-1) state[c']   state entering c
        y_off[t]    = exp(sum_{r <= t in chunk} a_r) enter[c] c_t                    inter-chunk
    """
    Bsz, T, H, P = x.shape
    N = B.shape[-1]
    nc = -(-T // chunk_size)
    Q = -(-T // nc)
    pad = nc * Q - T
    if pad:  # zero step size and input: padded steps leave the state alone
        x = F.pad(x, (0, 0, 0, 0, 0, pad))
        delta, B, C = (F.pad(v, (0, 0, 0, pad)) for v in (delta, B, C))
    X = (x * delta.unsqueeze(-1)).view(Bsz, nc, Q, H, P)  # (B, c, Q, H, P)
    a = (delta * A).view(Bsz, nc, Q, H).permute(0, 3, 1, 2)  # (B, H, c, Q)
    Bc = B.view(Bsz, nc, Q, N)  # (B, c, Q, N)
    Cc = C.view(Bsz, nc, Q, N)
    a_cum = torch.cumsum(a, dim=-1)  # (B, H, c, Q)

    # 1. intra-chunk: masked "attention" (L o C B^T) X
    L = torch.exp(segsum(a))  # (B, H, c, Q, Q)
    CB = Cc @ Bc.transpose(-1, -2)  # (B, c, Q, Q)  c_t . b_s
    y_diag = torch.einsum("bhcts,bcshp->bcthp", L * CB.unsqueeze(1), X)  # (B, c, Q, H, P)

    # 2. each chunk's own contribution to the state at its end
    decay_to_end = torch.exp(a_cum[..., -1:] - a_cum)  # (B, H, c, Q) exp(sum_{r > s} a_r) <= 1
    states = torch.einsum("bcsn,bhcs,bcshp->bchpn", Bc, decay_to_end, X)  # (B, c, H, P, N)

    # 3. states entering each chunk (and the final one): a recursion over chunk boundaries
    chunk_decay = torch.exp(segsum(F.pad(a_cum[..., -1], (1, 0))))  # (B, H, c+1, c+1)
    states = torch.cat((states.new_zeros(Bsz, 1, H, P, N), states), dim=1)  # (B, c+1, H, P, N)
    enter = torch.einsum("bhzc,bchpn->bzhpn", chunk_decay, states)  # (B, c+1, H, P, N)
    enter, last = enter[:, :-1], enter[:, -1]

    # 4. inter-chunk: the entering state read out through c_t, decayed to t
    y_off = torch.einsum("bctn,bchpn,bhct->bcthp", Cc, enter, torch.exp(a_cum))  # (B, c, Q, H, P)
    y = (y_diag + y_off).reshape(Bsz, nc * Q, H, P)[:, :T]
    return y, last


# ---- modules -----------------------------------------------------------------------------------
class RMSNormGated(nn.Module):
    """mamba_ssm's gated RMSNorm with norm_before_gate=False and one group: rmsnorm(y * silu(g)) * weight."""

    def __init__(self, d: int, eps: float = 1e-5) -> None:
        super().__init__()
        self.eps = eps
        self.weight = nn.Parameter(torch.ones(d))

    def forward(self, y: Tensor, g: Tensor) -> Tensor:
        return rms_norm(y * F.silu(g), self.weight, self.eps)


class Mamba2Mixer(nn.Module):
    """The block of ``mamba_ssm.modules.mamba2.Mamba2`` (ngroups=1, rmsnorm=True, no d_ssm MLP part).

    Parameters (d = d_model, E = d_inner, H = heads, N = d_state, K = d_conv):
        in_proj.weight (2E + 2N + H, d); conv1d.weight (E + 2N, 1, K), conv1d.bias (E + 2N,);
        dt_bias (H,); A_log (H,); D (H,); norm.weight (E,); out_proj.weight (d, E).
    """

    def __init__(self, cfg: Mamba2Config) -> None:
        super().__init__()
        d, E, H, N, K, P = cfg.d_model, cfg.d_inner, cfg.nheads, cfg.d_state, cfg.d_conv, cfg.headdim
        assert E % P == 0, "d_inner must be a multiple of headdim"
        self.d_inner, self.nheads, self.headdim, self.d_state, self.d_conv = E, H, P, N, K
        self.chunk_size = cfg.chunk_size
        self.use_cuda_kernels = cfg.use_cuda_kernels
        self.cpu_scan = "fused"  # CPU training scan: "fused" (numba) or "chunked" (torch SSD); not part of the model
        conv_dim = E + 2 * N
        self.in_proj = nn.Linear(d, 2 * E + 2 * N + H, bias=False)  # [z, x, B, C, dt]
        self.conv1d = nn.Conv1d(conv_dim, conv_dim, kernel_size=K, groups=conv_dim, padding=K - 1, bias=True)
        dt = torch.exp(torch.rand(H) * (math.log(cfg.dt_max) - math.log(cfg.dt_min)) + math.log(cfg.dt_min))
        dt = dt.clamp(min=cfg.dt_init_floor)
        self.dt_bias = nn.Parameter(dt + torch.log(-torch.expm1(-dt)))  # inverse softplus
        self.A_log = nn.Parameter(torch.log(torch.empty(H).uniform_(*cfg.A_init_range)))
        self.D = nn.Parameter(torch.ones(H))
        self.norm = RMSNormGated(E, eps=cfg.norm_eps)
        self.out_proj = nn.Linear(E, d, bias=False)

    def forward(self, h: Tensor, reference: bool = False) -> Tensor:
        """h (B, T, d) -> (B, T, d); ``reference=True`` uses :func:`ssd_ref`."""
        Bsz, T, _ = h.shape
        E, H, P, N = self.d_inner, self.nheads, self.headdim, self.d_state
        g, xbc, dt = self.in_proj(h).split([E, E + 2 * N, H], dim=-1)
        if (
            not reference
            and self.cpu_scan == "fused"
            and conv_silu_fused is not None
            and h.device.type == "cpu"
            and h.dtype in (torch.float32, torch.float64)
        ):
            xbc = conv_silu_fused(xbc, self.conv1d.weight, self.conv1d.bias)  # (B, T, E + 2N), one fused kernel
        else:
            xbc = F.silu(self.conv1d(xbc.transpose(1, 2))[..., :T].transpose(1, 2))  # (B, T, E + 2N)
        x, b, c = xbc.split([E, N, N], dim=-1)
        x = x.reshape(Bsz, T, H, P)  # (B, T, H, P)
        A = -torch.exp(self.A_log)  # (H,)
        if self.use_cuda_kernels and _cuda_chunk_scan is not None and h.is_cuda and not reference:
            y = _cuda_chunk_scan(
                x,
                dt,
                A.float(),
                b.unsqueeze(2),
                c.unsqueeze(2),
                chunk_size=256,
                D=self.D,
                dt_bias=self.dt_bias,
                dt_softplus=True,
            )  # (B, T, H, P), D included
        else:
            delta = F.softplus(dt + self.dt_bias)  # (B, T, H)
            if reference:
                y, _ = ssd_ref(x, delta, A, b, c)
            elif (
                self.cpu_scan == "fused"
                and ssd_scan_fused is not None
                and x.device.type == "cpu"
                and x.dtype in (torch.float32, torch.float64)
            ):
                y, _ = ssd_scan_fused(x, delta, A, b, c)
            else:
                y, _ = ssd_chunked(x, delta, A, b, c, self.chunk_size)
            y = y + x * self.D[:, None]  # (B, T, H, P)
        return self.out_proj(self.norm(y.reshape(Bsz, T, E), g))

    def init_state(self, batch: int, device=None, dtype=None) -> tuple[Tensor, Tensor]:
        """(conv_state (B, E + 2N, K), ssm_state (B, H, P, N)), zeros; mamba_ssm's cache layout."""
        conv = torch.zeros(batch, self.d_inner + 2 * self.d_state, self.d_conv, device=device, dtype=dtype)
        ssm = torch.zeros(batch, self.nheads, self.headdim, self.d_state, device=device, dtype=dtype)
        return conv, ssm

    def step(self, h: Tensor, conv_state: Tensor, ssm_state: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """h (B, d) -> (B, d) and the new (conv_state, ssm_state).

        Written for batch-1 latency: every tensor here is tiny, so the cost is the number of
        operations; functional calls avoid the module-call overhead.
        """
        Bsz = h.shape[0]
        E, H, P, N = self.d_inner, self.nheads, self.headdim, self.d_state
        g, xbc, dt = F.linear(h, self.in_proj.weight).split([E, E + 2 * N, H], dim=-1)
        conv_state = torch.cat((conv_state[..., 1:], xbc.unsqueeze(-1)), dim=-1)  # (B, E + 2N, K), newest last
        xbc = F.silu(torch.linalg.vecdot(conv_state, self.conv1d.weight[:, 0]) + self.conv1d.bias)
        x, b, c = xbc.split([E, N, N], dim=-1)
        x = x.view(Bsz, H, P)  # (B, H, P)
        delta = F.softplus(dt + self.dt_bias)  # (B, H)
        dA = torch.exp(delta * -torch.exp(self.A_log))  # (B, H)
        # S = dA S + (delta x) b^T as one batched outer-product update, S viewed as (B, E, N)
        ssm_state = torch.baddbmm(
            (ssm_state * dA[:, :, None, None]).view(Bsz, E, N),
            (x * delta.unsqueeze(-1)).view(Bsz, E, 1),
            b.view(Bsz, 1, N),
        )
        y = torch.baddbmm((x * self.D[:, None]).view(Bsz, E, 1), ssm_state, c.view(Bsz, N, 1))  # S c + D x
        ssm_state = ssm_state.view(Bsz, H, P, N)
        y = y.view(Bsz, E)
        y = rms_norm(y * F.silu(g), self.norm.weight, self.norm.eps)
        return F.linear(y, self.out_proj.weight), conv_state, ssm_state


class Mamba2Model(SSMEstimator):
    """Mamba-2 estimator: ``forward(z) (B, T, d_in) -> (B, T, d_out)``, ``step(z_t, state)``.

    The step state is ``(conv_0, ssm_0, conv_1, ssm_1, ...)``: per layer the (B, E + 2N, K) window
    of conv inputs and the (B, H, P, N) SSM state.
    The stack around the mixer is :class:`~neural_estimator.models.ssm_stack.SSMEstimator`.
    """

    def __init__(self, cfg: Mamba2Config) -> None:
        super().__init__(cfg, Mamba2Mixer)

    def onnx_form(self) -> nn.Module:
        """This model's batch-1 step in the form its ONNX graph is traced from (same arithmetic, its
        own state layout: :class:`~neural_estimator.models.onnx_forms.Mamba2StepForm`)."""
        from neural_estimator.models.onnx_forms import Mamba2StepForm

        return Mamba2StepForm(self)
