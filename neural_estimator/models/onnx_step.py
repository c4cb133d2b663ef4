"""One step of a neural model as an ONNX graph, served by ONNX Runtime (an optional backend).

At batch 1 a torch step costs the dispatch of every aten op (1.3-1.7 us each, 40-120 ops a step)
on top of the arithmetic; ONNX Runtime runs the same graph with one call from Python. The graph is
the model's own ``step`` traced at batch 1, or for Mamba, Mamba-2, GPT-2 and Filterformer the same
step in the form ONNX Runtime runs in fewer operators (their ``onnx_form()``,
:mod:`neural_estimator.models.onnx_forms`)::

    inputs:  z (1, d_in) float32 (normalised [y_k, u_{k-1}]), state_0 ... state_{S-1}
    outputs: mean (1, d_out) float32 (normalised), new_state_0 ... new_state_{S-1}

with the state flattened in the traced step's order (GRU: h; LSTM: h, c; KalmanNet: its filter's
memory, then the GRU's h; Mamba/Mamba-2: per layer the conv window (K, C) and the SSM state, (N, E)
for both, no batch axis; GPT-2, Filterformer: the slots' ages (W,), then per attention layer
the keys and the values of its ring buffer, (nh, W, hs) each). The graph owns its state:
``OrtStep`` keeps it between steps and nothing else reads it. The attention models serve a bounded
key/value cache of the last W steps (their attention window, the ``context`` option), so their step
graph has fixed shapes too; Filterformer's graph also outputs ``cov`` (1, d_out, d_out), its head's
covariance (normalised units), when exported with ``covariance``. A state that does not start at
zeros (the attention models' ages start at +inf: no slot written) is recorded in the graph's
metadata (``initial_fill``), which ``OrtStep`` resets to.
A recurrent model served with a bounded context (K restarted copies, :mod:`neural_estimator.serving.context`)
exports the step of its K copies as one batch of K rows, with the served copy's index as an input
(``export_step(copies=(L, K))``); ``OrtStep`` restarts the copies' rows between steps.
:func:`export_step` makes it from the loaded checkpoint (card + safetensors weights), so the export
is reproducible from the card: the same weights give the same graph. ``OrtStep`` serves it; a test
holds it equal to the torch step over hundreds of steps.

Serving needs ``onnxruntime``; exporting also needs torch and ``onnx`` (all three in the runtime
install). The serving side (``OrtStep``, the torch-free ``OnnxEstimator``) lives in
:mod:`neural_estimator.serving.onnx_runtime`, which imports no torch:
:func:`neural_estimator.serving.export.export_beside` writes
``step.onnx`` beside a checkpoint's card (``train`` does when it saves a model, the zoo ships them,
``scripts/export_onnx.py --beside``), and the per-message estimators serve it without torch.
"""

from __future__ import annotations

import io
import json
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from neural_estimator.methods import table


class OnnxError(RuntimeError):
    """The step cannot be exported (missing package, unsupported method): one line."""


OPSET = 17


def _flatten(state: Any) -> list:
    return list(state) if isinstance(state, (tuple, list)) else [state]


def state_batch_dims(model: Any, device: Any = None, dtype: Any = None) -> list[int]:
    """Each tensor of the model's step state (one tensor or a tuple), its batch axis: the axis where
    ``init_state(1)`` and ``init_state(2)`` differ (the models keep the batch on different axes).
    The exported copies' graph records them (``copy_dims``); torch's restarted copies use them too."""
    one = _flatten(model.init_state(1, device=device, dtype=dtype))
    two = _flatten(model.init_state(2, device=device, dtype=dtype))
    return [next(d for d in range(a.dim()) if a.shape[d] != b.shape[d]) for a, b in zip(one, two)]


def _starting_fills(method: str, flat: list) -> list[float]:
    """The state's starting values: one constant per tensor (zeros, or the mask's -inf)."""
    fills = []
    for t in flat:
        first = t.reshape(-1)[:1]
        if t.numel() and not bool((t == first).all()):
            raise OnnxError(f"{method}: a starting state that is not one constant per tensor cannot be exported")
        fills.append(float(first[0]) if t.numel() else 0.0)
    return fills


