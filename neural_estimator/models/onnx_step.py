"""One step of a recurrent model as an ONNX graph, served by ONNX Runtime (an optional backend).

At batch 1 a torch step costs the dispatch of every aten op (1.3-1.7 us each, 40-120 ops a step)
on top of the arithmetic; ONNX Runtime runs the same graph with one call from Python. The graph is
the model's own ``step`` traced at batch 1::

    inputs:  z (1, d_in) float32 (normalised [y_k, u_{k-1}]), state_0 ... state_{S-1}
    outputs: mean (1, d_out) float32 (normalised), new_state_0 ... new_state_{S-1}

with the state flattened in the model's order (GRU: h; LSTM: h, c; Mamba/Mamba-2: conv and SSM
state per layer). :func:`export_step` makes it from the loaded checkpoint (card + safetensors
weights), so the export is reproducible from the card: the same weights give the same graph.
:class:`OrtStep` serves it; a test holds it equal to the torch step over hundreds of steps.

The attention models (GPT-2, Filterformer) carry a growing key/value cache and are not exported.
Serving needs ``onnxruntime`` (``pip install onnxruntime``, the ``onnx`` extra); exporting also needs
torch and ``onnx``. A robot that gets the ``.onnx`` file (``scripts/export_onnx.py``) and the card
runs :class:`OrtStep` without torch.
"""

from __future__ import annotations

import io
import warnings
from pathlib import Path
from typing import Any

import numpy as np

EXPORTABLE = ("gru", "lstm", "mamba", "mamba2")
OPSET = 17


class OnnxError(RuntimeError):
    """The ONNX backend cannot serve this model (missing package, unsupported method): one line."""


def _flatten(state: Any) -> list:
    return list(state) if isinstance(state, (tuple, list)) else [state]


