"""Mamba (selective state-space model) in pure PyTorch, state_dict-compatible with ``mamba_ssm``.

References:
    Gu, Dao (2024), "Mamba: Linear-Time Sequence Modeling with Selective State Spaces",
        https://arxiv.org/abs/2312.00752 (Algorithm 2, the selective SSM; section 3.6 initialisation).
    state-spaces/mamba ``mamba_ssm/modules/mamba_simple.py`` (the block's parameters, their shapes
        and initialisation, ``step``), ``mamba_ssm/ops/selective_scan_interface.py``
        (``selective_scan_ref``, the sequential scan), ``mamba_ssm/models/mixer_seq_simple.py``
        (pre-norm residual blocks and the final norm).

Glossary: B batch, T time, d = d_model, E = expand * d_model (d_inner), N = d_state, R = dt_rank,
K = d_conv, Q scan chunk length.

One mixer (``MambaMixer``, the parameters and names of ``mamba_ssm.modules.mamba_simple.Mamba``):

    x, g   = in_proj(h).chunk(2)                    (B, T, E) each
    u      = silu(causal depthwise conv1d_K(x))     (B, T, E)
    dt, b, c = x_proj(u).split(R, N, N)
    delta  = softplus(dt_proj(dt))                  (B, T, E)    dt_proj carries the bias
    A      = -exp(A_log)                            (E, N)
    s_t    = exp(delta_t A) * s_{t-1} + (delta_t u_t) b_t^T      (B, E, N)   s_{-1} = 0
    y_t    = s_t c_t + D * u_t                      (B, E)
    out    = out_proj(y * silu(g))                  (B, T, d)

The model: z (B, T, d_in) -> input_proj -> n_layer x [h = h + mixer(norm(h))] -> norm_f -> head,
with RMSNorm, as ``mamba_ssm``'s MixerModel with ``rms_norm=True`` and no MLP. The state_dict keys
below ``backbone`` are those of MixerModel's ``layers`` and ``norm_f`` (its token ``embedding``
is replaced by ``input_proj`` and its LM head by ``head``), and each ``backbone.layers.i.mixer``
loads into ``mamba_ssm.modules.mamba_simple.Mamba`` and back unchanged.

Forms of the recurrence, held equal by the tests:

- :func:`selective_scan_ref`: the obvious loop over t (slow; the reference).
- :func:`selective_scan`, the training path, picks one of three exact rearrangements: on CPU the
  fused numba kernel :func:`neural_estimator.models.cpu_scan.mamba_scan_fused` (one pass per batch
  row with the state in L1 cache, a hand-written backward that recomputes the states and runs the
  adjoint recurrence backwards; fastest on CPU, measured in benchmarks/bench_training.py) or, as
  before it, :func:`selective_scan_stepwise` (the loop with an O(T) autograd graph), and
  :func:`selective_scan_chunked` elsewhere (time cut
  into chunks of Q ~ sqrt(T); the scan runs inside all chunks at once, then a loop over the chunks
  carries each end state into the next through the decay exp(A cumsum(delta)): about 2 sqrt(T)
  sequential steps instead of T, every exponent <= 0).
- ``MambaModel.step``: one time step with the conv state (B, E, K) and the SSM state (B, E, N);
  O(1) in the stream length.

When ``mamba_ssm`` imports and the tensors are on CUDA, the training path uses its fused
``selective_scan_fn`` instead (optional; never required).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

from neural_estimator.models.ssm_stack import SSMEstimator

try:  # the fused CPU kernels need numba (a dependency; the torch scan stands in if it is missing)
    from neural_estimator.models.cpu_scan import conv_silu_fused, mamba_scan_fused
except ImportError:
    conv_silu_fused = mamba_scan_fused = None

try:  # optional fused CUDA kernel; absent on CPU-only installs
    from mamba_ssm.ops.selective_scan_interface import selective_scan_fn as _cuda_selective_scan
except (ImportError, OSError):
    _cuda_selective_scan = None


@dataclass(frozen=True)
class MambaConfig:
    d_in: int
    d_out: int
    d_model: int = 80
    d_state: int = 16
    d_conv: int = 4
    expand: int = 2
    n_layer: int = 2
    dt_min: float = 0.001  # softplus(dt_proj.bias) starts log-uniform in [dt_min, dt_max]
    dt_max: float = 0.1
    dt_init_floor: float = 1e-4
    norm_eps: float = 1e-5
    scan_chunk: int = 0  # chunk length Q of the chunked scan (off-CPU); 0 = about sqrt(T)
    use_cuda_kernels: bool = True  # use mamba_ssm's fused scan when importable and on CUDA

    @property
    def d_inner(self) -> int:
        return self.expand * self.d_model

    @property
    def dt_rank(self) -> int:
        return math.ceil(self.d_model / 16)


# ---- the selective scan ------------------------------------------------------------------------
def selective_scan_ref(u: Tensor, delta: Tensor, A: Tensor, B: Tensor, C: Tensor) -> tuple[Tensor, Tensor]:
    """Sequential selective scan (the reference): s_t = exp(delta_t A) s_{t-1} + delta_t u_t b_t^T, y_t = s_t c_t.

    Args:
        u, delta: (B, T, E) input and positive step sizes.
        A: (E, N) negative diagonal state matrix.
        B, C: (B, T, N) input and output projections of the state.

    Returns:
        y (B, T, E) and the last state (B, E, N).
    """
    dA = torch.exp(delta.unsqueeze(-1) * A)  # (B, T, E, N)
    dBu = (delta * u).unsqueeze(-1) * B.unsqueeze(2)  # (B, T, E, N)
    s = u.new_zeros(u.shape[0], u.shape[2], A.shape[1])  # (B, E, N)
    ys = []
    for t in range(u.shape[1]):
        s = dA[:, t] * s + dBu[:, t]
        ys.append(torch.einsum("ben,bn->be", s, C[:, t]))
    return torch.stack(ys, dim=1), s


def selective_scan_stepwise(u: Tensor, delta: Tensor, A: Tensor, B: Tensor, C: Tensor) -> tuple[Tensor, Tensor]:
    """The recurrence of :func:`selective_scan_ref`, arranged for CPU training (same arguments and returns).

    Each step discretises its own (B, E, N) slice inside the loop instead of materialising the
    (B, T, E, N) tensors, so the working set stays in cache, and the inputs are split with
    ``unbind`` so that backward gathers the per-step gradients once (indexing ``x[:, t]`` makes
    backward write a full-size zero tensor per step: O(T^2)). Measured on one CPU core at B=64,
    E=160, N=16, forward+backward: 0.17 s at T=100 and 0.9 s at T=500, against 9.5 s at T=100
    for the reference and 1.0 s and 8.4 s for :func:`selective_scan_chunked`.
    """
    s = None
    ys = []
    for d_t, u_t, b_t, c_t in zip(delta.unbind(1), u.unbind(1), B.unbind(1), C.unbind(1)):
        dBu = (d_t * u_t).unsqueeze(-1) * b_t.unsqueeze(1)  # (B, E, N)
        s = dBu if s is None else torch.addcmul(dBu, torch.exp(d_t.unsqueeze(-1) * A), s)
        ys.append(torch.bmm(s, c_t.unsqueeze(-1)).squeeze(-1))  # (B, E)
    return torch.stack(ys, dim=1), s


def selective_scan_chunked(
    u: Tensor, delta: Tensor, A: Tensor, B: Tensor, C: Tensor, chunk: int = 0
) -> tuple[Tensor, Tensor]:
    """Chunked parallel selective scan, equal to :func:`selective_scan_ref` (same arguments and returns).

    With t = iQ + j (chunk i, offset j) and L_{i,j} = sum_{j' <= j} delta_{i,j'} (within chunk i):

        s_{i,j} = l_{i,j} + exp(A L_{i,j}) * carry_i
        l_{i,j} = exp(delta_{i,j} A) l_{i,j-1} + delta_{i,j} u_{i,j} b_{i,j}^T,  l_{i,-1} = 0
        carry_{i+1} = s_{i,Q-1} = l_{i,Q-1} + exp(A L_{i,Q-1}) * carry_i,        carry_0 = 0

    The l recursion runs for all chunks in parallel (Q steps), the carry recursion over chunks
    (T/Q steps): about 2 sqrt(T) sequential steps for the default Q = ceil(sqrt(T)) (evened out
    over T), every exponent <= 0. Few, large operations: the form for accelerators; on a CPU it is
    memory-bound and :func:`selective_scan_stepwise` is faster.
    """
    Bsz, T, E = u.shape
    N = A.shape[1]
    nc = -(-T // (chunk if chunk > 0 else math.isqrt(max(T - 1, 0)) + 1))
    Q = -(-T // nc)
    pad = nc * Q - T
    if pad:  # zero step size and input: the padded steps leave the state alone
        u, delta, B, C = (F.pad(x, (0, 0, 0, pad)) for x in (u, delta, B, C))
    dq = delta.view(Bsz, nc, Q, E)  # (B, nc, Q, E)
    dA = torch.exp(dq.unsqueeze(-1) * A)  # (B, nc, Q, E, N)
    dBu = (dq * u.view(Bsz, nc, Q, E)).unsqueeze(-1) * B.view(Bsz, nc, Q, 1, N)  # (B, nc, Q, E, N)

    s = None
    local = []
    for a_j, b_j in zip(dA.unbind(2), dBu.unbind(2)):  # scan inside every chunk at once
        s = b_j if s is None else torch.addcmul(b_j, a_j, s)  # (B, nc, E, N)
        local.append(s)
    local = torch.stack(local, dim=2)  # (B, nc, Q, E, N)

    decay = torch.exp(torch.cumsum(dq, dim=2).unsqueeze(-1) * A)  # (B, nc, Q, E, N) exp(A L_{i,j})
    carries = [local.new_zeros(Bsz, E, N)]
    for end, dec in zip(local[:, :, -1].unbind(1), decay[:, :, -1].unbind(1)):  # over chunks
        carries.append(torch.addcmul(end, dec, carries[-1]))  # (B, E, N)
    last = carries.pop()  # padded steps (delta = 0) leave the state unchanged
    carry = torch.stack(carries, dim=1)  # (B, nc, E, N) state entering each chunk

    states = torch.addcmul(local, decay, carry.unsqueeze(2))  # (B, nc, Q, E, N)
    y = (states * C.view(Bsz, nc, Q, 1, N)).sum(-1)  # (B, nc, Q, E)
    return y.reshape(Bsz, nc * Q, E)[:, :T], last


CPU_SCANS = ("fused", "stepwise")  # the CPU forms of the training scan, fastest first (measured)


def selective_scan(
    u: Tensor, delta: Tensor, A: Tensor, B: Tensor, C: Tensor, chunk: int = 0, cpu_scan: str = "fused"
) -> tuple[Tensor, Tensor]:
    """The training scan: on CPU the fused numba kernel (:mod:`~neural_estimator.models.cpu_scan`,
    hand-written backward) or ``cpu_scan="stepwise"`` (:func:`selective_scan_stepwise`, torch
    autograd, the previous path); :func:`selective_scan_chunked` elsewhere."""
    if u.device.type == "cpu":
        if cpu_scan == "fused" and u.dtype in (torch.float32, torch.float64) and mamba_scan_fused is not None:
            return mamba_scan_fused(u, delta, A, B, C)
        return selective_scan_stepwise(u, delta, A, B, C)
    return selective_scan_chunked(u, delta, A, B, C, chunk)


# ---- modules -----------------------------------------------------------------------------------
class MambaMixer(nn.Module):
    """The Mamba block of ``mamba_ssm.modules.mamba_simple.Mamba``: same parameter names, shapes, init.

    Parameters (d = d_model, E = d_inner, R = dt_rank, N = d_state, K = d_conv):
        in_proj.weight (2E, d); conv1d.weight (E, 1, K), conv1d.bias (E,); x_proj.weight (R + 2N, E);
        dt_proj.weight (E, R), dt_proj.bias (E,); A_log (E, N); D (E,); out_proj.weight (d, E).
    """

    def __init__(self, cfg: MambaConfig) -> None:
        super().__init__()
        d, E, N, R, K = cfg.d_model, cfg.d_inner, cfg.d_state, cfg.dt_rank, cfg.d_conv
        self.d_inner, self.d_state, self.dt_rank, self.d_conv = E, N, R, K
        self.scan_chunk = cfg.scan_chunk
        self.use_cuda_kernels = cfg.use_cuda_kernels
        self.cpu_scan = "fused"  # CPU training scan (CPU_SCANS); a runtime choice, not part of the model
        self.in_proj = nn.Linear(d, 2 * E, bias=False)
        self.conv1d = nn.Conv1d(E, E, kernel_size=K, groups=E, padding=K - 1, bias=True)
        self.x_proj = nn.Linear(E, R + 2 * N, bias=False)
        self.dt_proj = nn.Linear(R, E, bias=True)
        # dt init as mamba_ssm: weight U(-R^-1/2, R^-1/2); softplus(bias) log-uniform in [dt_min, dt_max]
        nn.init.uniform_(self.dt_proj.weight, -(R**-0.5), R**-0.5)
        dt = torch.exp(torch.rand(E) * (math.log(cfg.dt_max) - math.log(cfg.dt_min)) + math.log(cfg.dt_min))
        dt = dt.clamp(min=cfg.dt_init_floor)
        with torch.no_grad():
            self.dt_proj.bias.copy_(dt + torch.log(-torch.expm1(-dt)))  # inverse softplus
        # S4D-real init: A = -(1, 2, ..., N) for every channel
        self.A_log = nn.Parameter(torch.log(torch.arange(1, N + 1, dtype=torch.float32)).repeat(E, 1))  # (E, N)
        self.D = nn.Parameter(torch.ones(E))
        self.out_proj = nn.Linear(E, d, bias=False)

    def _ssm_inputs(self, u: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        dt, b, c = self.x_proj(u).split([self.dt_rank, self.d_state, self.d_state], dim=-1)
        return dt, b, c  # (..., R), (..., N), (..., N)

    def forward(self, h: Tensor, reference: bool = False) -> Tensor:
        """h (B, T, d) -> (B, T, d); ``reference=True`` uses :func:`selective_scan_ref`."""
        T = h.shape[1]
        x, g = self.in_proj(h).chunk(2, dim=-1)  # (B, T, E) each
        if (
            not reference
            and self.cpu_scan == "fused"
            and conv_silu_fused is not None
            and x.device.type == "cpu"
            and x.dtype in (torch.float32, torch.float64)
        ):
            u = conv_silu_fused(x, self.conv1d.weight, self.conv1d.bias)  # (B, T, E), one fused kernel
        else:
            u = F.silu(self.conv1d(x.transpose(1, 2))[..., :T]).transpose(1, 2)  # (B, T, E)
        dt, b, c = self._ssm_inputs(u)
        A = -torch.exp(self.A_log)  # (E, N)
        if self.use_cuda_kernels and _cuda_selective_scan is not None and u.is_cuda and not reference:
            y = _cuda_selective_scan(
                u.transpose(1, 2).contiguous(),
                (dt @ self.dt_proj.weight.t()).transpose(1, 2).contiguous(),
                A.float(),
                b.transpose(1, 2).contiguous(),
                c.transpose(1, 2).contiguous(),
                self.D.float(),
                z=g.transpose(1, 2).contiguous(),
                delta_bias=self.dt_proj.bias.float(),
                delta_softplus=True,
            ).transpose(1, 2)  # (B, T, E)
            return self.out_proj(y)
        delta = F.softplus(self.dt_proj(dt))  # (B, T, E)
        if reference:
            y, _ = selective_scan_ref(u, delta, A, b, c)
        else:
            y, _ = selective_scan(u, delta, A, b, c, self.scan_chunk, self.cpu_scan)
        y = torch.addcmul(y, u, self.D)  # (B, T, E)
        return self.out_proj(y * F.silu(g))

    def init_state(self, batch: int, device=None, dtype=None) -> tuple[Tensor, Tensor]:
        """(conv_state (B, E, K), ssm_state (B, E, N)), zeros; mamba_ssm's cache layout."""
        conv = torch.zeros(batch, self.d_inner, self.d_conv, device=device, dtype=dtype)
        return conv, torch.zeros(batch, self.d_inner, self.d_state, device=device, dtype=dtype)

    def step(self, h: Tensor, conv_state: Tensor, ssm_state: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """h (B, d) -> (B, d) and the new (conv_state, ssm_state).

        Written for batch-1 latency: every tensor here is tiny, so the cost is the number of
        operations; functional calls avoid the module-call overhead.
        """
        x, g = F.linear(h, self.in_proj.weight).chunk(2, dim=-1)  # (B, E) each
        conv_state = torch.cat((conv_state[..., 1:], x.unsqueeze(-1)), dim=-1)  # (B, E, K), newest last
        u = F.silu(torch.linalg.vecdot(conv_state, self.conv1d.weight[:, 0]) + self.conv1d.bias)  # (B, E)
        dt, b, c = F.linear(u, self.x_proj.weight).split([self.dt_rank, self.d_state, self.d_state], dim=-1)
        delta = F.softplus(F.linear(dt, self.dt_proj.weight, self.dt_proj.bias))  # (B, E)
        dA = torch.exp(delta.unsqueeze(-1) * -torch.exp(self.A_log))  # (B, E, N)
        ssm_state = torch.addcmul(ssm_state * dA, (delta * u).unsqueeze(-1), b.unsqueeze(1))  # (B, E, N)
        y = torch.addcmul(torch.bmm(ssm_state, c.unsqueeze(-1)).squeeze(-1), u, self.D)  # (B, E)
        return F.linear(y * F.silu(g), self.out_proj.weight), conv_state, ssm_state


class MambaModel(SSMEstimator):
    """Mamba estimator: ``forward(z) (B, T, d_in) -> (B, T, d_out)``, ``step(z_t, state)``.

    The step state is ``(conv_0, ssm_0, conv_1, ssm_1, ...)``: per layer the (B, E, K) window of
    conv inputs and the (B, E, N) SSM state.
    The stack around the mixer is :class:`~neural_estimator.models.ssm_stack.SSMEstimator`.
    """

    def __init__(self, cfg: MambaConfig) -> None:
        super().__init__(cfg, MambaMixer)

    def onnx_form(self) -> nn.Module:
        """This model's batch-1 step in the form its ONNX graph is traced from (same arithmetic, its
        own state layout: :class:`~neural_estimator.models.onnx_forms.MambaStepForm`)."""
        from neural_estimator.models.onnx_forms import MambaStepForm

        return MambaStepForm(self)
