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


def export_step(model: Any, method: str, path: str | Path | None = None, normalizer: Any = None) -> bytes:
    """The ONNX graph of ``model.step`` at batch 1, written to ``path`` when given.

    Without ``normalizer`` the graph is the network alone (z float32 in, mean float32 out). With the
    checkpoint's :class:`~neural_estimator.serving.normalization.Normalizer` it is the whole estimator
    step of :class:`~neural_estimator.serving.neural.NeuralEstimator`, in the same arithmetic::

        inputs:  y (1, dy) float64, u (1, du) float64 (absent when du = 0), state_0 ... state_{S-1}
        outputs: x (1, dx) float64 (denormalised, angles not yet wrapped), skipped (1, 1) bool
                 (y had NaN or inf: its part of z was the training mean 0), new_state_0 ...

    so a robot serves it with numpy and onnxruntime only (:class:`OrtStep`), without torch.

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
    d_in = model.input_proj.in_features

    def network(z, state):
        mean, new = model.step(z, tuple(state) if structured else state[0])
        return mean, _flatten(new)

    if normalizer is None:

        class Step(torch.nn.Module):
            def __init__(self) -> None:
                super().__init__()
                self.model = model

            def forward(self, z, *state):
                mean, new = network(z, state)
                return (mean, *new)

        args: tuple = (torch.zeros(1, d_in), *flat)
        names_in, names_out = ["z"], ["mean"]
    else:
        n = normalizer
        dy, du = int(n.dy), int(n.du)

        def t(a):
            return torch.as_tensor(np.asarray(a, dtype=np.float64)).reshape(1, -1)

        in_mean, in_std, out_mean, out_std = t(n.in_mean), t(n.in_std), t(n.out_mean), t(n.out_std)

        class Step(torch.nn.Module):  # the arithmetic of Normalizer.normalize_inputs / denormalize_states
            def __init__(self) -> None:
                super().__init__()
                self.model = model

            def forward(self, y, *rest):
                u, state = (rest[0], rest[1:]) if du else (None, rest)
                finite = torch.isfinite(y).all(dim=-1, keepdim=True)  # (1, 1)
                zy = torch.where(finite, (y - in_mean[:, :dy]) / in_std[:, :dy], torch.zeros_like(y))
                z = torch.cat([zy, (u - in_mean[:, dy:]) / in_std[:, dy:]], dim=-1) if du else zy
                mean, new = network(z.float(), state)
                return (mean.double() * out_std + out_mean, ~finite, *new)

        args = (torch.zeros(1, dy, dtype=torch.float64),)
        args += (torch.zeros(1, du, dtype=torch.float64),) if du else ()
        args += tuple(flat)
        names_in, names_out = ["y"] + (["u"] if du else []), ["x", "skipped"]

    _register_symbolics()
    names_in = names_in + [f"state_{i}" for i in range(len(flat))]
    names_out = names_out + [f"new_state_{i}" for i in range(len(flat))]
    buf = io.BytesIO()
    try:
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the exporter's notes on batch sizes and its deprecation
            torch.onnx.export(
                Step().eval(),
                args,
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
    """A stateful batch-1 step over an exported graph: ``reset()``, ``step()``.

    Every input and output is a preallocated numpy buffer bound once (no allocation, no dict per step):
    write the inputs into :attr:`inputs` (by name: ``z``, or ``y`` and ``u``), call :meth:`run`, read
    :attr:`outputs` (``mean``, or ``x`` and ``skipped``); the next run overwrites them. The state
    lives in two sets of buffers that swap roles every step (a run reads one and writes the other).

    Args:
        graph: the ``.onnx`` bytes or a path to them (:func:`export_step`).
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
        dtypes = {"tensor(float)": np.float32, "tensor(double)": np.float64, "tensor(bool)": np.bool_}

        def buffer(arg) -> np.ndarray:
            return np.zeros(tuple(int(d) for d in arg.shape), dtype=dtypes[arg.type])

        ins, outs = self.session.get_inputs(), self.session.get_outputs()
        state_in = [i for i in ins if i.name.startswith("state_")]
        state_out = [o for o in outs if o.name.startswith("new_state_")]
        self.inputs = {i.name: buffer(i) for i in ins if not i.name.startswith("state_")}
        self.outputs = {o.name: buffer(o) for o in outs if not o.name.startswith("new_state_")}
        self.normalized = "y" in self.inputs
        first = self.inputs["y" if self.normalized else "z"]
        self.d_in = int(first.shape[1])
        self._sets = [[buffer(i) for i in state_in] for _ in range(2)]
        value = ort.OrtValue.ortvalue_from_numpy
        self._bindings = []
        for src, dst in ((0, 1), (1, 0)):
            b = self.session.io_binding()
            for name, a in self.inputs.items():
                b.bind_ortvalue_input(name, value(a))
            for name, a in self.outputs.items():
                b.bind_ortvalue_output(name, value(a))
            for i, o, a, c in zip(state_in, state_out, self._sets[src], self._sets[dst]):
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

    def run(self) -> None:
        """One step on what :attr:`inputs` hold; the state advances."""
        self._run(self._bindings[self._current])
        self._current ^= 1

    def step(self, z: np.ndarray) -> np.ndarray:
        """A network-only graph: z (1, d_in) -> mean (1, d_out) float32, a view of a buffer the next
        step overwrites (copy it to keep it)."""
        np.copyto(self.inputs["z"], z, casting="same_kind")
        self.run()
        return self.outputs["mean"]