def export_step(model: Any, method: str, path: str | Path | None = None) -> bytes:
    """The ONNX graph of ``model.step`` at batch 1 (float32), written to ``path`` when given.

    Raises:
        OnnxError: ``method`` is not one of :data:`EXPORTABLE`, or torch's exporter is missing.
    """
    if method not in EXPORTABLE:
        raise OnnxError(f"{method}: the ONNX step exists for {', '.join(EXPORTABLE)} only")
    import torch

    model = model.eval()
    p = next(model.parameters())
    state0 = model.init_state(1, device=p.device, dtype=torch.float32)
    flat = _flatten(state0)
    structured = isinstance(state0, (tuple, list))

    class Step(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.model = model

        def forward(self, z, *state):
            mean, new = self.model.step(z, tuple(state) if structured else state[0])
            return (mean, *_flatten(new))

    _register_symbolics()
    d_in = model.input_proj.in_features
    z = torch.zeros(1, d_in)
    names_in = ["z"] + [f"state_{i}" for i in range(len(flat))]
    names_out = ["mean"] + [f"new_state_{i}" for i in range(len(flat))]
    buf = io.BytesIO()
    try:
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the exporter's notes on batch sizes and its deprecation
            torch.onnx.export(
                Step().eval(),
                (z, *flat),
                buf,
                input_names=names_in,
                output_names=names_out,
                opset_version=OPSET,
                dynamo=False,
            )
    except ImportError as exc:
        raise OnnxError(f"exporting needs the onnx package ({exc}): pip install onnx") from None
    data = buf.getvalue()
    if path is not None:
        Path(path).write_bytes(data)
    return data


_REGISTERED = False


def _register_symbolics() -> None:
    """ONNX forms of the two aten ops the SSM steps use that opset 17 lacks: ``rms_norm`` (as
    x / sqrt(mean(x^2) + eps) * w) and ``linalg_vecdot`` (as sum(a * b) over the last axis)."""
    global _REGISTERED
    if _REGISTERED:
        return
    import torch
    from torch.onnx import register_custom_op_symbolic
    from torch.onnx import symbolic_helper as sh

    def rms_norm(g, x, normalized_shape, weight, eps):
        eps_value = sh._maybe_get_const(eps, "f")
        eps_value = 1e-6 if sh._is_value(eps_value) or eps_value is None else float(eps_value)
        ms = g.op("ReduceMean", g.op("Mul", x, x), axes_i=[-1], keepdims_i=1)
        inv = g.op("Reciprocal", g.op("Sqrt", g.op("Add", ms, g.op("Constant", value_t=torch.tensor(eps_value)))))
        out = g.op("Mul", x, inv)
        return out if sh._is_none(weight) else g.op("Mul", out, weight)

    def vecdot(g, a, b, dim):
        axis = sh._get_const(dim, "i", "dim")
        return g.op("ReduceSum", g.op("Mul", a, b), g.op("Constant", value_t=torch.tensor([axis])), keepdims_i=0)

    register_custom_op_symbolic("aten::rms_norm", rms_norm, OPSET)
    register_custom_op_symbolic("aten::linalg_vecdot", vecdot, OPSET)
    _REGISTERED = True


class OrtStep:
    """A stateful batch-1 step over an exported graph: ``reset()``, ``step(z) -> mean``.

    Args:
        graph: the ``.onnx`` bytes or a path to them.
        threads: ONNX Runtime intra-op threads (1: the live node's case).
    """

    def __init__(self, graph: bytes | str | Path, threads: int = 1) -> None:
        try:
            import onnxruntime as ort
        except ImportError:
            raise OnnxError("backend onnxruntime needs the onnxruntime package: pip install onnxruntime") from None
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = max(1, int(threads))
        opts.inter_op_num_threads = 1
        opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        opts.add_session_config_entry("session.intra_op.allow_spinning", "0")  # never spin on a busy core
        model = graph if isinstance(graph, bytes) else Path(graph).read_bytes()
        self.session = ort.InferenceSession(model, opts, providers=["CPUExecutionProvider"])
        inputs, outputs = self.session.get_inputs(), self.session.get_outputs()
        self.d_in = int(inputs[0].shape[1])
        self.d_out = int(outputs[0].shape[1])
        shapes = [tuple(int(d) for d in i.shape) for i in inputs[1:]]
        # Preallocated buffers bound once (no allocation, no dict per step): z, the mean, and two sets of
        # state buffers that swap roles every step (the step reads one set and writes the other).
        self.z = np.zeros((1, self.d_in), dtype=np.float32)
        self.mean = np.zeros((1, self.d_out), dtype=np.float32)
        self._sets = [[np.zeros(sh, dtype=np.float32) for sh in shapes] for _ in range(2)]
        value = ort.OrtValue.ortvalue_from_numpy
        self._bindings = []
        for src, dst in ((0, 1), (1, 0)):
            b = self.session.io_binding()
            b.bind_ortvalue_input(inputs[0].name, value(self.z))
            b.bind_ortvalue_output(outputs[0].name, value(self.mean))
            for i, o, a, c in zip(inputs[1:], outputs[1:], self._sets[src], self._sets[dst]):
                b.bind_ortvalue_input(i.name, value(a))
                b.bind_ortvalue_output(o.name, value(c))
            self._bindings.append(b)
        self._run = self.session.run_with_iobinding
        self.reset()

    @property
    def state(self) -> list[np.ndarray]:
        """The current state buffers (float32, the graph's order)."""
        return self._sets[self._current]

    def reset(self) -> None:
        for buffers in self._sets:
            for a in buffers:
                a.fill(0.0)
        self._current = 0

    def step(self, z: np.ndarray | None = None) -> np.ndarray:
        """z (1, d_in) -> mean (1, d_out) float32, a view of a buffer the next step overwrites (copy it
        to keep it); the state advances. Without ``z``, the step reads :attr:`z` as written in place."""
        if z is not None:
            np.copyto(self.z, z, casting="same_kind")
        self._run(self._bindings[self._current])
        self._current ^= 1
        return self.mean
