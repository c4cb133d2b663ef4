"""ONNX Runtime's fused contrib operators against the standard-opset pieces the attention step forms use.

    python benchmarks/bench_ort_contrib.py [--scenario lorenz96] [--runs 2000] [--rounds 7]

Two parts of GPT-2's and Filterformer's batch-1 step (``models/onnx_forms.py``), each built as a
small graph at the shipped model's sizes and served both ways by one-thread ONNX Runtime sessions,
interleaved in one process:

- **Attention of one query over the window**: the form's operators (the query's heads against the
  (nh, W, hs) key cache: a product with the keys transposed and scaled, the ALiBi bias added, the
  softmax, the product with the values, the heads joined: ONNX Runtime fuses the transpose and the
  scale into one FusedMatMul), against com.microsoft ``MultiHeadAttention`` given the same caches in
  its (1, nh, W, hs) layout ("BNSH"), then in its (1, W, D) one ("BSD"), and the bias as
  ``attention_bias``.
- **The residual connection and the LayerNorm after it**, a chain of ``--chain`` of them: a Gemm with
  its bias, an Add of the stream and a LayerNormalization, against a MatMul and com.microsoft
  ``SkipLayerNormalization`` (the bias, the stream and the norm in one operator; output 3 the new
  stream).

Prints the p50 per ``session.run`` (µs) of each, their ratio (standard / contrib: above 1 the contrib
operator is faster), and the largest difference between their outputs.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from neural_estimator.serving.card import default_checkpoint  # noqa: E402


def _session(nodes: list, inputs: list, outputs: list, initializers: list):
    import onnxruntime as ort
    from onnx import helper

    graph = helper.make_graph(nodes, "bench", inputs, outputs, initializer=initializers)
    opsets = [helper.make_opsetid("", 17), helper.make_opsetid("com.microsoft", 1)]
    model = helper.make_model(graph, opset_imports=opsets)
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = opts.inter_op_num_threads = 1
    opts.log_severity_level = 3
    return ort.InferenceSession(model.SerializeToString(), opts, providers=["CPUExecutionProvider"])


def _value(name: str, shape: list[int]):
    from onnx import TensorProto, helper

    return helper.make_tensor_value_info(name, TensorProto.FLOAT, shape)


def attention_pair(nh: int, W: int, hs: int, rng: np.random.Generator, layout: str = "BNSH"):
    """(standard session, its feeds), (MultiHeadAttention session, its feeds), both -> (1, D).
    ``layout``: the caches as MultiHeadAttention gets them, "BNSH" (1, nh, W, hs) or "BSD" (1, W, D),
    the other layout it accepts (it then moves each cache into heads itself, every call)."""
    from onnx import helper, numpy_helper

    D = nh * hs
    scale = numpy_helper.from_array(np.array(1.0 / np.sqrt(hs), dtype=np.float32), "scale")
    row = numpy_helper.from_array(np.array([1, D], dtype=np.int64), "row")
    std = _session(
        [
            helper.make_node("Transpose", ["k"], ["kt"], perm=[0, 2, 1]),
            helper.make_node("MatMul", ["q", "kt"], ["qk"]),
            helper.make_node("Mul", ["qk", "scale"], ["scaled"]),
            helper.make_node("Add", ["scaled", "bias"], ["scores"]),
            helper.make_node("Softmax", ["scores"], ["p"], axis=-1),
            helper.make_node("MatMul", ["p", "v"], ["heads"]),
            helper.make_node("Reshape", ["heads", "row"], ["y"]),
        ],
        [_value("q", [nh, 1, hs]), _value("k", [nh, W, hs]), _value("v", [nh, W, hs]), _value("bias", [nh, 1, W])],
        [_value("y", [1, D])],
        [scale, row],
    )
    query = numpy_helper.from_array(np.array([1, 1, D], dtype=np.int64), "query")
    mha = _session(
        [
            helper.make_node("Reshape", ["q", "query"], ["q3"]),
            helper.make_node(
                "MultiHeadAttention", ["q3", "k", "v", "", "", "bias"], ["y3"], domain="com.microsoft", num_heads=nh
            ),
            helper.make_node("Reshape", ["y3", "row"], ["y"]),
        ],
        [_value("q", [nh, 1, hs]), *(_value(n, [1, nh, W, hs] if layout == "BNSH" else [1, W, D]) for n in "kv")]
        + [_value("bias", [1, nh, 1, W])],
        [_value("y", [1, D])],
        [query, row],
    )
    q = rng.standard_normal((nh, 1, hs)).astype(np.float32)
    k, v = (rng.standard_normal((nh, W, hs)).astype(np.float32) for _ in range(2))
    ages = np.arange(W, dtype=np.float32)[::-1].copy()
    bias = (-np.linspace(0.05, 0.5, nh, dtype=np.float32)[:, None, None] * ages).astype(np.float32)
    if layout == "BNSH":
        caches = {"k": k[None], "v": v[None]}
    else:  # head h's hs channels side by side in each slot's row
        caches = {"k": k.transpose(1, 0, 2).reshape(1, W, D).copy(), "v": v.transpose(1, 0, 2).reshape(1, W, D).copy()}
    return (std, {"q": q, "k": k, "v": v, "bias": bias}), (mha, {"q": q, **caches, "bias": bias[None]})


def residual_pair(D: int, chain: int, rng: np.random.Generator):
    """(Gemm + Add + LayerNormalization) x chain, (MatMul + SkipLayerNormalization) x chain: (1, D)."""
    from onnx import helper, numpy_helper

    inits, std_nodes, skip_nodes = [], [], []
    for i in range(chain):
        w = (rng.standard_normal((D, D)) / np.sqrt(D)).astype(np.float32)
        inits += [
            numpy_helper.from_array(w, f"w{i}"),
            numpy_helper.from_array(rng.standard_normal(D).astype(np.float32), f"b{i}"),
            numpy_helper.from_array((1.0 + 0.1 * rng.standard_normal(D)).astype(np.float32), f"g{i}"),
            numpy_helper.from_array((0.1 * rng.standard_normal(D)).astype(np.float32), f"beta{i}"),
        ]
        x, h = ("x", "h") if i == 0 else (f"x{i - 1}", f"h{i - 1}")
        std_nodes += [
            helper.make_node("Gemm", [x, f"w{i}", f"b{i}"], [f"p{i}"]),
            helper.make_node("Add", [h, f"p{i}"], [f"h{i}"]),
            helper.make_node("LayerNormalization", [f"h{i}", f"g{i}", f"beta{i}"], [f"x{i}"], axis=-1),
        ]
        skip_nodes += [
            helper.make_node("MatMul", [x, f"w{i}"], [f"p{i}"]),
            helper.make_node(
                "SkipLayerNormalization",
                [f"p{i}", h, f"g{i}", f"beta{i}", f"b{i}"],
                [f"x{i}", "", "", f"h{i}"],
                domain="com.microsoft",
            ),
        ]
    io = [_value("x", [1, D]), _value("h", [1, D])], [_value(f"x{chain - 1}", [1, D])]
    feeds = {"x": rng.standard_normal((1, D)).astype(np.float32), "h": rng.standard_normal((1, D)).astype(np.float32)}
    return (_session(std_nodes, *io, inits), feeds), (_session(skip_nodes, *io, inits), feeds)


def compare(name: str, pair, runs: int, rounds: int) -> str:
    (a, fa), (b, fb) = pair
    diff = float(np.abs(a.run(None, fa)[0] - b.run(None, fb)[0]).max())
    times: tuple[list[float], list[float]] = ([], [])
    for _ in range(rounds):
        for (sess, feeds), acc in zip(pair, times):
            t0 = time.perf_counter()
            for _ in range(runs):
                sess.run(None, feeds)
            acc.append((time.perf_counter() - t0) / runs * 1e6)
    ta, tb = (float(np.median(t)) for t in times)
    return f"| {name} | {ta:.1f} | {tb:.1f} | {ta / tb:.2f}x | {diff:.1e} |"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="lorenz96")
    ap.add_argument("--runs", type=int, default=2000, help="session runs per round and side")
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--chain", type=int, default=4, help="residual + LayerNorm pairs in a row (GPT-2's 2 layers: 4)")
    args = ap.parse_args(argv)
    import onnxruntime as ort

    rng = np.random.default_rng(0)
    flags = f"--scenario {args.scenario} --runs {args.runs} --rounds {args.rounds}"
    print(f"command: python benchmarks/bench_ort_contrib.py {flags}")
    print(f"onnxruntime {ort.__version__}, 1 thread; p50 µs per session.run, interleaved rounds\n")
    print("| graph | standard opset | contrib operator | standard / contrib | max difference |")
    print("|---|---:|---:|---:|---:|")
    for method, window_key, width_key in (("gpt2", "decode_chunk", "n_embd"), ("filterformer", "window", "d_model")):
        card = json.loads((default_checkpoint(args.scenario, method) / "card.json").read_text())
        cfg = card["architecture"]["config"]
        nh, W, D = int(cfg["n_head"]), int(cfg[window_key]), int(cfg[width_key])
        for layout in ("BNSH", "BSD"):
            label = f"{method} attention, nh {nh}, W {W}, hs {D // nh}: MultiHeadAttention, caches {layout}"
            print(compare(label, attention_pair(nh, W, D // nh, rng, layout), args.runs, args.rounds), flush=True)
        label = f"{method} {args.chain} x (residual + LayerNorm), D {D}: SkipLayerNormalization"
        print(compare(label, residual_pair(D, args.chain, rng), args.runs, args.rounds), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
