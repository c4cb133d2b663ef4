"""Sequence mode at batch 1: trajectories per second of each architecture against the GRU's.

The paper's runtime table runs each network over whole sequences; there the attention models are
6.5x (GPT-2) and 10x (Filterformer) the GRU's throughput. This benchmark times ``model(x)`` on one
sequence of T = 500 steps at Lorenz 96 size (d_in = d_out = 40, the paper's hyperparameters, one
thread, eval mode, inference mode), rounds interleaved so that a busy machine slows every row
alike, and prints the median per call and the ratio to the GRU. The attention models run twice:
with the ALiBi/window bias built afresh in every layer on every call (``--no-cache`` rows, the
code before :func:`neural_estimator.models.layers.window_bias` cached it) and cached. The
results must be bit-identical; the script says whether they are.

Last, the served estimator: ``NeuralEstimator.run`` (normalising, chunking, denormalising) against
the bare ``model.forward`` of the shipped Lorenz 96 Mamba-2, with and without its covariance head.

Run: python benchmarks/bench_sequence.py [--repeats 15] [--rounds 3]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import numpy as np
import torch

from neural_estimator.models import ARCHITECTURES, SystemDims, build_model
from neural_estimator.models import layers

D = 40  # Lorenz 96


def median_seconds(fn, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def architectures(args) -> None:
    torch.manual_seed(0)
    x = torch.randn(1, args.seq_len, D)
    models = {a: build_model(a, SystemDims(dx=D, dy=D)).eval() for a in ARCHITECTURES}
    uncached = layers._make_window_bias
    cached = layers.window_bias
    rows: dict[tuple[str, str], list[float]] = {}
    with torch.inference_mode():
        for _ in range(args.rounds):
            for mode in ("no-cache", "cached"):
                layers.window_bias = cached if mode == "cached" else uncached
                for name, model in models.items():
                    if mode == "no-cache" and name not in ("gpt2", "filterformer"):
                        continue
                    rows.setdefault((name, mode), []).append(median_seconds(lambda m=model: m(x), args.repeats))
        layers.window_bias = uncached
        before = {n: models[n](x) for n in ("gpt2", "filterformer")}
        layers.window_bias = cached
        identical = all(torch.equal(before[n], models[n](x)) for n in before)
    gru = min(rows[("gru", "cached")])
    print(f"sequence mode, B = 1, T = {args.seq_len}, d = {D}, 1 thread, best of {args.rounds} rounds")
    print("| model | bias | ms per trajectory | trajectories/s vs GRU |")
    print("|---|---|---:|---:|")
    for (name, mode), t in rows.items():
        bias = mode if name in ("gpt2", "filterformer") else "-"
        print(f"| {name} | {bias} | {min(t) * 1e3:.2f} | {gru / min(t):.2f}x |")
    print(f"cached and uncached outputs bit-identical: {identical}")


def served_run(args) -> None:
    from neural_estimator.data import simulate
    from neural_estimator.methods.registry import make_estimator
    from neural_estimator.scenarios import make_scenario

    scenario = make_scenario("lorenz96")
    data = simulate(scenario, 1, args.seq_len, seed=1)
    print("\nserved Lorenz 96 Mamba-2: NeuralEstimator.run against model.forward (B = 1)")
    print("| covariance head | forward (ms) | forward_with_cov (ms) | run (ms) | run / forward | run / its forward |")
    print("|---|---:|---:|---:|---:|---:|")
    for cov in (False, True):
        est = make_estimator("mamba2", scenario, covariance=cov)
        z, _ = est.normalizer.normalize_inputs(data.y, np.zeros((*data.y.shape[:2], 0)))
        z = torch.as_tensor(z, dtype=torch.float32)
        with torch.inference_mode():
            fwd = median_seconds(lambda: est.model(z), args.repeats)
            fwc = median_seconds(lambda: est.model.forward_with_cov(z), args.repeats) if cov else None
        run = median_seconds(lambda: est.run(data.y, data.u), args.repeats)
        own = fwc if cov else fwd
        fwc_text = f"{fwc * 1e3:.2f}" if fwc else "-"
        print(
            f"| {'yes' if cov else 'no'} | {fwd * 1e3:.2f} | {fwc_text} | {run * 1e3:.2f} | "
            f"{run / fwd:.2f}x | {run / own:.2f}x |"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seq-len", type=int, default=500)
    ap.add_argument("--repeats", type=int, default=15, help="timed calls per round (median taken)")
    ap.add_argument("--rounds", type=int, default=3, help="interleaved rounds (best taken)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    print(f"load average {os.getloadavg()[0]:.2f}")
    architectures(args)
    served_run(args)


if __name__ == "__main__":
    main()
