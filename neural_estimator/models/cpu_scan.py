"""Fused CPU kernels (numba) for the two selective scans, with hand-written backward passes.

Why: on a CPU the step-by-step torch scan of Mamba and Mamba-2 is memory-bound. Each time step
touches the whole (B, E, N) state (640 KB at Lorenz 96 sizes), every operation is a separate pass
over it, and autograd keeps a graph node per operation and step. Here one compiled loop per batch
row keeps that row's state in L1 cache ((E, N) = 10 KB for Mamba, (H, P, N) = 24 KB for Mamba-2),
does all of a step's arithmetic in one pass, and keeps no graph: the backward pass recomputes the
row's states and runs the adjoint recurrence backwards in time.

Mamba (per batch row; a_t = exp(delta_t A), all products elementwise over (E, N)):

    s_t = a_t s_{t-1} + (delta_t u_t) b_t^T,   y_t = s_t c_t                           forward
    lam_t = gy_t c_t^T + a_{t+1} lam_{t+1}     (lam_T = 0; lam_t = dL/ds_t)             adjoint
    gc_t  = s_t^T gy_t                          gb_t = lam_t^T (delta_t u_t)
    gu_t  = delta_t (lam_t b_t)                 gdelta_t = u_t (lam_t b_t) + sum_n lam_t s_{t-1} a_t A
    gA    = sum_t lam_t s_{t-1} a_t delta_t

Mamba-2 (per batch row; one scalar decay per head, a_t = exp(delta_t A) (H,), state (H, P, N)):

    S_t = a_t S_{t-1} + (delta_t x_t) b_t^T,   y_t = S_t c_t
    lam_t = gy_t c_t^T + a_{t+1} lam_{t+1}
    gc_t = sum_{h,p} gy_t S_t                  gb_t = sum_{h,p} lam_t (delta_t x_t)
    gx_t = delta_t (lam_t b_t)                  gdelta_t = x_t . (lam_t b_t) + a_t A sum_{p,n} lam_t S_{t-1}
    gA   = sum_t a_t delta_t sum_{p,n} lam_t S_{t-1}

Rows are independent, so with several threads the batch is split in row ranges run side by side
(the kernels release the GIL); the per-row partial gradients of A are summed afterwards (no races). The
autograd functions
:class:`MambaScanFn` and :class:`SSDScanFn` wrap them; the tests hold their outputs and gradients
equal to the sequential references in float64.
"""

from __future__ import annotations

import math

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch
from numba import njit
from torch import Tensor

_JIT = dict(nogil=True, cache=True, fastmath=True)


# ---- Mamba ---------------------------------------------------------------------------------------
@njit(**_JIT)
def _mamba_fwd(u, delta, dA, Bm, Cm, y, last):  # pragma: no cover - compiled
    """u, delta (B, T, E); dA = exp(delta A) (B, T, E, N); Bm, Cm (B, T, N) -> y (B, T, E), last (B, E, N)."""
    Bsz, T, E = u.shape
    N = dA.shape[3]
    zero = u.dtype.type(0)  # accumulators in the arrays' precision (a 0.0 literal would be float64)
    for b in range(Bsz):
        s = np.zeros((E, N), dtype=u.dtype)
        for t in range(T):
            for e in range(E):
                d = delta[b, t, e]
                du = d * u[b, t, e]
                acc = zero
                for n in range(N):
                    v = dA[b, t, e, n] * s[e, n] + du * Bm[b, t, n]
                    s[e, n] = v
                    acc += v * Cm[b, t, n]
                y[b, t, e] = acc
        last[b] = s


@njit(**_JIT)
def _mamba_fwd_exp(u, delta, A, Bm, Cm, y, last):  # pragma: no cover - compiled
    """:func:`_mamba_fwd` computing exp(delta A) on the fly: for inference, where a (B, T, E, N)
    tensor of decays would be large (100 x 500 validation trajectories: 0.5 GB) and is not needed."""
    Bsz, T, E = u.shape
    N = A.shape[1]
    zero = u.dtype.type(0)
    for b in range(Bsz):
        s = np.zeros((E, N), dtype=u.dtype)
        for t in range(T):
            for e in range(E):
                d = delta[b, t, e]
                du = d * u[b, t, e]
                acc = zero
                for n in range(N):
                    v = math.exp(d * A[e, n]) * s[e, n] + du * Bm[b, t, n]
                    s[e, n] = v
                    acc += v * Cm[b, t, n]
                y[b, t, e] = acc
        last[b] = s


