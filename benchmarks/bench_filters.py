"""Speed of the batched classical filters (EKF, UKF, EnKF, PF) against filterpy, and the cost of
the paper's evaluation protocol.

    .venv/bin/python benchmarks/bench_filters.py                     # everything, ~10 min on 2 cores
    .venv/bin/python benchmarks/bench_filters.py --scenarios lorenz96 --methods ukf --batch 2000

(1) Throughput: trajectory-steps per second of each filter on each scenario, ``run`` over
    B = ``--batch`` (8000) simulated trajectories of ``--steps`` (50) steps: a shorter horizon than
    the paper's 500 to keep the benchmark at minutes, and enough steps that the first one (update
    only, no prediction) weighs 2 %. The PF, 100-1000x costlier per trajectory-step, runs the same
    8000 trajectories (``--pf-batch``) for ``--pf-steps`` (5) steps; there the update-only first
    step is a fifth of the steps, so its figure overstates the steady rate by up to ~15 % (the
    prediction, f on 1024 particles, is about half of a PF step). Next to each: filterpy's
    one-trajectory-at-a-time loop (:mod:`neural_estimator.filters.reference`:
    ExtendedKalmanFilter, UnscentedKalmanFilter with MerweScaledSigmaPoints(1e-3, 2, 0),
    EnsembleKalmanFilter(N=50), and for the PF a bootstrap PF on
    filterpy.monte_carlo.systematic_resample, vectorised over its particles) on
    ``--fp-trajectories`` (4) of the same trajectories for ``--fp-steps`` (30) steps, after one
    warm-up trajectory, extrapolated per trajectory-step; the ratio is ours / filterpy's.
    Ours runs on 1 thread and on the usable cores (``--filter-threads``): the blocks of streams of
    a batch run concurrently (numpy releases the GIL); filterpy's loop is one thread. Both ratios
    are printed. ``--repeats`` K keeps the fastest of K runs of each (ours and filterpy's alike):
    on a shared machine single runs of the same code varied by +-10 %.
(2) Latency: wall time of one ``step`` at B = 1 on Lorenz 96 (40 states, 40 observations), p50 and
    p99 over ``--latency-steps`` (400) steps after 20 warm-up steps.
(3) The paper's protocol: 3 evaluation sets x 8000 trajectories x horizon (500; planar quadrotor
    200) per scenario, estimated as 24000 x horizon / throughput(1), with the batch cut into chunks
    that keep memory under ``--mem-gib`` (8 GiB).

Chunk rule. Peak memory of ``run`` over b trajectories of T steps is modelled as

    M(b, T) = a + b (c + T o),    o = 8 bytes x (dy + du + dx + dx^2)

o: the inputs Y, U and the outputs (estimates and covariances, which ``run`` returns); a: the
blocks' transient arrays (independent of b); c: the per-trajectory state (sigma points are
transient, members and particles are not). a and c come from tracemalloc's peak over two short
runs (b = 2 and 6 blocks of streams, T = 3); the chunk is floor((M_max - a) / (c + T o)), at most
8000. Throughput runs here use chunks for ``--run-mem-gib`` (2 GiB: the machine is shared); chunks
of any size >= one block do the same work per trajectory-step.

BLAS threads: ``--threads`` (1) is exported as OPENBLAS_NUM_THREADS / OMP_NUM_THREADS / MKL_NUM_THREADS
before numpy is imported. The filters' matrices are 1x1 to 40x40 per stream; on this 2-core machine,
shared with other jobs, a second OpenBLAS thread made stacked products up to 500x slower when the
other core was busy (spinning threads), and never faster for these sizes.
"""

from __future__ import annotations

import argparse
import os
import sys

from neural_estimator.paper import PAPER_SCENARIOS  # no numpy: the thread variables are still unset

