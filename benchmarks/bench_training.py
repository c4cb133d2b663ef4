"""Training throughput of the six architectures: windows per second at the paper's batch and window.

One training step is what :func:`neural_estimator.training.loop.train` does per batch: forward a
(64, 100, d_in) batch, the weighted MSE on (64, 100, d_out), backward, gradient clipping at 1.0 and
an AdamW step. Inputs are random (throughput does not depend on the data); the default widths are
Lorenz 96's (d_in = d_out = 40), the largest of the paper's five systems. Also measured: the
validation forward (eval mode, no grad) over full-length trajectories, in timesteps per second, and
from both the cost of one epoch at the paper's 20:1 setting (20,000 windows + 8,000 x 500
validation steps).

    python benchmarks/bench_training.py                      # all six, CPU
    python benchmarks/bench_training.py --archs gru,mamba --device cuda --iters 50

Mamba, Mamba-2, GPT-2 and the Filterformer are measured twice in the same run: ``(before)`` is the
previous CPU training path (Mamba: the stepwise torch scan; Mamba-2: the chunked torch SSD, both with
autograd graphs; GPT-2 and Filterformer: attention on torch's unfused math path), ``fused`` the
current one (the SSMs: the numba kernels with hand-written backward,
:mod:`neural_estimator.models.cpu_scan`; the attention models: torch's fused CPU attention kernel,
which the 4-D operands and mask of :func:`~neural_estimator.models.layers.window_attention` admit,
for validation, and in training the written-out attention and dropout with the cheaper CPU mask of
:mod:`neural_estimator.models.dropout`; ``(before)`` there is torch's dropout and math path).

Achieved GFLOP/s = model FLOPs of one training step / its time. Model FLOPs are counted by torch's
FlopCounterMode over forward + backward on the *before* path (matmuls, convolutions and the scans'
contractions; elementwise work is not counted), so both paths of an architecture are charged the
same work and their GFLOP/s ratio is their speed ratio. The machine's rate is float32 GEMM on the
model's own matmul shapes ((B T) x d_model times d_model x 2 E and the like), measured in the same
run and thread setting.

Prints a markdown table and the command that produced it.
"""

from __future__ import annotations

import argparse
import platform
import shlex
import sys
import time

import torch
from torch.utils.flop_counter import FlopCounterMode

from neural_estimator.models import ARCHITECTURES, SystemDims, build_model
from neural_estimator.models.dropout import Dropout
from neural_estimator.serving.neural import resolve_device
from neural_estimator.training.loss import weighted_loss
from neural_estimator.core.runtime import tune_allocator

EPOCH_WINDOWS = 20_000  # windows per epoch at 20:1 (protocol.windows_per_epoch)
VAL_STEPS = 8_000 * 500  # validation timesteps per epoch


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


# The previous CPU path of each architecture: the SSMs' scans, the attention models' unfused SDPA.
BEFORE = {"mamba": "stepwise", "mamba2": "chunked", "gpt2": "math", "filterformer": "math"}


def set_scan(model: torch.nn.Module, scan: str) -> None:
    """Select the CPU training path of every SSM mixer (``cpu_scan``), attention layer
    (``attention_path``) and dropout (``Dropout.fast``) in ``model``: "fused" or the
    architecture's BEFORE path."""
    for m in model.modules():
        if hasattr(m, "cpu_scan"):
            m.cpu_scan = scan
        if hasattr(m, "attention_path"):
            m.attention_path = scan
        if isinstance(m, Dropout):
            m.fast = scan == "fused"


def step_flops(arch: str, args: argparse.Namespace) -> float:
    """FLOPs of one forward + backward on the *before* path (FlopCounterMode), see the module docstring."""
    model = build_model(arch, SystemDims(dx=args.d_out, dy=args.d_in))
    set_scan(model, BEFORE.get(arch, "fused"))
    z = torch.randn(args.batch, args.window, args.d_in)
    with FlopCounterMode(display=False) as counter:
        model(z).square().mean().backward()
    return float(counter.get_total_flops())


def gemm_rate(args: argparse.Namespace, reps: int = 20) -> float:
    """float32 GFLOP/s of torch matmul on Mamba's GEMM shapes at this batch (forward and backward shapes)."""
    M, d = args.batch * args.window, 80
    E = 2 * d
    shapes = [(M, d, 2 * E), (M, E, 5 + 32), (M, E, d), (M, 2 * E, d), (2 * E, M, d), (d, M, E)]
    mats = [(torch.randn(m, k), torch.randn(k, n)) for m, k, n in shapes]
    for a, b in mats:
        a @ b
    t0, c0 = time.perf_counter(), time.process_time()
    for _ in range(reps):
        for a, b in mats:
            a @ b
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    flops = reps * sum(2 * m * k * n for m, k, n in shapes)
    return flops / wall / 1e9, flops / cpu / 1e9