@njit(**_JIT)
def _mamba_bwd(u, delta, dA, A, Bm, Cm, gy, gu, gdelta, gA_rows, gB, gC):  # pragma: no cover - compiled
    """Gradients of the Mamba scan given gy (B, T, E); all outputs written in place.

    gA_rows (B, E, N) holds each row's share of gA (summed by the caller). States are recomputed
    per row into a (T + 1, E, N) buffer, then the adjoint runs from t = T-1 down to 0. The inner
    loop over n is split in two passes (lam and what reads it; then the decay terms) over row views,
    which the compiler vectorises better (measured 30 % faster than one pass).
    """
    Bsz, T, E = u.shape
    N = A.shape[1]
    zero = u.dtype.type(0)  # accumulators in the arrays' precision (a 0.0 literal would be float64)
    states = np.empty((T + 1, E, N), dtype=u.dtype)  # one row's states[t + 1] = s_t, states[0] = s_{-1} = 0
    states[0] = 0.0
    carry = np.empty((E, N), dtype=u.dtype)  # a_{t+1} lam_{t+1}
    lam = np.empty(N, dtype=u.dtype)
    gb_t = np.empty(N, dtype=u.dtype)  # this step's gB and gC, summed over e
    gc_t = np.empty(N, dtype=u.dtype)
    for b in range(Bsz):
        for t in range(T):
            for e in range(E):
                du = delta[b, t, e] * u[b, t, e]
                for n in range(N):
                    states[t + 1, e, n] = dA[b, t, e, n] * states[t, e, n] + du * Bm[b, t, n]
        carry[:] = 0.0
        gAr = gA_rows[b]
        for t in range(T - 1, -1, -1):
            gb_t[:] = zero
            gc_t[:] = zero
            b_t, c_t = Bm[b, t], Cm[b, t]
            for e in range(E):
                d = delta[b, t, e]
                ut = u[b, t, e]
                du = d * ut
                g = gy[b, t, e]
                s_t, s_prev, car, a_t, A_e, gA_e = states[t + 1, e], states[t, e], carry[e], dA[b, t, e], A[e], gAr[e]
                lb = zero  # sum_n lam b
                for n in range(N):
                    lv = g * c_t[n] + car[n]  # lam_t
                    lam[n] = lv
                    gc_t[n] += g * s_t[n]
                    gb_t[n] += lv * du
                    lb += lv * b_t[n]
                ga_sum = zero  # sum_n lam s_{t-1} a A
                for n in range(N):
                    gas = lam[n] * s_prev[n] * a_t[n]  # dL/da_t * a_t
                    ga_sum += gas * A_e[n]
                    gA_e[n] += gas * d
                    car[n] = a_t[n] * lam[n]
                gu[b, t, e] = d * lb
                gdelta[b, t, e] = ut * lb + ga_sum
            gB[b, t] = gb_t
            gC[b, t] = gc_t


def _threads() -> int:
    """Threads for the kernels: torch's intra-op setting, so one option (``--threads``) governs both."""
    return max(1, torch.get_num_threads())


_POOL: ThreadPoolExecutor | None = None


def _by_rows(kernel, row_args: list[np.ndarray], shared: list[np.ndarray], tail: list[np.ndarray]) -> None:
    """kernel(*rows(row_args), *shared, *rows(tail)) over the batch, split in contiguous row ranges.

    The kernels release the GIL (``nogil``), so a plain thread pool runs the ranges in parallel;
    numba's own threading layer is not used because its worker threads slow torch's down afterwards
    (measured: a 0.8 s torch scan took 5 s after a ``parallel=True`` kernel had run).
    """
    global _POOL
    n = row_args[0].shape[0]
    k = min(_threads(), n)
    if k == 1:
        kernel(*row_args, *shared, *tail)
        return
    if _POOL is None or _POOL._max_workers < k:
        _POOL = ThreadPoolExecutor(max_workers=k, thread_name_prefix="scan")
    bounds = np.linspace(0, n, k + 1).astype(int)
    futures = [
        _POOL.submit(kernel, *(a[i:j] for a in row_args), *shared, *(a[i:j] for a in tail))
        for i, j in zip(bounds[:-1], bounds[1:])
    ]
    for f in futures:
        f.result()


