"""CPU speed of the six architectures at Lorenz 96 size (d_in = d_out = 40), paper hyperparameters.

Three figures per architecture:

- step latency: one ``model.step`` at batch 1 (the live node's case), p50 and p99 over ``--steps``
  steps after ``--warmup`` steps, under ``torch.inference_mode`` and in eval mode, by the wall
  clock and by the thread's CPU time (which leaves out waiting for a core on a shared machine).
  The stream runs on, so the attention models' KV windows are full for most of the measured steps.
- with ``--compile``, the step latency again with ``torch.compile(model.step)`` (inductor, C++
  kernels; compiling takes seconds to a minute per model and happens in the warm-up).
- sequence throughput: the parallel form on one sequence of T = 500 (the evaluation horizon),
  timesteps per second (median of ``--repeats`` runs).
- training throughput: windows per second for forward + backward + AdamW step on a batch of 64
  windows of length 100 (the paper's training batch), train mode (median of ``--train-iters``).

Threads: ``torch.set_num_threads(--threads)``, 1 by default. One thread is the deployment case of
a node sharing a robot's CPU, and it keeps figures comparable on a shared machine; more threads
help the batched figures, not the batch-1 step latency.

Run: python benchmarks/bench_models.py [--archs gru mamba] [--threads 1] [--compile]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time

import torch

from neural_estimator.models import ARCHITECTURES, SystemDims, build_model, count_parameters

D_IN = D_OUT = 40  # Lorenz 96


def percentiles(seconds: list[float]) -> tuple[float, float]:
    ms = sorted(1e3 * t for t in seconds)
    return ms[len(ms) // 2], ms[min(len(ms) - 1, int(0.99 * len(ms)))]


def step_latency(
    model: torch.nn.Module, steps: int, warmup: int, compiled: bool = False
) -> tuple[float, float, float, float]:
    """Wall-clock (p50, p99) and thread CPU time (p50, p99) of one step at batch 1, in milliseconds.

    The CPU time leaves out the time the thread waited for a core, so on a shared machine it shows
    what a dedicated core would give; the wall clock is what a caller sees here and now.
    ``compiled``: through torch.compile (the first warm-up step compiles).
    """
    z = torch.randn(warmup + steps, 1, D_IN)
    step = torch.compile(model.step, dynamic=False) if compiled else model.step
    wall, cpu = [], []
    with torch.inference_mode():
        state = model.init_state(1)
        for k in range(warmup + steps):
            t0, c0 = time.perf_counter(), time.thread_time()
            _, state = step(z[k], state)
            wall.append(time.perf_counter() - t0)
            cpu.append(time.thread_time() - c0)
    return (*percentiles(wall[warmup:]), *percentiles(cpu[warmup:]))


def sequence_throughput(model: torch.nn.Module, T: int, repeats: int) -> float:
    """Timesteps per second of the parallel form on one sequence of length T."""
    z = torch.randn(1, T, D_IN)
    times = []
    with torch.inference_mode():
        model(z)
        for _ in range(repeats):
            t0 = time.perf_counter()
            model(z)
            times.append(time.perf_counter() - t0)
    return T / statistics.median(times)


def training_throughput(model: torch.nn.Module, batch: int, length: int, iters: int) -> float:
    """Windows per second of forward + backward + AdamW step."""
    model.train()
    opt = torch.optim.AdamW(model.parameters(), lr=2e-3, weight_decay=1e-5)
    z = torch.randn(batch, length, D_IN)
    x = torch.randn(batch, length, D_OUT)
    times = []
    for i in range(iters + 1):
        t0 = time.perf_counter()
        opt.zero_grad(set_to_none=True)
        loss = torch.nn.functional.mse_loss(model(z), x)
        loss.backward()
        opt.step()
        if i:  # the first iteration allocates the optimiser state
            times.append(time.perf_counter() - t0)
    model.eval()
    return batch / statistics.median(times)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--archs", nargs="+", default=list(ARCHITECTURES), choices=list(ARCHITECTURES))
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--steps", type=int, default=3000, help="measured steps for the latency")
    ap.add_argument("--warmup", type=int, default=300)
    ap.add_argument("--seq-len", type=int, default=500)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--train-iters", type=int, default=5)
    ap.add_argument("--compile", action="store_true", help="also time torch.compile(model.step)")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)

    print(f"command: python benchmarks/bench_models.py {' '.join(argv if argv is not None else sys.argv[1:])}".rstrip())
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(
        f"torch {torch.__version__}, {args.threads} thread(s), {os.cpu_count()} CPUs ({platform.machine()}), "
        f"load average {load:.1f} at start, Lorenz 96 dims ({D_IN} -> {D_OUT})\n"
    )
    extra = " compiled p50 / p99 (ms) | compiled CPU p50 / p99 (ms) |" if args.compile else ""
    print(
        f"| arch | params | step p50 / p99 (ms) | step CPU p50 / p99 (ms) |{extra} seq T={args.seq_len} (steps/s) "
        f"| train B=64 T=100 (windows/s) |"
    )
    print("|---|---:|---:|---:|" + ("---:|---:|" if args.compile else "") + "---:|---:|")
    for name in args.archs:
        model = build_model(name, SystemDims(dx=D_OUT, dy=D_IN)).eval()
        p50, p99, c50, c99 = step_latency(model, args.steps, args.warmup)
        cols = f" {p50:.3f} / {p99:.3f} | {c50:.3f} / {c99:.3f} |"
        if args.compile:
            p50, p99, c50, c99 = step_latency(model, args.steps, args.warmup, compiled=True)
            cols += f" {p50:.3f} / {p99:.3f} | {c50:.3f} / {c99:.3f} |"
        seq = sequence_throughput(model, args.seq_len, args.repeats)
        train = training_throughput(model, 64, 100, args.train_iters)
        print(f"| {name} | {count_parameters(model):,} |{cols} {seq:,.0f} | {train:,.1f} |", flush=True)


if __name__ == "__main__":
    main()