METHODS = ("ekf", "ukf", "enkf", "pf")


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--scenarios", nargs="+", default=list(PAPER_SCENARIOS))
    p.add_argument("--methods", nargs="+", default=list(METHODS))
    p.add_argument("--batch", type=int, default=8000, help="trajectories for the EKF, UKF and EnKF (8000)")
    p.add_argument("--steps", type=int, default=50, help="time steps of the throughput runs (50)")
    p.add_argument("--pf-batch", type=int, default=8000, help="trajectories for the PF (8000)")
    p.add_argument("--pf-steps", type=int, default=5, help="time steps of the PF's throughput runs (5)")
    p.add_argument("--fp-trajectories", type=int, default=4, help="trajectories for filterpy's loop (4)")
    p.add_argument("--fp-steps", type=int, default=30, help="time steps for filterpy's loop (30)")
    p.add_argument("--latency-steps", type=int, default=400, help="B = 1 steps timed on Lorenz 96 (400)")
    p.add_argument("--mem-gib", type=float, default=8.0, help="memory bound of the protocol estimate (8)")
    p.add_argument("--run-mem-gib", type=float, default=2.0, help="memory bound of the runs made here (2)")
    p.add_argument("--threads", type=int, default=1, help="BLAS threads (1)")
    p.add_argument("--repeats", type=int, default=1, help="throughput runs per figure, the fastest kept (1)")
    p.add_argument(
        "--filter-threads",
        type=int,
        nargs="+",
        help="the filters' worker threads to measure (default: 1 and the usable cores)",
    )
    p.add_argument("--seed", type=int, default=0)
    return p.parse_args(argv)


ARGS = parse_args() if __name__ == "__main__" else None
if ARGS is not None:
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = str(ARGS.threads)

import platform  # noqa: E402
import time  # noqa: E402
import tracemalloc  # noqa: E402

import numpy as np  # noqa: E402

from neural_estimator.data.simulate import simulate  # noqa: E402
from neural_estimator.methods.registry import make_estimator, previous_controls  # noqa: E402
from neural_estimator.filters import reference  # noqa: E402
from neural_estimator.filters.base import default_threads  # noqa: E402
from neural_estimator.core.runtime import tune_allocator  # noqa: E402
from neural_estimator.scenarios import Scenario, make_scenario  # noqa: E402

PAPER_SETS, PAPER_TRAJECTORIES = 3, 8000
FILTERPY = {
    "ekf": lambda s, y, u: reference.filterpy_ekf(s, y, u),
    "ukf": lambda s, y, u: reference.filterpy_ukf(s, y, u),
    "enkf": lambda s, y, u: reference.filterpy_enkf(s, y, u, N=50, seed=0),
    "pf": lambda s, y, u: reference.reference_pf(s, y, u, N=1024, init_std=1.0, seed=0),
}


# ---- memory model and chunks -------------------------------------------------------------------------
def io_bytes_per_step(s: Scenario) -> int:
    """o: bytes per trajectory and step of Y, U and the returned estimates and covariances."""
    return 8 * (s.dy + s.du + s.dx + s.dx * s.dx)