class MambaScanFn(torch.autograd.Function):
    """y, last = selective scan of Mamba (see :func:`neural_estimator.models.mamba.selective_scan_ref`).

    The decays dA = exp(delta A) (B, T, E, N) are computed once by torch (vectorised exp) and kept
    for backward; everything else runs in the fused kernels. No per-step graph is kept; the states
    are recomputed in backward, one row at a time.
    """

    @staticmethod
    def forward(ctx, u: Tensor, delta: Tensor, A: Tensor, B: Tensor, C: Tensor):
        u, delta, A, B, C = (x.detach().contiguous() for x in (u, delta, A, B, C))
        Bsz, T, E = u.shape
        dA = torch.mul(delta.unsqueeze(-1), A).exp_()  # (B, T, E, N), one allocation
        y = u.new_empty(Bsz, T, E)
        last = u.new_empty(Bsz, E, A.shape[1])
        _by_rows(
            _mamba_fwd, [u.numpy(), delta.numpy(), dA.numpy(), B.numpy(), C.numpy()], [], [y.numpy(), last.numpy()]
        )
        ctx.save_for_backward(u, delta, dA, A, B, C)
        ctx.mark_non_differentiable(last)
        return y, last

    @staticmethod
    def backward(ctx, gy: Tensor, _glast):
        u, delta, dA, A, B, C = ctx.saved_tensors
        gy = gy.contiguous()
        gu, gdelta = torch.empty_like(u), torch.empty_like(delta)
        gB, gC = torch.zeros_like(B), torch.zeros_like(C)
        gA_rows = u.new_zeros(u.shape[0], *A.shape)
        _by_rows(
            lambda u_, d_, dA_, B_, C_, gy_, A_, *out: _mamba_bwd(u_, d_, dA_, A_, B_, C_, gy_, *out),
            [u.numpy(), delta.numpy(), dA.numpy(), B.numpy(), C.numpy(), gy.numpy()],
            [A.numpy()],
            [gu.numpy(), gdelta.numpy(), gA_rows.numpy(), gB.numpy(), gC.numpy()],
        )
        return gu, gdelta, gA_rows.sum(0), gB, gC


def mamba_scan_fused(u: Tensor, delta: Tensor, A: Tensor, B: Tensor, C: Tensor) -> tuple[Tensor, Tensor]:
    """The fused CPU selective scan; same arguments and returns as ``selective_scan_ref``.

    Without gradients (validation, inference) one kernel computes the decays on the fly.
    """
    if torch.is_grad_enabled() and any(x.requires_grad for x in (u, delta, A, B, C)):
        return MambaScanFn.apply(u, delta, A, B, C)
    u, delta, A, B, C = (x.detach().contiguous() for x in (u, delta, A, B, C))
    y = u.new_empty(u.shape)
    last = u.new_empty(u.shape[0], u.shape[2], A.shape[1])
    _by_rows(
        lambda u_, d_, B_, C_, A_, y_, l_: _mamba_fwd_exp(u_, d_, A_, B_, C_, y_, l_),
        [u.numpy(), delta.numpy(), B.numpy(), C.numpy()],
        [A.numpy()],
        [y.numpy(), last.numpy()],
    )
    return y, last


# ---- Mamba-2 -------------------------------------------------------------------------------------
@njit(**_JIT)
def _ssd_fwd(x, delta, A, Bm, Cm, y, last):  # pragma: no cover - compiled
    """x (B, T, H, P); delta (B, T, H); A (H,); Bm, Cm (B, T, N) -> y (B, T, H, P), last (B, H, P, N)."""
    Bsz, T, H, P = x.shape
    N = Bm.shape[2]
    zero = x.dtype.type(0)
    for b in range(Bsz):
        S = np.zeros((H, P, N), dtype=x.dtype)
        for t in range(T):
            for h in range(H):
                d = delta[b, t, h]
                a = math.exp(d * A[h])
                for p in range(P):
                    dx = d * x[b, t, h, p]
                    acc = zero
                    for n in range(N):
                        v = a * S[h, p, n] + dx * Bm[b, t, n]
                        S[h, p, n] = v
                        acc += v * Cm[b, t, n]
                    y[b, t, h, p] = acc
        last[b] = S


