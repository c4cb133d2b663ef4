"""The attention models' ONNX step with its KV caches updated in place against double-buffered.

    python benchmarks/bench_inplace_caches.py [--scenario lorenz96] [--steps 2000] [--rounds 6]

For GPT-2 and Filterformer: the shipped ``step.onnx`` served by ``OrtStep`` as it is (the caches
listed in the graph's ``inplace_states``: one buffer each, read and written by the same run) and the
same graph with that list removed (every state double-buffered: each ScatterND copies its cache
before writing one row). Interleaved rounds in one process, one ONNX Runtime thread; prints the
p50 per ``OrtStep.step`` (µs) of each and their ratio, and checks that both give the same
estimates to the bit.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from neural_estimator.serving.card import default_checkpoint  # noqa: E402
from neural_estimator.serving.onnx_runtime import ONNX_FILE, OrtStep  # noqa: E402


def without_inplace(path: Path) -> bytes:
    """The graph at ``path`` with its ``inplace_states`` metadata removed."""
    import onnx

    model = onnx.load(str(path))
    kept = [p for p in model.metadata_props if p.key != "inplace_states"]
    del model.metadata_props[:]
    model.metadata_props.extend(kept)
    return model.SerializeToString()


def timed(step: OrtStep, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Seconds per step over the rows of ``z``, and the estimates."""
    out = np.empty((len(z), step.outputs["mean"].shape[1]), dtype=np.float32)
    took = np.empty(len(z))
    for k, row in enumerate(z):
        t0 = time.perf_counter()
        out[k] = step.step(row[None])
        took[k] = time.perf_counter() - t0
    return took, out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scenario", default="lorenz96")
    p.add_argument("--steps", type=int, default=2000, help="steps per round and variant")
    p.add_argument("--rounds", type=int, default=6)
    a = p.parse_args(argv)
    print(f"command: python benchmarks/bench_inplace_caches.py {' '.join(argv or sys.argv[1:])}")
    print(f"{a.scenario}, 1 ONNX Runtime thread, {a.rounds} interleaved rounds x {a.steps} steps; p50 µs per step")
    print("| model | caches in place | double-buffered | double / in place | same estimates |")
    print("|---|---:|---:|---:|---|")
    for method in ("gpt2", "filterformer"):
        graph = default_checkpoint(a.scenario, method) / ONNX_FILE
        shared, double = OrtStep(graph), OrtStep(without_inplace(graph))
        if not shared.inplace or double.inplace:
            raise SystemExit(f"{graph}: no inplace_states to compare (re-export it: scripts/export_onnx.py --beside)")
        z = np.random.default_rng(0).standard_normal((a.steps, shared.d_in)).astype(np.float32)
        times: dict[str, list[np.ndarray]] = {"in place": [], "double": []}
        same = True
        for _ in range(a.rounds):
            shared.reset()
            double.reset()
            t_in, x_in = timed(shared, z)
            t_db, x_db = timed(double, z)
            times["in place"].append(t_in)
            times["double"].append(t_db)
            same = same and np.array_equal(x_in, x_db)
        p50 = {k: float(np.median(np.concatenate(v))) * 1e6 for k, v in times.items()}
        ratio = p50["double"] / p50["in place"]
        print(f"| {method} | {p50['in place']:.1f} | {p50['double']:.1f} | {ratio:.2f}x | {same} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
