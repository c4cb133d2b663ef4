"""Peak memory of scoring a recording, against the recording's length.

Writes synthetic recordings of a 500 Hz run (bearings, 500-step trajectories, ground truth,
observations, three estimate streams and two covariance streams, as the evaluator records them)
of each length in ``--minutes``, then scores each in a fresh process, twice: the evaluator node's
post-run analysis (:func:`neural_estimator.evaluation.bag_report.evaluate_bag`) and ``neural-estimator
metrics BAG``. Prints each process's peak resident memory (``ru_maxrss`` of the child) and wall
time, and each peak as a multiple of the shortest recording's: a scorer whose memory does not grow
with the run's length prints about 1.0x (the issue's target: within 1.2x from 2 to 20 minutes).

    python benchmarks/bench_scoring_memory.py                         # 2 and 20 minutes
    python benchmarks/bench_scoring_memory.py --minutes 1,4 --dir /tmp/scoring

The recordings are kept in ``--dir`` and reused when present (writing 20 minutes takes about a
minute). Prints a markdown table and the command that produced it.
"""

from __future__ import annotations

import argparse
import os
import platform
import shlex
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

RATE_HZ = 500
HORIZON = 500
METHODS = ("ekf", "ukf", "gru")
WITH_COVARIANCE = ("ekf", "ukf")


def write_recording(path: Path, minutes: float, seed: int = 0) -> tuple[int, int]:
    """A synthetic recording of ``minutes`` at RATE_HZ; (trajectories, messages)."""
    from neural_estimator.bags.dataset import arrays_to_bag
    from neural_estimator.scenarios import make_scenario

    scen = make_scenario("bearings")
    n = max(1, int(round(minutes * 60 * RATE_HZ / HORIZON)))
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, HORIZON, scen.dx))
    y = rng.normal(size=(n, HORIZON, scen.dy))
    est = {m: x + 0.1 * rng.normal(size=x.shape) for m in METHODS}
    cov = {m: np.broadcast_to(np.eye(scen.dx) * 0.01, (n, HORIZON, scen.dx, scen.dx)) for m in WITH_COVARIANCE}
    tmp = path.with_name(path.name + ".partial.mcap")
    arrays_to_bag(tmp, scen, x, y, estimates=est, covariances=cov, overwrite=True)
    tmp.replace(path)
    return n, n * HORIZON * (2 + len(METHODS) + len(WITH_COVARIANCE))


SCORERS = {
    "evaluator analysis": [
        sys.executable,
        "-c",
        "import sys; from neural_estimator.evaluation.bag_report import evaluate_bag; "
        "print(evaluate_bag(sys.argv[1]).summary())",
    ],
    "metrics": [sys.executable, "-m", "neural_estimator.cli", "metrics"],
}


def peak_of(cmd: list[str]) -> tuple[float, float]:
    """(peak RSS in MiB, wall seconds) of one child process; its output is discarded."""
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    err = proc.stderr.read().decode(errors="replace") if proc.stderr else ""
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"{shlex.join(cmd)} failed:\n{err}")
    return usage.ru_maxrss / 1024, wall  # Linux: KiB


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", default="2,20", help="comma-separated recording lengths (default 2,20)")
    ap.add_argument("--dir", default="/tmp/bench_scoring_memory", help="where the recordings are kept")
    args = ap.parse_args(argv)
    lengths = [float(m) for m in args.minutes.split(",") if m.strip()]
    out = Path(args.dir)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for minutes in lengths:
        bag = out / f"run-{minutes:g}min.mcap"
        n = max(1, int(round(minutes * 60 * RATE_HZ / HORIZON)))
        messages = n * HORIZON * (2 + len(METHODS) + len(WITH_COVARIANCE))
        if not bag.exists():
            t0 = time.perf_counter()
            n, messages = write_recording(bag, minutes)
            print(f"wrote {bag} ({messages:,} messages) in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
        for name, cmd in SCORERS.items():
            peak, wall = peak_of([*cmd, str(bag)])
            rows.append((minutes, n, messages, bag.stat().st_size / 2**20, name, peak, wall))
            print(f"{minutes:g} min, {name}: {peak:.0f} MiB peak, {wall:.1f} s", file=sys.stderr, flush=True)
    first = {name: peak for m, _, _, _, name, peak, _ in rows if m == lengths[0]}
    print(
        f"scoring memory against recording length ({platform.node()}, load average "
        f"{' '.join(f'{x:.1f}' for x in os.getloadavg())})\n"
    )
    print(
        "| minutes at 500 Hz | trajectories | messages | bag MiB | scorer | peak RSS MiB | x the shortest | seconds |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for minutes, n, messages, size, name, peak, wall in rows:
        print(
            f"| {minutes:g} | {n:,} | {messages:,} | {size:.0f} | {name} | {peak:.0f} | "
            f"{peak / first[name]:.2f} | {wall:.1f} |"
        )
    print(f"\n`{shlex.join(['python', 'benchmarks/bench_scoring_memory.py', *(argv or sys.argv[1:])])}`")
    return 0


if __name__ == "__main__":
    sys.exit(main())