def memory_model(method: str, s: Scenario, Y: np.ndarray, U: np.ndarray) -> tuple[float, float]:
    """(a, c) of M(b, T) = a + b (c + T o), from tracemalloc peaks at two batch sizes, T = 3."""
    f = make_estimator(method, s)
    f.reset(1)
    block = f.block_size
    T = 3
    o = io_bytes_per_step(s)
    peaks = []
    avail = Y.shape[0]
    sizes = (max(1, min(2 * block, avail // 3)), min(6 * block, avail))
    for b in sizes:
        y, u = np.ascontiguousarray(Y[:b, :T]), np.ascontiguousarray(U[:b, :T])
        tracemalloc.start()
        tracemalloc.reset_peak()
        base = tracemalloc.get_traced_memory()[0]
        make_estimator(method, s).run(y, u)
        peak = tracemalloc.get_traced_memory()[1] - base
        tracemalloc.stop()
        peaks.append(peak + b * T * 8 * (s.dy + s.du))  # the inputs were allocated before tracing
    c_plus = (peaks[1] - peaks[0]) / (sizes[1] - sizes[0])  # c + T o
    c = max(c_plus - T * o, 0.0)
    a = max(peaks[0] - sizes[0] * c_plus, 0.0)
    return a, c


def chunk_size(a: float, c: float, s: Scenario, T: int, mem_bytes: float, cap: int = PAPER_TRAJECTORIES) -> int:
    """floor((M - a) / (c + T o)), between 1 and ``cap``."""
    per = c + T * io_bytes_per_step(s)
    return int(max(1, min(cap, (mem_bytes - a) // per)))


# ---- measurements --------------------------------------------------------------------------------------
def throughput(method: str, s: Scenario, Y: np.ndarray, U: np.ndarray, chunk: int, threads: int) -> tuple[float, int]:
    """(trajectory-steps per second, diverged count) of ``run`` over Y in chunks, on ``threads`` threads."""
    B, T, _ = Y.shape
    diverged = 0
    # warm-up: loads (or on a first run compiles) the PF's numba kernels, outside the timing
    make_estimator(method, s, threads=threads).run(Y[:2, :2], U[:2, :2])
    t0 = time.perf_counter()
    for i in range(0, B, chunk):
        est = make_estimator(method, s, threads=threads).run(Y[i : i + chunk], U[i : i + chunk])
        diverged += int(est.diverged.sum())
    return B * T / (time.perf_counter() - t0), diverged


def filterpy_throughput(method: str, s: Scenario, Y: np.ndarray, U: np.ndarray, n: int, T: int) -> float:
    """Trajectory-steps per second of filterpy's loop over n trajectories of T steps (after a warm-up)."""
    fn = FILTERPY[method]
    fn(s, Y[n, :2], U[n, :2])  # warm-up: imports, first-call caches
    t0 = time.perf_counter()
    for b in range(n):
        fn(s, Y[b, :T], U[b, :T])
    return n * T / (time.perf_counter() - t0)


def latency(
    method: str, s: Scenario, y: np.ndarray, u: np.ndarray, steps: int, warmup: int = 20
) -> tuple[float, float]:
    """(p50, p99) in ms of one step at B = 1."""
    f = make_estimator(method, s, threads=1)
    f.reset(1)
    times = []
    for k in range(warmup + steps):
        t0 = time.perf_counter()
        f.step(y[k : k + 1], u[k : k + 1])
        times.append(time.perf_counter() - t0)
    ms = np.array(times[warmup:]) * 1e3
    return float(np.percentile(ms, 50)), float(np.percentile(ms, 99))


def fmt_rate(x: float) -> str:
    return f"{x:,.0f}" if x >= 100 else f"{x:.1f}"


def fmt_duration(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.1f} min"
    return f"{seconds / 3600:.1f} h"


def main(args: argparse.Namespace) -> None:
    cmd = " ".join([".venv/bin/python", "benchmarks/bench_filters.py"] + sys.argv[1:])
    print(f"# Classical filters: throughput, latency, protocol cost\n\n`{cmd}`\n")
    print(
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, numpy {np.__version__}, "
        f"BLAS threads {args.threads}, load average at start {os.getloadavg()[0]:.2f}\n"
    )
    tuned = tune_allocator()
    thread_counts = sorted(set(args.filter_threads or (1, default_threads())))
    print(f"Allocator tuned (neural_estimator.core.runtime): {tuned}. Filter threads measured: {thread_counts}.\n")
    t_start = time.perf_counter()
    results = {}  # (scenario, method) -> dict
    for name in args.scenarios:
        s = make_scenario(name)
        need = max(args.batch if set(args.methods) - {"pf"} else 0, args.pf_batch if "pf" in args.methods else 0)
        T_sim = max(args.steps, args.pf_steps, args.fp_steps, 3)
        tr = simulate(s, need, T_sim, seed=args.seed)
        for method in args.methods:
            B, T = (args.pf_batch, args.pf_steps) if method == "pf" else (args.batch, args.steps)
            Y, U = tr.y[:B, :T], tr.u[:B, :T]
            a, c = memory_model(method, s, tr.y, tr.u)
            run_chunk = chunk_size(a, c, s, T, args.run_mem_gib * 2**30)
            rates = {}
            for threads in thread_counts:
                runs = [throughput(method, s, Y, U, run_chunk, threads) for _ in range(args.repeats)]
                rates[threads], diverged = max(r for r, _ in runs), runs[0][1]
            rate = rates[thread_counts[-1]]
            fp_rate = max(
                filterpy_throughput(method, s, tr.y, tr.u, args.fp_trajectories, min(args.fp_steps, T_sim))
                for _ in range(args.repeats)
            )
            H = s.horizon
            chunk = chunk_size(a, c, s, H, args.mem_gib * 2**30)
            results[name, method] = dict(
                B=B,
                T=T,
                rate=rate,
                rates=rates,
                fp_rate=fp_rate,
                diverged=diverged,
                run_chunk=run_chunk,
                a=a,
                c=c,
                horizon=H,
                chunk=chunk,
                peak=a + chunk * (c + H * io_bytes_per_step(s)),
                protocol_s=PAPER_SETS * PAPER_TRAJECTORIES * H / rate,
            )
            print(
                f"  {name:10s} {method:5s} B={B} T={T}: "
                + ", ".join(f"{fmt_rate(r)} traj-steps/s on {t} thread(s)" for t, r in rates.items())
                + f" (filterpy {fmt_rate(fp_rate)}/s), diverged {diverged}, chunk {run_chunk}",
                file=sys.stderr,
                flush=True,
            )

    # (1) throughput
    print("## (1) Throughput, trajectory-steps per second (ours / filterpy's one-trajectory loop)\n")
    print(
        f"EKF, UKF, EnKF: B = {args.batch} trajectories x T = {args.steps} steps; PF: B = {args.pf_batch} x "
        f"T = {args.pf_steps} (see the docstring). filterpy: {args.fp_trajectories} trajectories x "
        f"{args.fp_steps} steps, extrapolated per trajectory-step (one thread: it is a Python loop). "
        f"Ours on {' and '.join(map(str, thread_counts))} thread(s); the ratios are ours on "
        f"{thread_counts[-1]} / filterpy, and in brackets ours on {thread_counts[0]} / filterpy.\n"
    )
    lo, hi = thread_counts[0], thread_counts[-1]
    print("| scenario | " + " | ".join(f"{m.upper()} ours | {m.upper()} filterpy | ratio" for m in args.methods) + " |")
    print("|---|" + "---:|---:|---:|" * len(args.methods))
    for name in args.scenarios:
        cells = []
        for m in args.methods:
            r = results[name, m]
            ratio = f"{r['rates'][hi] / r['fp_rate']:.0f}x"
            if hi != lo:
                ratio += f" ({r['rates'][lo] / r['fp_rate']:.0f}x)"
            cells += [fmt_rate(r["rate"]), fmt_rate(r["fp_rate"]), ratio]
        print(f"| {name} | " + " | ".join(cells) + " |")
    div = [(n, m, r["diverged"], r["B"]) for (n, m), r in results.items() if r["diverged"]]
    if div:
        print("\nStreams flagged as diverged in these runs: " + ", ".join(f"{m} on {n}: {d}/{b}" for n, m, d, b in div))

    # (2) latency
    s = make_scenario("lorenz96")
    tr = simulate(s, 1, args.latency_steps + 20, seed=args.seed + 1)
    print("\n## (2) Latency of one step at B = 1, Lorenz 96 (40 states, 40 observations)\n")
    print(f"{args.latency_steps} steps after 20 warm-up steps.\n")
    print("| filter | p50 ms | p99 ms |\n|---|---:|---:|")
    for m in args.methods:
        p50, p99 = latency(m, s, tr.y[0], previous_controls(tr.u)[0], args.latency_steps)
        print(f"| {m.upper()} | {p50:.3f} | {p99:.3f} |")

    # (3) protocol
    print(
        f"\n## (3) The paper's protocol: {PAPER_SETS} sets x {PAPER_TRAJECTORIES} trajectories x horizon, "
        f"memory <= {args.mem_gib:g} GiB\n"
    )
    print(
        f"Estimated wall time = 24000 x horizon / throughput (1) on {thread_counts[-1]} thread(s), on this machine.\n"
    )
    print(
        "| scenario | horizon | "
        + " | ".join(f"{m.upper()} time | {m.upper()} chunk (peak GiB)" for m in args.methods)
        + " |"
    )
    print("|---|---:|" + "---:|---:|" * len(args.methods))
    totals = {m: 0.0 for m in args.methods}
    for name in args.scenarios:
        cells = []
        for m in args.methods:
            r = results[name, m]
            totals[m] += r["protocol_s"]
            cells += [fmt_duration(r["protocol_s"]), f"{r['chunk']} ({r['peak'] / 2**30:.1f})"]
        print(f"| {name} | {results[name, args.methods[0]]['horizon']} | " + " | ".join(cells) + " |")
    print("| **all five** | | " + " | ".join(f"**{fmt_duration(totals[m])}** | " for m in args.methods) + "|")
    print(
        f"\nChunk = floor(({args.mem_gib:g} GiB - a) / (c + horizon x o)), o = 8 (dy + du + dx + dx^2) bytes; "
        "a, c per filter and scenario from tracemalloc:\n"
    )
    print("| scenario | " + " | ".join(f"{m.upper()} a MiB | {m.upper()} c KiB" for m in args.methods) + " |")
    print("|---|" + "---:|---:|" * len(args.methods))
    for name in args.scenarios:
        cells = []
        for m in args.methods:
            r = results[name, m]
            cells += [f"{r['a'] / 2**20:.1f}", f"{r['c'] / 2**10:.1f}"]
        print(f"| {name} | " + " | ".join(cells) + " |")
    print(
        f"\nWall time of this benchmark: {fmt_duration(time.perf_counter() - t_start)}; load average at the end "
        f"{os.getloadavg()[0]:.2f}."
    )


if __name__ == "__main__":
    main(ARGS)
