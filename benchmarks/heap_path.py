"""Heap of the estimator node's per-message Python path over a long stream: does anything grow?

    .venv/bin/python benchmarks/heap_path.py --method ekf --messages 60000 --warmup 10000
    .venv/bin/python benchmarks/heap_path.py --method gru --messages 20000 --warmup 5000
    .venv/bin/python benchmarks/heap_path.py --method mamba --rss-only --messages 300000 --warmup 50000

Runs what the estimator node does with each observation, without ROS: the fast decode
(``OnlineEstimator.feed``: identity, quarantine, the method's step), the estimate, covariance and
state encodings, the stats counters (a record per message, a diagnostics window and its health
every 500 messages), on a simulated ``bearings`` stream of trajectories of ``--horizon`` steps,
with tracemalloc tracing 6 frames. After ``--warmup`` estimates it takes a baseline snapshot
(:class:`neural_estimator.nodes.heap_trace.HeapTrace`, the node's own tool), and at the end it
prints the traced heap's growth since then, the sites that grew most, and the process's RSS at
both points. A leak in this path shows as growth proportional to the messages; what DDS and rclpy
hold is outside it (the soak's RSS slope covers the whole node: ``benchmarks/soak.py``).

With ``--rss-only`` nothing is traced (the path runs at its own speed, so a long stream is cheap
for every method): the process's heap is set up as a node's (glibc's thresholds pinned, a trim
every ``--trim-every`` messages, 10 s at 500 Hz), its RSS is sampled every 5,000 messages, and
the least-squares slope after ``--warmup`` is printed in KiB per 100,000 messages and in MiB/s at
500 Hz: the method's share of a node's slope. Neural methods serve with ``--backend`` (the nodes'
default ``auto``: ONNX Runtime where the model ships a ``step.onnx``).
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
    from neural_estimator.nodes.estimator_stats import EstimatorStats
    from neural_estimator.nodes.heap_trace import HeapTrace
    from neural_estimator.nodes.outputs import StateEncoder
    from neural_estimator.stream.online import OnlineEstimator
    from neural_estimator.methods.registry import make_estimator
    from neural_estimator.scenarios import make_scenario
    from neural_estimator.methods import table

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--method", default="ekf")
    ap.add_argument("--messages", type=int, default=60000, help="observations fed (default 60000)")
    ap.add_argument("--warmup", type=int, default=10000, help="estimates before the baseline (default 10000)")
    ap.add_argument("--horizon", type=int, default=1000, help="steps per trajectory (default 1000)")
    ap.add_argument("--rss-only", action="store_true", help="no tracing: the RSS slope of a long stream")
    ap.add_argument("--trim-every", type=int, default=5000, help="messages between heap trims (--rss-only)")
    ap.add_argument("--backend", default="auto", help="serving backend of a neural method (default auto)")
    a = ap.parse_args(argv)
    if not 0 < a.warmup < a.messages:
        ap.error("need 0 < --warmup < --messages")
    scen = make_scenario("bearings")
    data = simulate(scen, 4, a.horizon, seed=0)  # trajectories reused: the stream's identities go on
    codec = MSG.VectorCodec(scen.name, MSG.observation_labels(scen))
    options = {"backend": a.backend} if table.spec(a.method).trainable else {}
    online = OnlineEstimator(make_estimator(a.method, scen, **options), a.method, horizon=a.horizon)
    state = StateEncoder(scen.state_names)
    stats = EstimatorStats()
    if a.rss_only:
        return rss_slope(a, scen, data, codec, online, state, stats)
    tracemalloc.start(6)
    heap = HeapTrace(after=a.warmup)
    rss_warm = None
    t0 = time.perf_counter()
    for _ in node_path(a, scen, data, codec, online, state, stats):
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


def node_path(a, scen, data, codec, online, state, stats):
    """The node's per-message path over ``a.messages`` observations; yields each message's index
    once its estimate is encoded and counted (a diagnostics window and its health every 500)."""
    from neural_estimator.nodes.estimator_stats import health
    from neural_estimator.stream import messages as MSG

    period_ns = MSG.dt_ns(scen.dt)
    for g in range(a.messages):
        n, k = divmod(g, a.horizon)
        raw = codec.encode(MSG.step_stamp_ns(10**18, g, period_ns), n, k, data.y[n % 4, k])
        for res in online.feed(raw, 0.0):
            if res.status == "estimated":
                state.encode(res.x_hat, res.P)
                stats.estimated += 1
                stats.missed += res.missed
        stats.record(1e-4)
        if g % 500 == 0:
            health(stats, stats.window(time.monotonic()), waiting=False, foreign=set())
        yield g


def rss_slope(a, scen, data, codec, online, state, stats) -> int:
    """The ``--rss-only`` run: the node's heap settings, RSS every 5,000 messages, its slope after the warm-up."""
    import numpy as np

    from neural_estimator.nodes.heap_trace import HeapTrim, pin_malloc_thresholds

    pin_malloc_thresholds()
    trim = HeapTrim()
    samples = []
    t0 = time.perf_counter()
    for g in node_path(a, scen, data, codec, online, state, stats):
        if g % a.trim_every == 0:
            trim()
        if g % 5000 == 0 and g >= a.warmup:
            samples.append((g, rss_mib()))
    seconds = time.perf_counter() - t0
    g, mib = np.array(samples).T
    slope = np.polyfit(g, mib, 1)[0]  # MiB per message
    print(
        f"{a.method}: {a.messages} messages in {seconds:.0f} s ({1e6 * seconds / a.messages:.0f} us each); "
        f"RSS {mib[0]:.1f} MiB at message {int(g[0])} -> {mib[-1]:.1f} at {int(g[-1])}, max {mib.max():.1f}; "
        f"slope {1024 * 1e5 * slope:+.1f} KiB per 100,000 messages = {500 * slope:+.5f} MiB/s at 500 Hz "
        f"({len(samples)} samples; {trim.calls} trims)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
