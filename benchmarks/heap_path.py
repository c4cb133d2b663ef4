"""Heap of the estimator node's per-message Python path over a long stream: does anything grow?

    .venv/bin/python benchmarks/heap_path.py --method ekf --messages 60000 --warmup 10000
    .venv/bin/python benchmarks/heap_path.py --method gru --messages 20000 --warmup 5000

Runs what the estimator node does with each observation, without ROS: the fast decode
(``OnlineEstimator.feed``: identity, quarantine, the method's step), the estimate, covariance and
state encodings, the stats counters (a record per message, a diagnostics window and its health
every 500 messages), on a simulated ``bearings`` stream of trajectories of ``--horizon`` steps,
with tracemalloc tracing 6 frames. After ``--warmup`` estimates it takes a baseline snapshot
(:class:`neural_estimator.nodes.heap_trace.HeapTrace`, the node's own tool), and at the end it
prints the traced heap's growth since then, the sites that grew most, and the process's RSS at
both points. A leak in this path shows as growth proportional to the messages; what DDS and rclpy
hold is outside it (the soak's RSS slope covers the whole node: ``benchmarks/soak.py``).
"""

from __future__ import annotations

import argparse
import sys
import time
import tracemalloc
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def rss_mib() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def main(argv: list[str] | None = None) -> int:
    from neural_estimator.stream import messages as MSG
    from neural_estimator.data import simulate
    from neural_estimator.nodes.estimator_stats import EstimatorStats, health
    from neural_estimator.nodes.heap_trace import HeapTrace
    from neural_estimator.nodes.outputs import StateEncoder
    from neural_estimator.stream.online import OnlineEstimator
    from neural_estimator.methods.registry import make_estimator
    from neural_estimator.scenarios import make_scenario

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--method", default="ekf")
    ap.add_argument("--messages", type=int, default=60000, help="observations fed (default 60000)")
    ap.add_argument("--warmup", type=int, default=10000, help="estimates before the baseline (default 10000)")
    ap.add_argument("--horizon", type=int, default=1000, help="steps per trajectory (default 1000)")
    a = ap.parse_args(argv)
    if not 0 < a.warmup < a.messages:
        ap.error("need 0 < --warmup < --messages")
    scen = make_scenario("bearings")
    data = simulate(scen, 4, a.horizon, seed=0)  # trajectories reused: the stream's identities go on
    codec = MSG.VectorCodec(scen.name, MSG.observation_labels(scen))
    online = OnlineEstimator(make_estimator(a.method, scen), a.method, horizon=a.horizon)
    state = StateEncoder(scen.state_names)
    stats = EstimatorStats()
    tracemalloc.start(6)
    heap = HeapTrace(after=a.warmup)
    rss_warm = None
    t0 = time.perf_counter()
    for g in range(a.messages):
        n, k = divmod(g, a.horizon)
        raw = codec.encode(MSG.step_stamp_ns(10**18, g, MSG.dt_ns(scen.dt)), n, k, data.y[n % 4, k])
        for res in online.feed(raw, 0.0):
            if res.status == "estimated":
                state.encode(res.x_hat, res.P)
                stats.estimated += 1
                stats.missed += res.missed
        stats.record(1e-4)
        if g % 500 == 0:
            health(stats, stats.window(time.monotonic()), waiting=False, foreign=set())
        heap.tick(stats.estimated)
        if rss_warm is None and heap.baseline is not None:
            rss_warm = rss_mib()
    report = heap.report(stats.estimated, top=8)
    print(
        f"{a.method}: {a.messages} messages in {time.perf_counter() - t0:.0f} s (traced); "
        f"RSS {rss_warm:.1f} MiB at estimate {report['baseline_estimates']} -> {rss_mib():.1f} MiB at "
        f"{report['estimates']}; traced heap growth since the baseline {report['traced_growth_kib']} KiB"
    )
    for t in report["top"]:
        print(f"  {t['kib']:+.1f} KiB in {t['blocks']:+d} blocks: {t['where']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
