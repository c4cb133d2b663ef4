"""Resident memory of the estimator node, per backend: the design card's command, and with torch.

    .venv/bin/python benchmarks/bench_node_memory.py                       # lorenz96: gru, mamba
    .venv/bin/python benchmarks/bench_node_memory.py --methods mamba --scenario nlink

For each method, starts ``python -m neural_estimator.nodes.estimator_node --ros-args -p method:=M
-p scenario:=S`` (the default backend: ``auto``, step.onnx beside the shipped card on ONNX Runtime)
and the same with ``-p options:=[backend=torch]``, one at a time, in this machine's ROS_DOMAIN_ID
(or a random one in 100-199), waits until the node has built its estimator and warmed it up (its
start-up log line), lets it spin for ``--settle`` seconds and reads VmRSS and VmHWM from /proc, and
whether libtorch is mapped into the process. Prints a Markdown table (MiB).
"""

from __future__ import annotations

import argparse
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
READY = " on "  # the start-up line: "<method> on <scenario> (dx=...)"


def status_mib(pid: int) -> dict[str, float]:
    out = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            out[key] = int(value.split()[0]) / 1024
    return out


def measure(method: str, scenario: str, backend: str | None, settle: float, env: dict[str, str]) -> dict:
    args = ["--ros-args", "-p", f"method:={method}", "-p", f"scenario:={scenario}"]
    if backend:
        args += ["-p", f"options:=[backend={backend}]"]
    cmd = [sys.executable, "-m", "neural_estimator.nodes.estimator_node", *args]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env, cwd=ROOT)
    try:
        t0 = time.monotonic()
        lines = []
        while time.monotonic() - t0 < 180:
            line = proc.stdout.readline()
            if not line:
                raise RuntimeError(f"{method}: the node exited: {''.join(lines)[-1500:]}")
            lines.append(line)
            if f"{method}{READY}{scenario}" in line:
                break
        ready = time.monotonic() - t0
        time.sleep(settle)
        mem = status_mib(proc.pid)
        maps = Path(f"/proc/{proc.pid}/maps").read_text()
        mem["torch"] = "libtorch" in maps
        mem["onnxruntime"] = "onnxruntime" in maps
        mem["start_s"] = ready
        return mem
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="lorenz96")
    ap.add_argument("--methods", nargs="+", default=["gru", "mamba"])
    ap.add_argument("--settle", type=float, default=3.0, help="seconds of spinning before reading the memory")
    a = ap.parse_args(argv)
    env = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONUNBUFFERED="1")
    env.setdefault("ROS_DOMAIN_ID", str(random.SystemRandom().randint(100, 199)))
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    print(f"command: python benchmarks/bench_node_memory.py {' '.join(argv if argv is not None else sys.argv[1:])}")
    print(f"{a.scenario}; ROS_DOMAIN_ID {env['ROS_DOMAIN_ID']}; load average {os.getloadavg()[0]:.1f} at start\n")
    print("| method | backend | VmRSS MiB | VmHWM MiB | libtorch mapped | onnxruntime mapped | start-up s |")
    print("|---|---|---:|---:|---|---|---:|")
    for m in a.methods:
        for backend in (None, "torch"):
            r = measure(m, a.scenario, backend, a.settle, env)
            print(
                f"| {m} | {backend or 'default (auto)'} | {r['VmRSS']:.0f} | {r['VmHWM']:.0f} | "
                f"{'yes' if r['torch'] else 'no'} | {'yes' if r['onnxruntime'] else 'no'} | {r['start_s']:.1f} |",
                flush=True,
            )
    print(f"\nload average {os.getloadavg()[0]:.1f} at the end")
    return 0


if __name__ == "__main__":
    sys.exit(main())