def bench_arch(arch: str, args: argparse.Namespace, device: torch.device, scan: str | None = None) -> dict[str, float]:
    torch.manual_seed(0)
    model = build_model(arch, SystemDims(dx=args.d_out, dy=args.d_in)).to(device).train()
    if scan:
        set_scan(model, scan)
    opt = torch.optim.AdamW(model.parameters(), lr=2e-3, weight_decay=1e-5)
    z = torch.randn(args.batch, args.window, args.d_in, device=device)
    x = torch.randn(args.batch, args.window, args.d_out, device=device)
    w = torch.ones(args.batch, args.window, device=device)
    w[:, :10] = 0.0
    no_angles = torch.zeros(args.d_out, dtype=torch.bool, device=device)

    def train_step() -> None:
        loss = weighted_loss(model(z), x, w, no_angles)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()

    for _ in range(args.warmup):
        train_step()
    _sync(device)
    t0, c0 = time.perf_counter(), time.process_time()
    for _ in range(args.iters):
        train_step()
    _sync(device)
    train_s = (time.perf_counter() - t0) / args.iters
    train_cpu_s = (time.process_time() - c0) / args.iters  # this process's CPU time: less sensitive to load

    model.eval()
    zv = torch.randn(args.val_batch, args.val_length, args.d_in, device=device)
    with torch.no_grad():
        model(zv)
        _sync(device)
        t0 = time.perf_counter()
        for _ in range(args.val_iters):
            model(zv)
        _sync(device)
    val_s = (time.perf_counter() - t0) / args.val_iters
    windows_per_s = args.batch / train_s
    val_steps_per_s = args.val_batch * args.val_length / val_s
    return {
        "train_s": train_s,
        "train_cpu_s": train_cpu_s,
        "params": sum(p.numel() for p in model.parameters()),
        "ms_per_step": 1e3 * train_s,
        "windows_per_s": windows_per_s,
        "val_steps_per_s": val_steps_per_s,
        "epoch_s": EPOCH_WINDOWS / windows_per_s + VAL_STEPS / val_steps_per_s,
    }


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--archs", default=",".join(ARCHITECTURES), help="comma-separated architectures")
    p.add_argument("--device", default="cpu")
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--window", type=int, default=100)
    p.add_argument("--d-in", type=int, default=40, help="input width (Lorenz 96: 40)")
    p.add_argument("--d-out", type=int, default=40, help="state width (Lorenz 96: 40)")
    p.add_argument("--warmup", type=int, default=2, help="untimed training steps first")
    p.add_argument("--iters", type=int, default=10, help="timed training steps")
    p.add_argument("--val-batch", type=int, default=100)
    p.add_argument("--val-length", type=int, default=500)
    p.add_argument("--val-iters", type=int, default=1)
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    args = p.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    tuned = tune_allocator()  # as the CLI does: large tensors reuse memory instead of new zeroed pages
    device = resolve_device(args.device)
    archs = [a.strip() for a in args.archs.split(",") if a.strip()]
    unknown = [a for a in archs if a not in ARCHITECTURES]
    if unknown:
        p.error(f"unknown architectures {unknown}; known: {', '.join(ARCHITECTURES)}")

    if device.type == "cuda":
        where = torch.cuda.get_device_name(device)
    else:
        where = f"{platform.processor() or platform.machine()}, {torch.get_num_threads()} threads"
    print(
        f"Training throughput, batch {args.batch} x window {args.window}, d_in={args.d_in}, d_out={args.d_out}, "
        f"{device} ({where}), torch {torch.__version__}, allocator tuned: {tuned}"
    )
    rate, rate_cpu = gemm_rate(args) if device.type == "cpu" else (float("nan"), float("nan"))
    print(
        f"float32 GEMM rate on the models' matmul shapes (this run, same threads): {rate:.1f} GFLOP/s per wall "
        f"second, {rate_cpu:.1f} GFLOP/s per CPU second\n"
    )
    print(
        "| model | path | params | ms / step | windows / s | GFLOP / step | GFLOP/s | % of GEMM rate "
        "| windows / CPU-s | GFLOP / CPU-s | % of GEMM CPU rate | val steps / s | epoch at 20:1 (s) |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for arch in archs:
        flops = step_flops(arch, args)
        paths = [BEFORE[arch] + " (before)", "fused"] if arch in BEFORE and device.type == "cpu" else ["default"]
        for path in paths:
            r = bench_arch(arch, args, device, None if path == "default" else path.split()[0])
            gflops, gflops_cpu = flops / r["train_s"] / 1e9, flops / r["train_cpu_s"] / 1e9
            print(
                f"| {arch} | {path} | {r['params']:,} | {r['ms_per_step']:.1f} | {r['windows_per_s']:,.0f} | "
                f"{flops / 1e9:.2f} | {gflops:.1f} | {100 * gflops / rate:.0f} % | "
                f"{args.batch / r['train_cpu_s']:,.0f} | {gflops_cpu:.1f} | {100 * gflops_cpu / rate_cpu:.0f} % | "
                f"{r['val_steps_per_s']:,.0f} | {r['epoch_s']:,.0f} |",
                flush=True,
            )
    print(f"\nepoch = {EPOCH_WINDOWS:,} training windows + {VAL_STEPS:,} validation timesteps")
    words = [sys.argv[0], *(argv if argv is not None else sys.argv[1:])]
    print("command: python " + " ".join(shlex.quote(a) for a in words))


if __name__ == "__main__":
    main()