@njit(**_JIT)
def _ssd_bwd(x, delta, A, Bm, Cm, gy, gx, gdelta, gA_rows, gB, gC):  # pragma: no cover - compiled
    """Gradients of the Mamba-2 scan given gy (B, T, H, P); outputs written in place (gA_rows (B, H))."""
    Bsz, T, H, P = x.shape
    N = Bm.shape[2]
    zero = x.dtype.type(0)
    states = np.empty((T + 1, H, P, N), dtype=x.dtype)  # one row's states[t + 1] = S_t, states[0] = 0
    states[0] = 0.0
    carry = np.empty((H, P, N), dtype=x.dtype)  # a_{t+1} lam_{t+1}
    gb_t = np.empty(N, dtype=x.dtype)  # this step's gB and gC, summed over heads and channels
    gc_t = np.empty(N, dtype=x.dtype)
    for b in range(Bsz):
        for t in range(T):
            for h in range(H):
                d = delta[b, t, h]
                a = math.exp(d * A[h])
                for p in range(P):
                    dx = d * x[b, t, h, p]
                    for n in range(N):
                        states[t + 1, h, p, n] = a * states[t, h, p, n] + dx * Bm[b, t, n]
        carry[:] = 0.0
        for t in range(T - 1, -1, -1):
            gb_t[:] = zero
            gc_t[:] = zero
            b_t, c_t = Bm[b, t], Cm[b, t]
            for h in range(H):
                d = delta[b, t, h]
                a = math.exp(d * A[h])
                gd = zero  # x . (lam b)
                gas = zero  # sum_{p,n} lam S_{t-1}
                for p in range(P):
                    g = gy[b, t, h, p]
                    xv = x[b, t, h, p]
                    dx = d * xv
                    s_t, s_prev, car = states[t + 1, h, p], states[t, h, p], carry[h, p]
                    lb = zero
                    for n in range(N):
                        lv = g * c_t[n] + car[n]  # lam_t
                        gc_t[n] += g * s_t[n]
                        gb_t[n] += lv * dx
                        lb += lv * b_t[n]
                        gas += lv * s_prev[n]
                        car[n] = a * lv
                    gx[b, t, h, p] = d * lb
                    gd += xv * lb
                gdelta[b, t, h] = gd + gas * a * A[h]
                gA_rows[b, h] += gas * a * d
            gB[b, t] = gb_t
            gC[b, t] = gc_t


class SSDScanFn(torch.autograd.Function):
    """y, last = the Mamba-2 scan (see :func:`neural_estimator.models.mamba2.ssd_ref`), fused, hand-written backward."""

    @staticmethod
    def forward(ctx, x: Tensor, delta: Tensor, A: Tensor, B: Tensor, C: Tensor):
        x, delta, A, B, C = (v.detach().contiguous() for v in (x, delta, A, B, C))
        Bsz, T, H, P = x.shape
        y = x.new_empty(Bsz, T, H, P)
        last = x.new_empty(Bsz, H, P, B.shape[-1])
        _by_rows(
            lambda x_, d_, B_, C_, A_, y_, l_: _ssd_fwd(x_, d_, A_, B_, C_, y_, l_),
            [x.numpy(), delta.numpy(), B.numpy(), C.numpy()],
            [A.numpy()],
            [y.numpy(), last.numpy()],
        )
        ctx.save_for_backward(x, delta, A, B, C)
        ctx.mark_non_differentiable(last)
        return y, last

    @staticmethod
    def backward(ctx, gy: Tensor, _glast):
        x, delta, A, B, C = ctx.saved_tensors
        gy = gy.contiguous()
        gx, gdelta = torch.empty_like(x), torch.empty_like(delta)
        gB, gC = torch.zeros_like(B), torch.zeros_like(C)
        gA_rows = x.new_zeros(x.shape[0], A.shape[0])
        _by_rows(
            lambda x_, d_, B_, C_, gy_, A_, *out: _ssd_bwd(x_, d_, A_, B_, C_, gy_, *out),
            [x.numpy(), delta.numpy(), B.numpy(), C.numpy(), gy.numpy()],
            [A.numpy()],
            [gx.numpy(), gdelta.numpy(), gA_rows.numpy(), gB.numpy(), gC.numpy()],
        )
        return gx, gdelta, gA_rows.sum(0), gB, gC


def ssd_scan_fused(x: Tensor, delta: Tensor, A: Tensor, B: Tensor, C: Tensor) -> tuple[Tensor, Tensor]:
    """The fused CPU Mamba-2 scan; same arguments and returns as ``ssd_ref``."""
    return SSDScanFn.apply(x, delta, A, B, C)


