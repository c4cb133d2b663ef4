"""Batch-1 neural serving beside its limits: the node's step against ONNX Runtime and the GEMV bound.

    .venv/bin/python benchmarks/bench_serving.py                        # lorenz96 zoo, all six models
    .venv/bin/python benchmarks/bench_serving.py --scenario bearings --methods gru mamba --core 0
    .venv/bin/python benchmarks/bench_serving.py --scenario bearings --methods gru lstm --context card

For every shipped model of the scenario (the paper's sizes), in one process, in interleaved rounds
(so that a busy machine slows every column alike):

- ``torch step``: ``model.step`` on a float32 tensor (inference mode), the network alone;
- ``node step (torch)``: ``Estimator.step`` with numpy in and out, the live node's call, torch backend;
- ``ORT step``: the same step exported to ONNX (``models/onnx_step.py``) run by ONNX Runtime, one thread,
  through preallocated bound buffers (``run_with_iobinding``: the fastest call ONNX Runtime offers);
- ``ORT own step``: the model's own ``step`` traced as it is (what the export traced before Mamba,
  Mamba-2 and GPT-2 got their step forms, ``models/onnx_forms.py``), bound buffers too: the "before"
  of those three; for the other models it is the same graph as ``ORT step``;
- ``ORT run()``: the same graph through the plain ``session.run(None, feed)`` call (numpy in and out);
- ``node step (ORT)``: ``Estimator.step`` with ``backend=onnxruntime`` (its graph also normalises and
  denormalises, in float64);
- ``wrapper``: node step (ORT) minus ORT step, p50 (normalise, checks, denormalise, copies: everything
  the node's call adds to the network's step);
- ``GEMV limit``: 2 x parameters / the single-core float32 GEMV rate measured here (the time a step
  would take if it only streamed its weights once through the fastest matrix-vector product);
  ``ORT / limit`` is the ORT step over it;
- ``step limit``: the same, counting also the step's arithmetic that no weight does (:func:`state_flops`:
  the attention over the window's keys and values, the SSM state's decay, update and read-out, the
  conv's window), which the GEMV limit leaves out; ``ORT / step limit`` the ORT step over it;
- ``nodes``: the operators ONNX Runtime runs per step, after its graph optimisations (the graph it
  serves, then the model's own step traced), read back from the optimised model it writes.

``--context 0`` (the default) serves every model with an unbounded context (attention models: the
paper's window); ``--context card`` serves each as its card validated it, as the nodes do: a GRU
validated with a bounded context (the ballistic and bearings zoo GRUs: L = 100, K = 4 restarted
copies) steps its K copies as one batch of K rows, torch's ``BatchedCopies`` in the torch columns
(``torch step``: the copies' step with their restarts, no covariance head) and the copies' graph
in the ORT columns (``ORT step`` restarts the copies' rows in numpy, ``ORT run()`` leaves the
restarts out); its GEMV limit is then K times the model's.

p50 and p99 of the wall clock, microseconds. ``--core N`` pins the process to one core. The load
average is printed before and after: on a shared machine, compare the columns of one run only.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def gemv_rate(bursts: int = 200) -> float:
    """Single-thread float32 GEMV rate (FLOP/s): the fastest of many short bursts (a burst that the
    scheduler interrupted is slower, so the fastest one is the core's rate), matrix sizes 256-1024."""
    import torch

    best = 0.0
    for n in (256, 512, 1024):
        a, x = torch.randn(n, n), torch.randn(n)
        for _ in range(20):
            torch.mv(a, x)
        for _ in range(bursts):
            t0 = time.perf_counter()
            for _ in range(5):
                torch.mv(a, x)
            best = max(best, 2 * n * n * 5 / (time.perf_counter() - t0))
    return best


def state_flops(model) -> int:
    """Floating-point operations of one batch-1 step that act on the state, not on a weight (those are
    the 2 x parameters of the GEMV limit), read from the model's step form (``models/onnx_forms.py``):

    - attention over a window of W slots, per layer: q k_j and the sum of p_j v_j over the W slots, for
      every one of the D channels: 4 D W;
    - an SSM layer with state (N, E): the decay of every element, its product with the state, the
      input's outer product added, the read-out's multiply-adds: 5 N E (Mamba's decay exp(delta A) is
      per element: 6 N E); the causal conv's K-tap window over its C channels: 2 K C;
    - the GRU and LSTM: 0 (their gates act on products that the weights make)."""
    from neural_estimator.models.onnx_step import step_form

    form = step_form(model)
    trunk = getattr(form, "trunk", form)
    if hasattr(trunk, "W") and hasattr(trunk, "n_layers"):  # a ring form: GPT-2, Filterformer
        return 4 * trunk.D * trunk.W * trunk.n_layers
    if hasattr(trunk, "N") and hasattr(trunk, "layers"):  # an SSM form: Mamba (no heads), Mamba-2
        per_element, channels = (5, trunk.E + 2 * trunk.N) if hasattr(trunk, "H") else (6, trunk.E)
        return len(trunk.layers) * (per_element * trunk.N * trunk.E + 2 * trunk.K * channels)
    return 0


def optimized_nodes(graph: bytes) -> int:
    """How many operators ONNX Runtime runs for ``graph`` at the serving optimisation level."""
    import tempfile

    import onnx
    import onnxruntime as ort

    with tempfile.TemporaryDirectory() as tmp:
        opts = ort.SessionOptions()
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        opts.optimized_model_filepath = str(Path(tmp) / "optimized.onnx")
        opts.log_severity_level = 3  # its note that an optimised file is machine specific
        ort.InferenceSession(graph, opts, providers=["CPUExecutionProvider"])
        return len(onnx.load(opts.optimized_model_filepath).graph.node)


def own_step(model):
    """``model`` without its ``onnx_form``: ``export_step`` then traces the model's own ``step``."""
    import torch

    class OwnStep(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.model = model
            self.input_proj = model.input_proj

        def init_state(self, *args, **kwargs):
            return model.init_state(*args, **kwargs)

        def step(self, z, state):
            return model.step(z, state)

    return OwnStep()


def pct(samples: list[float]) -> tuple[float, float]:
    a = np.asarray(samples) * 1e6
    return float(np.percentile(a, 50)), float(np.percentile(a, 99))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="lorenz96")
    ap.add_argument("--methods", nargs="+", default=["gru", "lstm", "gpt2", "filterformer", "mamba", "mamba2"])
    ap.add_argument("--steps", type=int, default=2000, help="measured steps per column")
    ap.add_argument("--rounds", type=int, default=10, help="interleaved rounds (steps split among them)")
    ap.add_argument("--core", type=int, default=-1, help="pin to this core (-1: no pinning)")
    ap.add_argument(
        "--context", choices=["0", "card"], default="0", help="0: unbounded; card: as each card validated it"
    )
    a = ap.parse_args(argv)
    warnings.filterwarnings("ignore")
    if a.core >= 0:
        os.sched_setaffinity(0, {a.core})
    import torch

    torch.set_num_threads(1)
    from neural_estimator.data import simulate
    from neural_estimator.models import count_parameters
    from neural_estimator.serving.load import load_neural_estimator
    from neural_estimator.scenarios import make_scenario

    load0 = os.getloadavg()[0]
    rate = gemv_rate()
    scen = make_scenario(a.scenario)
    data = simulate(scen, 1, 1000, 0)
    Y = data.y[0]
    U = np.vstack([np.zeros((1, scen.du)), data.u[0, :-1]])
    print(f"command: python benchmarks/bench_serving.py {' '.join(argv if argv is not None else sys.argv[1:])}")
    print(
        f"{a.scenario}, torch {torch.__version__}, 1 thread, {os.cpu_count()} cores"
        + (f", pinned to core {a.core}" if a.core >= 0 else "")
        + f"; single-core GEMV {rate / 1e9:.1f} GFLOP/s; load average {load0:.1f} at start"
    )
    print()
    heads = ["torch step", "node (torch)", "ORT step", "ORT own step", "ORT run()", "node (ORT)"]
    print(
        "| model | params | GEMV limit | step limit | nodes (own step) | "
        + " | ".join(f"{h} p50 / p99" for h in heads)
        + " | ORT / limit | ORT / step limit | wrapper p50 | node (ORT) / ORT step | node (ORT) / ORT run()"
        + " | node (torch) / ORT step"
        + " | node (torch) / node (ORT) |"
    )
    print("|---|---:|---:|---:|---:|" + "---:|" * len(heads) + "---:|---:|---:|---:|---:|---:|---:|")
    context = {"context": 0} if a.context == "0" else {}  # {}: the card's
    for m in a.methods:
        est_t = load_neural_estimator(m, scen, **context)
        est_o = load_neural_estimator(m, scen, backend="onnxruntime", **context)
        steps, copies, nodes = _columns(m, est_t, est_o, Y, U)
        params = count_parameters(est_t.model)
        limit = 2 * params * (copies[1] if copies else 1) / rate * 1e6
        step_limit = limit + state_flops(est_t.model) * (copies[1] if copies else 1) / rate * 1e6
        if copies:
            print(f"{m}: context bounded to {copies[0]} steps, {copies[1]} copies as one batch", flush=True)
        times = _interleaved(steps, heads, a.rounds, max(1, a.steps // a.rounds))
        p = {h: pct(v) for h, v in times.items()}
        wrapper = p["node (ORT)"][0] - p["ORT step"][0]
        cells = " | ".join(f"{p[h][0]:.1f} / {p[h][1]:.1f}" for h in heads)
        print(
            f"| {m} | {params:,} | {limit:.1f} | {step_limit:.1f} | {nodes} | {cells} | "
            f"{p['ORT step'][0] / limit:.1f}x | "
            f"{p['ORT step'][0] / step_limit:.1f}x | {wrapper:.1f} | "
            f"{p['node (ORT)'][0] / p['ORT step'][0]:.2f}x | {p['node (ORT)'][0] / p['ORT run()'][0]:.2f}x | "
            f"{p['node (torch)'][0] / p['ORT step'][0]:.2f}x | {p['node (torch)'][0] / p['node (ORT)'][0]:.2f}x |",
            flush=True,
        )
    print(f"\nload average {os.getloadavg()[0]:.1f} at the end (microseconds, wall clock)")
    return 0


def _columns(m: str, est_t, est_o, Y: np.ndarray, U: np.ndarray) -> tuple[dict, tuple[int, int] | None, str]:
    """The timed call of every column, each a function of the step index j (numpy inputs Y, U), the
    bounded context (L, K) where the card's is one (else None), and the optimised operator counts
    (the served graph's, then the model's own step traced)."""
    import torch

    from neural_estimator.models.onnx_step import export_step, has_step_form
    from neural_estimator.serving.context import BatchedCopies
    from neural_estimator.serving.onnx_runtime import OrtStep

    model = est_t.model
    copies = (est_t.context, est_t.context_copies) if est_t.context_by_copies else None
    graph = export_step(model, m, copies=copies)  # the network alone, as the torch step column
    own_graph = export_step(own_step(model), m, copies=copies) if has_step_form(model) else graph
    nodes = f"{optimized_nodes(graph)} ({optimized_nodes(own_graph)})"
    ort = OrtStep(graph)
    ort_own = OrtStep(own_graph)
    plain = OrtStep(graph).session
    names_out = [o.name for o in plain.get_outputs()]
    dtypes = {"tensor(int64)": np.int64}
    feed = {
        i.name: np.zeros([int(d) for d in i.shape], dtype=dtypes.get(i.type, np.float32)) for i in plain.get_inputs()
    }
    z32 = [est_t.normalizer.normalize_inputs(Y[k : k + 1], U[k : k + 1])[0].astype(np.float32) for k in range(len(Y))]
    with torch.inference_mode():
        state = [model.init_state(1)]
        batched = BatchedCopies(model, copies[0], copies[1], 1, "cpu", torch.float32) if copies else None
    est_t.reset(1)
    est_o.reset(1)
    clock = [0]  # the copies' step count

    def torch_step(j: int) -> None:
        zt = torch.from_numpy(z32[j])
        with torch.inference_mode():
            if batched is None:
                _, state[0] = model.step(zt, state[0])
            else:
                batched.step(zt, clock[0], model.step)
                clock[0] += 1

    def ort_run(j: int) -> None:
        feed["z"] = z32[j]
        res = plain.run(names_out, feed)
        for i, name in enumerate(names_out[1:], 1):
            feed[name.replace("new_", "")] = res[i]

    steps = {
        "torch step": torch_step,
        "node (torch)": lambda j: est_t.step(Y[j : j + 1], U[j : j + 1]),
        "ORT step": lambda j: ort.step(z32[j]),
        "ORT own step": lambda j: ort_own.step(z32[j]),
        "ORT run()": ort_run,
        "node (ORT)": lambda j: est_o.step(Y[j : j + 1], U[j : j + 1]),
    }
    return steps, copies, nodes


def _interleaved(steps: dict, heads: list[str], rounds: int, per_round: int) -> dict[str, list[float]]:
    """Wall-clock seconds of every column's calls, in interleaved rounds (round 0 warms up)."""
    times: dict[str, list[float]] = {h: [] for h in heads}
    k, n = 0, 1000
    for r in range(rounds + 1):
        for h in heads:
            call, out = steps[h], times[h]
            for i in range(per_round):
                j = (k + i) % n
                t0 = time.perf_counter()
                call(j)
                dt = time.perf_counter() - t0
                if r > 0:
                    out.append(dt)
        k += per_round
    return times


if __name__ == "__main__":
    sys.exit(main())