def export_step(
    model: Any,
    method: str,
    path: str | Path | None = None,
    normalizer: Any = None,
    covariance: bool = False,
    metadata: dict[str, str] | None = None,
    copies: tuple[int, int] | None = None,
) -> bytes:
    """The ONNX graph of ``model.step`` at batch 1, written to ``path`` when given.

    ``covariance``: a model with ``step_with_cov`` (Filterformer) exports that, with the extra output
    ``cov`` (normalised units; with ``normalizer``: ``covariance``, in state units). ``metadata``:
    strings stored in the graph (e.g. the card's weight digest) beside ``method``, ``window`` (the
    attention models) and ``initial_fill``.

    Without ``normalizer`` the graph is the network alone (z float32 in, mean float32 out). With the
    checkpoint's :class:`~neural_estimator.serving.normalization.Normalizer` it is the whole estimator
    step of :class:`~neural_estimator.serving.neural.NeuralEstimator`, in the same arithmetic::

        inputs:  y (1, dy) float64, u (1, du) float64 (absent when du = 0), state_0 ... state_{S-1}
        outputs: x (1, dx) float64 (denormalised, angles not yet wrapped), skipped (1, 1) bool
                 (y had NaN or inf: its part of z was the training mean 0), new_state_0 ...

    so a robot serves it with numpy and onnxruntime only
    (:class:`~neural_estimator.serving.onnx_runtime.OrtStep`), without torch.

    ``copies`` = (L, K): a recurrent model served with its context bounded to L steps by K restarted
    copies (:mod:`neural_estimator.serving.context`), network-only, one stream: see
    :func:`_bounded_module` for the graph, whose metadata adds ``context`` (L), ``context_copies``
    (K) and ``copy_dims`` (each state tensor's batch axis, where copy k holds row k).

    Raises:
        OnnxError: ``method`` is not exportable (its spec in the table of methods), or torch's exporter
            is missing.
    """
    if not table.has(method, exportable=True):
        raise OnnxError(f"{method}: the ONNX step exists for {', '.join(table.names(exportable=True))} only")
    import torch

    model = model.eval()
    p = next(model.parameters())
    if copies is not None and (normalizer is not None or not table.has(method, context="recurrent")):
        raise OnnxError(
            f"{method}: a bounded context by restarted copies exports for "
            f"{', '.join(table.names(context='recurrent'))}, network-only"
        )
    d_in = model.input_proj.in_features if hasattr(model, "input_proj") else int(model.cfg.d_in)
    blocker = getattr(model, "onnx_blocker", None)  # a hybrid whose system's f or h has no ONNX form
    if blocker:
        raise OnnxError(f"{method}: {blocker}")
    missing_nan = bool(getattr(model, "reads_missing_observations", False))
    if copies is None:  # the step forms serve one stream; K copies step as a batch of K rows
        model = step_form(model)
    state0 = model.init_state(1 if copies is None else int(copies[1]), device=p.device, dtype=torch.float32)
    flat = _flatten(state0)
    structured = isinstance(state0, (tuple, list))
    with_cov = bool(covariance) and hasattr(model, "step_with_cov")
    fills = _starting_fills(method, flat)

    def network(z, state):
        state = tuple(state) if structured else state[0]
        if with_cov:
            mean, cov, new = model.step_with_cov(z, state)
            return (mean, cov), _flatten(new)
        mean, new = model.step(z, state)
        return (mean,), _flatten(new)

    bounded: dict[str, str] = {}
    if copies is not None:
        step, args, names_in, names_out = _bounded_module(model, flat, structured, with_cov, d_in, int(copies[1]))
        bounded = {
            "context": str(int(copies[0])),
            "context_copies": str(int(copies[1])),
            "copy_dims": json.dumps(state_batch_dims(model, p.device, torch.float32)),
        }
    elif normalizer is None:
        step, args, names_in, names_out = _network_module(model, network, flat, with_cov, d_in)
    else:
        step, args, names_in, names_out = _estimator_module(model, network, flat, with_cov, normalizer, missing_nan)
    _register_symbolics()
    names_in = names_in + [f"state_{i}" for i in range(len(flat))]
    names_out = names_out + [f"new_state_{i}" for i in range(len(flat))]
    data = _with_metadata(
        _exported(step, args, names_in, names_out),
        {
            "method": method,
            "initial_fill": json.dumps(fills),
            **(
                {"window": str(int(flat[0].shape[0]))} if table.has(method, context="window") else {}
            ),  # a KV cache over W
            **({"missing_observations": "nan"} if missing_nan else {}),  # see OnnxEstimator.step
            **bounded,
            **(metadata or {}),
        },
    )
    if path is not None:
        Path(path).write_bytes(data)
    return data


def has_step_form(model: Any) -> bool:
    """Whether ``model``'s class has an ``onnx_form()`` (Mamba, Mamba-2, GPT-2, Filterformer, and a
    covariance head's wrapper: :mod:`neural_estimator.models.onnx_forms`, the same step in fewer ONNX
    Runtime operators, with its own state layout). Looked up on the class: a wrapper that forwards
    unknown attributes to its trunk must define its own."""
    return getattr(type(model), "onnx_form", None) is not None


def step_form(model: Any) -> Any:
    """What is traced: the model's ``onnx_form()`` where it has one (:func:`has_step_form`), else the
    model itself."""
    return model.onnx_form().eval() if has_step_form(model) else model


