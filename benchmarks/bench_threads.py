"""Training with two threads beside one, on a busy machine: the OpenMP wait policy's effect.

    .venv/bin/python benchmarks/bench_threads.py                      # gru, with a busy neighbour
    .venv/bin/python benchmarks/bench_threads.py --archs mamba2 --no-busy --rounds 3

Every configuration (architecture x threads 1 or 2 x wait policy) is a fresh process that times
training steps (forward, backward, AdamW at the paper's batch of 64 windows of 100 steps, Lorenz 96
widths) after two warm-up steps and reports windows/s over all of them (a governed run's probes
included); configurations alternate in rounds so that a changing machine load touches them alike,
and the median over rounds is printed. A configuration still running after
``--timeout`` s is stopped and reported as a bound ("< x windows/s"). ``--busy`` (default) runs a spinning
process beside them (a second job on another core, as when two trainings share this machine).

Wait policies (``--policies``): ``spin`` is OpenMP's default (libgomp's workers spin for a while
before sleeping; ``OMP_WAIT_POLICY`` unset), ``passive`` sleeps at once (``OMP_WAIT_POLICY=PASSIVE``),
``spincount=N`` spins N iterations, then sleeps (``GOMP_SPINCOUNT=N``, policy unset); what
``neural-estimator`` sets before torch loads is :data:`neural_estimator.core.runtime.WAIT_POLICY`.
``governed`` is passive with the thread count chosen by measurement, as ``neural-estimator train
--threads N`` does (:class:`neural_estimator.training.threads.ThreadGovernor`, 4-step probes).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

CHILD = r"""
import json, sys, time
import torch
from neural_estimator.models import SystemDims, build_model
arch, threads, iters, governed = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4] == "1"
torch.set_num_threads(threads)
gov = None
if governed:
    from neural_estimator.training.threads import ThreadGovernor
    gov = ThreadGovernor(threads, probe_steps=4)
torch.manual_seed(0)
model = build_model(arch, SystemDims(dx=40, dy=40)).train()
opt = torch.optim.AdamW(model.parameters(), lr=2e-3)
z, x = torch.randn(64, 100, 40), torch.randn(64, 100, 40)
times = []
for i in range(iters + 2):
    t0 = time.perf_counter()
    if gov is not None:
        gov.before_step()
    opt.zero_grad(set_to_none=True)
    torch.nn.functional.mse_loss(model(z), x).backward()
    torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
    opt.step()
    if gov is not None:
        gov.after_step()
    if i >= 2:
        times.append(time.perf_counter() - t0)
times.sort()
print(json.dumps({"windows_per_s": 64 * len(times) / sum(times)}))
"""

BUSY = "import time\nx = 0\nwhile True:\n    x += 1\n"


def run_child(arch: str, threads: int, policy: str, iters: int, timeout: float) -> float:
    """Training windows/s of one configuration; a run past ``timeout`` s counts as the bound
    (iters + 2) x 64 / timeout (negative: "slower than this")."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    for var in ("OMP_WAIT_POLICY", "KMP_BLOCKTIME", "OMP_NUM_THREADS", "GOMP_SPINCOUNT"):
        env.pop(var, None)
    if policy == "passive":
        env["OMP_WAIT_POLICY"] = "PASSIVE"
    elif policy == "governed":
        env["OMP_WAIT_POLICY"] = "PASSIVE"  # what neural-estimator sets, and the count measured
    elif policy.startswith("spincount="):
        env["GOMP_SPINCOUNT"] = policy.split("=", 1)[1]
    elif policy != "spin":
        raise SystemExit(f"unknown policy {policy!r}: spin, passive, governed or spincount=N")
    try:
        out = subprocess.run(
            [sys.executable, "-c", CHILD, arch, str(threads), str(iters), str(int(policy == "governed"))],
            env=env,
            capture_output=True,
            text=True,
            timeout=timeout,
        )
    except subprocess.TimeoutExpired:
        return -(iters + 2) * 64 / timeout
    if out.returncode:
        raise RuntimeError(out.stderr[-2000:])
    return json.loads(out.stdout.strip().splitlines()[-1])["windows_per_s"]


def _fmt(v: float) -> str:
    return f"{v:.1f}" if v > 0 else f"< {-v:.1f} (timed out)"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--archs", nargs="+", default=["gru"])
    ap.add_argument("--iters", type=int, default=4, help="timed training steps per process")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--timeout", type=float, default=240.0, help="seconds per configuration (then a bound)")
    ap.add_argument("--busy", action=argparse.BooleanOptionalAction, default=True)
    ap.add_argument(
        "--policies", nargs="+", default=["spin", "passive", "governed"], help="spin, passive, governed, spincount=N"
    )
    a = ap.parse_args(argv)
    print(f"command: python benchmarks/bench_threads.py {' '.join(argv if argv is not None else sys.argv[1:])}")
    busy = subprocess.Popen([sys.executable, "-c", BUSY]) if a.busy else None
    load0 = os.getloadavg()[0]
    t0 = time.monotonic()
    configs = [(arch, th, pol) for arch in a.archs for pol in a.policies for th in (1, 2)]
    res: dict[tuple, list[float]] = {c: [] for c in configs}
    try:
        for r in range(a.rounds):
            for c in configs:
                res[c].append(run_child(*c, a.iters, a.timeout))
                print(f"round {r + 1}: {c[0]}, {c[1]} thread(s), {c[2]}: {_fmt(res[c][-1])} windows/s", flush=True)
    finally:
        if busy is not None:
            busy.kill()
            busy.wait()
    print(
        f"{os.cpu_count()} cores, {'a spinning neighbour process, ' if a.busy else ''}load average "
        f"{load0:.1f} at start, {os.getloadavg()[0]:.1f} at the end, {time.monotonic() - t0:.0f} s; "
        f"median of {a.rounds} rounds, training windows/s (batch 64 x 100 steps)\n"
    )
    print("| arch | policy | 1 thread | 2 threads | 2 / 1 |")
    print("|---|---|---:|---:|---:|")
    for arch in a.archs:
        for pol in a.policies:
            one, two = (statistics.median(res[(arch, th, pol)]) for th in (1, 2))
            ratio = f"{two / one:.2f}x" if one > 0 and two > 0 else f"< {abs(two) / abs(one):.2f}x"
            print(f"| {arch} | {pol} | {_fmt(one)} | {_fmt(two)} | {ratio} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