# ---- the causal depthwise convolution + SiLU in front of both scans ------------------------------
@njit(**_JIT)
def _conv_silu_fwd(x, w, bias, pre, out):  # pragma: no cover - compiled
    """pre[b, t, c] = bias[c] + sum_k w[c, k] x[b, t - K + 1 + k, c] (zero before t = 0); out = silu(pre).

    x (B, T, C) may be a strided view (the in_proj output split in two); pre, out (B, T, C).
    """
    Bsz, T, C = x.shape
    K = w.shape[1]
    for b in range(Bsz):
        for t in range(T):
            for c in range(C):
                pre[b, t, c] = bias[c]
            for k in range(K):
                s = t - K + 1 + k
                if s >= 0:
                    for c in range(C):
                        pre[b, t, c] += w[c, k] * x[b, s, c]
            for c in range(C):
                p = pre[b, t, c]
                out[b, t, c] = p / (1 + math.exp(-p))


@njit(**_JIT)
def _conv_silu_bwd(x, w, pre, gout, gx, gw_rows, gbias_rows):  # pragma: no cover - compiled
    """Gradients of :func:`_conv_silu_fwd`: gx (B, T, C), and per-row gw (B, C, K), gbias (B, C).

    silu'(p) = s (1 + p (1 - s)) with s = sigmoid(p); gx[s] = sum_k w[c, k] gpre[s + K - 1 - k].
    """
    Bsz, T, C = x.shape
    K = w.shape[1]
    gpre = np.empty((T, C), dtype=x.dtype)
    for b in range(Bsz):
        for t in range(T):
            for c in range(C):
                p = pre[b, t, c]
                sg = 1 / (1 + math.exp(-p))
                g = gout[b, t, c] * sg * (1 + p * (1 - sg))
                gpre[t, c] = g
                gbias_rows[b, c] += g
        for s in range(T):
            for c in range(C):
                gx[b, s, c] = 0
            for k in range(K):
                t = s + K - 1 - k
                if t < T:
                    for c in range(C):
                        gx[b, s, c] += w[c, k] * gpre[t, c]
                        gw_rows[b, c, k] += gpre[t, c] * x[b, s, c]


class ConvSiLUFn(torch.autograd.Function):
    """silu(causal depthwise conv1d(x)) on (B, T, C) inputs, with ``nn.Conv1d``'s weight (C, 1, K) and bias (C,).

    Equal to ``F.silu(conv1d(x.transpose(1, 2), weight, bias, padding=K-1, groups=C)[..., :T]).transpose(1, 2)``
    (tested), without the transposes, the padded output and the graph of two operations.
    """

    @staticmethod
    def forward(ctx, x: Tensor, weight: Tensor, bias: Tensor):
        x = x.detach()
        w = weight.detach()[:, 0].contiguous()  # (C, K)
        b = bias.detach().contiguous()
        Bsz, T, C = x.shape
        pre, out = x.new_empty(Bsz, T, C), x.new_empty(Bsz, T, C)
        xn = x.numpy() if x.stride(-1) == 1 else x.contiguous().numpy()
        _by_rows(
            lambda x_, w_, b_, p_, o_: _conv_silu_fwd(x_, w_, b_, p_, o_),
            [xn],
            [w.numpy(), b.numpy()],
            [pre.numpy(), out.numpy()],
        )
        ctx.save_for_backward(x, w, pre)
        ctx.weight_shape = weight.shape
        return out

    @staticmethod
    def backward(ctx, gout: Tensor):
        x, w, pre = ctx.saved_tensors
        gout = gout.contiguous()
        Bsz, T, C = x.shape
        gx = x.new_empty(Bsz, T, C)
        gw_rows = x.new_zeros(Bsz, C, w.shape[1])
        gb_rows = x.new_zeros(Bsz, C)
        xn = x.numpy() if x.stride(-1) == 1 else x.contiguous().numpy()
        _by_rows(
            lambda x_, p_, g_, w_, gx_, gw_, gb_: _conv_silu_bwd(x_, w_, p_, g_, gx_, gw_, gb_),
            [xn, pre.numpy(), gout.numpy()],
            [w.numpy()],
            [gx.numpy(), gw_rows.numpy(), gb_rows.numpy()],
        )
        return gx, gw_rows.sum(0).view(ctx.weight_shape), gb_rows.sum(0)


def conv_silu_fused(x: Tensor, weight: Tensor, bias: Tensor) -> Tensor:
    """silu(causal depthwise conv(x)) for x (B, T, C) on CPU; see :class:`ConvSiLUFn`."""
    return ConvSiLUFn.apply(x, weight, bias)