# Operations a trace records that the exporter's own passes fold away before it looks for ONNX forms
# (a Python number read from a tensor, a constant lifted into the graph).
_TRACE_ONLY = frozenset({"aten::Int", "aten::Float", "aten::ScalarImplicit", "aten::lift_fresh"})


def unsupported_reason(fn: Any, args: tuple, what: str) -> str | None:
    """Why ``fn(*args)`` has no ONNX form at :data:`OPSET`, or None when it exports: the probe a hybrid
    makes of its system's f and h before its step is exported (``KalmanNetModel.onnx_blocker``;
    N-link's f solves its mass-matrix system with ``aten::linalg_solve``, which opset 17 lacks).

    ``fn`` is traced and its aten operations looked up in torch's table of ONNX forms (no export is
    attempted: a failed export prints its whole graph to the process's stderr)."""
    import torch
    from torch.onnx._internal.torchscript_exporter.registration import registry

    _register_symbolics()
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the tracer's notes on Python values
        graph = torch.jit.trace(fn, args, check_trace=False).graph
    missing = sorted(
        {
            n.kind()
            for n in graph.nodes()
            if n.kind().startswith("aten::")
            and n.kind() not in _TRACE_ONLY
            and not registry.is_registered_op(n.kind(), OPSET)
        }
    )
    if not missing:
        return None
    return f"{what} uses {', '.join(missing)}, with no ONNX form at opset {OPSET}; it is served by torch"


