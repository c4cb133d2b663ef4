"""The estimator node's per-message callback beside the bare ONNX Runtime step it wraps.

    .venv/bin/python benchmarks/bench_callback.py                      # lorenz96, gru mamba mamba2 gpt2
    .venv/bin/python benchmarks/bench_callback.py --scenario nlink --methods gru --core 0

For each shipped model of the scenario, served as the estimator node serves it by default (backend
``auto``: ``step.onnx`` beside the card, ONNX Runtime, no torch), in one process, in interleaved rounds
(so that a busy machine slows every column alike), wall clock per message:

- ``bare step``: ``OrtStep.run()`` on the bound buffers, the graph alone (the floor);
- ``estimator step``: ``Estimator.step(y, u)``: normalise, the graph, denormalise, checks;
- ``callback``: ``OnlineEstimator.feed(raw)`` on the observation message's CDR bytes, the node's
  subscription callback without DDS: decode and check the message, the stream rules, the estimator
  step, encode the estimate and covariance messages;
- ``message handling``: the callback with the estimator replaced by a stand-in that returns its last
  estimate and covariance at once: everything the callback does besides the estimator step;
- ``decode`` and ``encode``: the message codec's parts of the callback alone.

The callback is more than the estimator step plus the message handling: between two graph runs the
callback's Python touches other memory, so the graph's weights are partly evicted from the core's
caches, which a tight loop of bare steps keeps warm (on a shared, loaded machine, more so).

p50 and p99 in microseconds and the ratios callback / bare step and estimator step / bare step (p50).
The load average is printed before and after: on a shared machine, compare the columns of one run only.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def pct(samples: list[float]) -> tuple[float, float]:
    a = np.asarray(samples) * 1e6
    return float(np.percentile(a, 50)), float(np.percentile(a, 99))


class _StandIn:
    """An estimator that returns the last estimate (and covariance) of ``est`` without computing."""

    def __init__(self, est, y, u) -> None:
        est.reset(1)
        self.x = est.step(y, u).copy()
        self.covariance, self.diverged = est.covariance, est.diverged
        self.scenario, self.has_covariance = est.scenario, est.has_covariance

    def reset(self, batch: int = 1) -> None:
        pass

    def step(self, y, u_prev=None):
        return self.x


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="lorenz96")
    ap.add_argument("--methods", nargs="+", default=["gru", "mamba", "mamba2", "gpt2"])
    ap.add_argument("--steps", type=int, default=3000, help="measured messages per column")
    ap.add_argument("--rounds", type=int, default=10, help="interleaved rounds (messages split among them)")
    ap.add_argument("--core", type=int, default=-1, help="pin to this core (-1: no pinning)")
    a = ap.parse_args(argv)
    if a.core >= 0:
        os.sched_setaffinity(0, {a.core})
    from neural_estimator.stream import messages as MSG
    from neural_estimator.data import simulate
    from neural_estimator.stream.online import OnlineEstimator
    from neural_estimator.methods.registry import make_estimator, per_message_options
    from neural_estimator.scenarios import make_scenario

    load0 = os.getloadavg()[0]
    scen = make_scenario(a.scenario)
    T = 500
    data = simulate(scen, 1, T, 0)
    U = np.vstack([np.zeros((1, scen.du)), data.u[0, :-1]])
    print(f"command: python benchmarks/bench_callback.py {' '.join(argv if argv is not None else sys.argv[1:])}")
    print(f"{a.scenario}, {os.cpu_count()} cores; load average {load0:.1f} at start")
    print()
    heads = ["bare step", "estimator step", "callback", "message handling", "decode", "encode"]
    print(
        "| model | backend | "
        + " | ".join(f"{h} p50 / p99" for h in heads)
        + " | callback / bare step | estimator step / bare step |"
    )
    print("|---|---|" + "---:|" * len(heads) + "---:|---:|")
    per_round = max(1, a.steps // a.rounds)
    for m in a.methods:
        est = make_estimator(m, scen, **per_message_options(m, {}))
        backend = getattr(est, "backend", "torch")
        if backend != "onnxruntime" or not hasattr(est, "ort"):
            print(f"| {m} | {backend} | not served by ONNX Runtime (no step.onnx beside the card) |")
            continue
        online = OnlineEstimator(est, m)
        handling = OnlineEstimator(_StandIn(est, data.y[0, :1], U[:1]), m)
        codec = MSG.VectorCodec(m, MSG.state_labels(scen))
        x_out = np.zeros(scen.dx)
        # a long stream of consecutive messages: every one is the successor of the last (no quarantine)
        n_msgs = (a.rounds + 1) * per_round + 1
        raws = [
            MSG.encode_observation(scen, 1_000_000 * (k + 1), k // T, k % T, data.y[0, k % T], U[k % T])
            for k in range(n_msgs)
        ]
        online.feed(raws[0], now=0.0)
        handling.feed(raws[0], now=0.0)
        times: dict[str, list[float]] = {h: [] for h in heads}
        est_ort = est.ort
        k = 1
        for r in range(a.rounds + 1):  # round 0 warms up
            keep = r > 0
            for h in heads:
                out = times[h]
                for i in range(per_round):
                    j = (k + i) % T
                    if h == "bare step":
                        t0 = time.perf_counter()
                        est_ort.run()
                        dt = time.perf_counter() - t0
                    elif h == "estimator step":
                        y, u = data.y[0, j : j + 1], U[j : j + 1]
                        t0 = time.perf_counter()
                        est.step(y, u)
                        dt = time.perf_counter() - t0
                    elif h == "callback":
                        raw = raws[k + i]
                        t0 = time.perf_counter()
                        online.feed(raw, now=0.0)
                        dt = time.perf_counter() - t0
                    elif h == "message handling":
                        raw = raws[k + i]
                        t0 = time.perf_counter()
                        handling.feed(raw, now=0.0)
                        dt = time.perf_counter() - t0
                    elif h == "decode":
                        raw = raws[k + i]
                        t0 = time.perf_counter()
                        online._decode(raw)
                        dt = time.perf_counter() - t0
                    else:
                        t0 = time.perf_counter()
                        codec.encode(k + i, 0, j, x_out)
                        dt = time.perf_counter() - t0
                    if keep:
                        out.append(dt)
            k += per_round
        p = {h: pct(v) for h, v in times.items()}
        cells = " | ".join(f"{p[h][0]:.1f} / {p[h][1]:.1f}" for h in heads)
        print(
            f"| {m} | {backend} | {cells} | {p['callback'][0] / p['bare step'][0]:.2f}x | "
            f"{p['estimator step'][0] / p['bare step'][0]:.2f}x |",
            flush=True,
        )
    print(f"\nload average {os.getloadavg()[0]:.1f} at the end (microseconds, wall clock)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
