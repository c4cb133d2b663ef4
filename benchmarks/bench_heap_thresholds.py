"""What pinning glibc's thresholds costs the estimator node's per-message callback.

    .venv/bin/python benchmarks/bench_heap_thresholds.py                          # ekf ukf pf, bearings
    .venv/bin/python benchmarks/bench_heap_thresholds.py --scenario lorenz96 --methods pf enkf ukf

Every node pins glibc's mmap and trim thresholds at 128 KiB (``nodes/heap_trace.py``
``pin_malloc_thresholds``, called by ``nodes.common.run_node`` unless ``NEURAL_ESTIMATOR_HEAP_TRIM=0``):
a block of 128 KiB or more is then mapped on its own and unmapped when freed, where glibc's
default, once the process has freed a large block, serves it from the heap and keeps it. A method
whose per-message temporaries reach that size pays a map, an unmap and the page faults for each.
This measures it: for each method, fresh processes alternately with the thresholds pinned (as in
a node) and with glibc's defaults, each building the estimator and feeding ``--messages``
observations through ``OnlineEstimator.feed`` (the node's callback without DDS) after a warm-up;
per process the p50 and p99 wall time per message, the minor page faults per message and the
growth of its anonymous memory over the measured messages. Medians over ``--rounds`` processes
per setting; the load average is printed before and after (compare the two settings of one run).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def anon_mib() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("RssAnon:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def child(method: str, scenario: str, messages: int, warmup: int, pin: bool) -> dict:
    """One process: build, warm up, time ``messages`` callbacks (run as ``--child``)."""
    from neural_estimator.nodes.heap_trace import pin_malloc_thresholds

    pinned = pin_malloc_thresholds() if pin else False  # before the build, as run_node does
    from neural_estimator.data import simulate
    from neural_estimator.methods.registry import make_estimator
    from neural_estimator.scenarios import make_scenario
    from neural_estimator.stream import messages as MSG
    from neural_estimator.stream.online import OnlineEstimator

    horizon = 1000
    scen = make_scenario(scenario)
    data = simulate(scen, 2, horizon, seed=0)
    codec = MSG.VectorCodec(scen.name, MSG.observation_labels(scen))
    online = OnlineEstimator(make_estimator(method, scen), method, horizon=horizon)
    dt_ns = MSG.dt_ns(scen.dt)
    zeros = np.zeros(scen.du)

    def raw(g: int) -> bytes:  # as the simulator node publishes it: y and the previous control
        n, k = divmod(g, horizon)
        u_prev = data.u[n % 2, k - 1] if k else zeros
        return codec.encode(MSG.step_stamp_ns(10**18, g, dt_ns), n, k, np.concatenate([data.y[n % 2, k], u_prev]))

    for g in range(warmup):
        online.feed(raw(g), 0.0)
    faults0, anon0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt, anon_mib()
    times = np.empty(messages)
    for i in range(messages):
        r = raw(warmup + i)
        t0 = time.perf_counter()
        online.feed(r, 0.0)
        times[i] = time.perf_counter() - t0
    return {
        "pinned": pinned,
        "p50_us": float(np.percentile(times, 50) * 1e6),
        "p99_us": float(np.percentile(times, 99) * 1e6),
        "faults_per_message": (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults0) / messages,
        "anon_growth_mib": anon_mib() - anon0,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", default="bearings")
    ap.add_argument("--methods", nargs="+", default=["ekf", "ukf", "pf"])
    ap.add_argument("--messages", type=int, default=3000, help="measured messages per process")
    ap.add_argument("--warmup", type=int, default=300)
    ap.add_argument("--rounds", type=int, default=3, help="processes per method and setting, alternated")
    ap.add_argument("--child", choices=("pin", "default"), help=argparse.SUPPRESS)
    ap.add_argument("--method", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.child:
        print(json.dumps(child(a.method, a.scenario, a.messages, a.warmup, a.child == "pin")))
        return 0
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(ROOT))
    env = {k: v for k, v in env.items() if not k.startswith("MALLOC_")}  # glibc's own variables would win
    print(f"# bench_heap_thresholds: {a.scenario}, {a.messages} messages per process, {a.rounds} rounds")
    print(f"# load average at start: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    print("| method | thresholds | p50 µs | p99 µs | page faults / message | anon growth MiB |")
    print("|---|---|---|---|---|---|")
    for method in a.methods:
        runs: dict[str, list[dict]] = {"pin": [], "default": []}
        for _ in range(a.rounds):
            for mode in ("pin", "default"):
                cmd = [sys.executable, __file__, "--child", mode, "--method", method, "--scenario", a.scenario]
                cmd += ["--messages", str(a.messages), "--warmup", str(a.warmup)]
                out = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=1800)
                if out.returncode != 0:
                    print(f"| {method} | {mode} | failed: {out.stderr.strip().splitlines()[-1:]} |")
                    break
                runs[mode].append(json.loads(out.stdout.strip().splitlines()[-1]))
        for mode, label in (("pin", "pinned at 128 KiB (the nodes)"), ("default", "glibc's defaults")):
            rs = runs[mode]
            if not rs:
                continue
            med = {k: float(np.median([r[k] for r in rs])) for k in rs[0] if k != "pinned"}
            print(
                f"| {method} | {label} | {med['p50_us']:.1f} | {med['p99_us']:.1f} | "
                f"{med['faults_per_message']:.2f} | {med['anon_growth_mib']:+.2f} |"
            )
    print(f"# load average at end: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