def _network_module(model: Any, network, flat: list, with_cov: bool, d_in: int) -> tuple:
    """The network alone as a module (z float32 in, mean float32 out): (module, example inputs,
    input names, output names), the state's names not yet appended."""
    import torch

    class Step(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.model = model

        def forward(self, z, *state):
            outs, new = network(z, state)
            return (*outs, *new)

    args: tuple = (torch.zeros(1, d_in), *flat)
    return Step(), args, ["z"], ["mean"] + (["cov"] if with_cov else [])


def _bounded_module(model: Any, flat: list, structured: bool, with_cov: bool, d_in: int, copies: int) -> tuple:
    """The step of K restarted copies of a recurrent model for one stream, as a module: (module,
    example inputs, input names, output names), the state's names not yet appended::

        inputs:  z (1, d_in) float32, copy (1,) int64 (the served copy k), state_i (K rows: copy k's is row k)
        outputs: mean (1, d_out), [cov (1, d_out, d_out)], new_state_i

    The arithmetic of :class:`~neural_estimator.serving.neural.NeuralEstimator`'s bounded step: z
    repeated on the K rows, one batched step, the served copy's row read (a covariance head runs on
    that row's features only). The restarts are not in the graph: the numpy wrapper
    (:class:`~neural_estimator.serving.onnx_runtime.OrtStep`) writes a copy's starting values
    into its rows of the bound state buffer before the steps it restarts at. That is K of every L
    steps (4 in 100 on the zoo's GRUs), a slice assignment each, where a restart mask in the graph
    would cost a Where per state tensor at every step, and it keeps the graph the model's own step
    at batch K. The served copy is a graph input because the covariance head must see one row."""
    import torch

    head = with_cov and hasattr(model, "cov_head")  # a fitted covariance head: on the served row only

    class Step(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.model = model

        def forward(self, z, copy, *state):
            rows = z.expand(copies, -1)  # the input of every copy (BatchedCopies repeats it)
            st = tuple(state) if structured else state[0]
            if head:
                h, new = model.trunk.step_features(rows, st)
                h = h.index_select(0, copy)
                return (model.mean_of(h), model.cov_head(h), *_flatten(new))
            if with_cov:
                mean, cov, new = model.step_with_cov(rows, st)
                return (mean.index_select(0, copy), cov.index_select(0, copy), *_flatten(new))
            mean, new = model.step(rows, st)
            return (mean.index_select(0, copy), *_flatten(new))

    args: tuple = (torch.zeros(1, d_in), torch.zeros(1, dtype=torch.long), *flat)
    return Step(), args, ["z", "copy"], ["mean"] + (["cov"] if with_cov else [])


def _estimator_module(
    model: Any, network, flat: list, with_cov: bool, normalizer: Any, missing_nan: bool = False
) -> tuple:
    """The whole estimator step, the checkpoint's normalisation around the network, as a module:
    (module, example inputs, input names, output names), the state's names not yet appended.
    ``missing_nan``: a non-finite y reaches the model as NaN (a hybrid then only predicts) instead of
    the training mean 0."""
    import torch

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
            missing = torch.full_like(y, float("nan")) if missing_nan else torch.zeros_like(y)
            zy = torch.where(finite, (y - in_mean[:, :dy]) / in_std[:, :dy], missing)
            z = torch.cat([zy, (u - in_mean[:, dy:]) / in_std[:, dy:]], dim=-1) if du else zy
            outs, new = network(z.float(), state)
            x = outs[0].double() * out_std + out_mean
            if with_cov:  # diag(sigma_x) C diag(sigma_x), as Normalizer.denormalize_covariance
                cov = outs[1].double() * (out_std.reshape(1, -1, 1) * out_std.reshape(1, 1, -1))
                return (x, cov, ~finite, *new)
            return (x, ~finite, *new)

    args: tuple = (torch.zeros(1, dy, dtype=torch.float64),)
    args += (torch.zeros(1, du, dtype=torch.float64),) if du else ()
    args += tuple(flat)
    names_in = ["y"] + (["u"] if du else [])
    return Step(), args, names_in, ["x"] + (["covariance"] if with_cov else []) + ["skipped"]


def _exported(step: Any, args: tuple, names_in: list[str], names_out: list[str]) -> bytes:
    """torch's (TorchScript) exporter on ``step`` at :data:`OPSET`: the graph's bytes."""
    import torch

    buf = io.BytesIO()
    try:
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the exporter's notes on batch sizes and its deprecation
            torch.onnx.export(
                step.eval(),
                args,
                buf,
                input_names=names_in,
                output_names=names_out,
                opset_version=OPSET,
                dynamo=False,
            )
    except ImportError as exc:
        raise OnnxError(f"exporting needs the onnx package ({exc}): pip install onnx") from None
    return buf.getvalue()


def inplace_states(graph: Any) -> list[int]:
    """The states i that a step may update in place (an ``onnx.ModelProto``'s graph): ``state_i``'s
    one reader is a ScatterND that takes it as its data and writes ``new_state_i``. Such a node copies
    its data into its output and then writes a few rows; bound to the same buffer as its input (ONNX
    Runtime skips the copy when the two are one), it writes only the rows: the attention models' KV
    caches, 2 x (nh, W, hs) floats a layer, are no longer copied every step. Any other reader could
    see the rows already written, so a state with one is never listed."""
    readers: dict[str, list[tuple[Any, int]]] = {}
    for node in graph.node:
        for k, name in enumerate(node.input):
            readers.setdefault(name, []).append((node, k))
    outputs = {o.name for o in graph.output}
    found = []
    for inp in graph.input:
        if not inp.name.startswith("state_"):
            continue
        users = readers.get(inp.name, [])
        new = "new_" + inp.name
        if (
            len(users) == 1
            and users[0][0].op_type == "ScatterND"
            and users[0][1] == 0
            and users[0][0].output[0] == new
            and new in outputs
            and inp.name not in outputs  # a state passed through unchanged is its own output
        ):
            found.append(int(inp.name[len("state_") :]))
    return sorted(found)


def _with_metadata(data: bytes, props: dict[str, str]) -> bytes:
    """The graph ``data`` with ``props`` as its metadata (key/value strings), and ``inplace_states``
    (:func:`inplace_states`) where a state may be updated in place."""
    import onnx

    graph = onnx.load_from_string(data)
    inplace = inplace_states(graph.graph)
    if inplace:
        props = {**props, "inplace_states": json.dumps(inplace)}
    for key, value in props.items():
        entry = graph.metadata_props.add()
        entry.key, entry.value = str(key), str(value)
    return graph.SerializeToString()


_REGISTERED = False


def _register_symbolics() -> None:
    """ONNX forms of the aten ops the steps use that opset 17 lacks: ``rms_norm`` (as
    x / sqrt(mean(x^2) + eps) * w) and ``linalg_vecdot`` (as sum(a * b) over the last axis) of the SSM
    models' own ``step`` (their batch-1 forms export without them), ``diag_embed`` (as
    x[..., None] * I) of Filterformer's covariance."""
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

    def diag_embed(g, x, offset, dim1, dim2):  # only the default form (offset 0, the last two axes)
        if sh._get_const(offset, "i", "offset") != 0 or (
            sh._get_const(dim1, "i", "dim1"),
            sh._get_const(dim2, "i", "dim2"),
        ) not in ((-2, -1),):
            return sh._unimplemented("diag_embed", "offset 0 on the last two axes only", x)
        n = sh._get_tensor_sizes(x)[-1]
        eye = g.op("Constant", value_t=torch.eye(n, dtype=torch.float32))
        return g.op("Mul", g.op("Unsqueeze", x, g.op("Constant", value_t=torch.tensor([-1]))), eye)

    register_custom_op_symbolic("aten::diag_embed", diag_embed, OPSET)
    register_custom_op_symbolic("aten::rms_norm", rms_norm, OPSET)
    register_custom_op_symbolic("aten::linalg_vecdot", vecdot, OPSET)
    _REGISTERED = True
