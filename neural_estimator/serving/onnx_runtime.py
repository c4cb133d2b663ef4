"""Serving a neural model's exported step with ONNX Runtime and numpy only: no torch on the robot.

:class:`OrtStep` runs a step graph (``neural_estimator.models.onnx_step.export_step``) through
preallocated bound buffers; :class:`OnnxEstimator` is the estimator over a network-only graph (the
card's normalisation in numpy); :func:`load_onnx_estimator` serves ``step.onnx`` beside a checkpoint's
card (written by ``train`` and shipped beside every zoo model that it can serve;
``scripts/export_onnx.py --beside`` for others). This module imports neither torch nor the model
code: a robot needs numpy and onnxruntime (``scripts/requirements-serve.txt``).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from neural_estimator.core.angles import wrap_components
from neural_estimator.methods import table
from neural_estimator.methods.interface import Estimator, EstimatorError
from neural_estimator.serving.onnx_kernels import denormalize, denormalize_covariance, normalize_into

ONNX_FILE = "step.onnx"  # the network-only graph beside a checkpoint's card (scripts/export_onnx.py --beside)


class WindowMismatch(EstimatorError):
    """The exported context is not the one asked for: another attention window, or another bounded
    context (steps, copies) of a recurrent model (the ``auto`` backend then uses torch)."""


def graph_metadata(session: Any) -> dict[str, str]:
    """The metadata strings of a loaded graph (an onnxruntime InferenceSession)."""
    return dict(session.get_modelmeta().custom_metadata_map)


def served_files(card: dict[str, Any]) -> dict[str, str]:
    """What a graph beside ``card`` was exported from, as its metadata strings: the weights' sha256
    and the covariance head's (its sha256 and correlation shrinkage, the card's entry; '' without a
    head). A graph whose strings differ from its card's is stale and is refused."""
    head = card.get("covariance_head") or {}
    return {
        "weights_sha256": str((card.get("weights") or {}).get("sha256") or ""),
        "covariance_head": json.dumps({"sha256": head.get("sha256", ""), "shrink": head.get("shrink", 0.0)})
        if head
        else "",
    }


class OrtStep:
    """A stateful batch-1 step over an exported graph: ``reset()``, ``step()``.

    Every input and output is a preallocated numpy buffer bound once (no allocation, no dict per step):
    write the inputs into :attr:`inputs` (by name: ``z``, or ``y`` and ``u``), call :meth:`run`, read
    :attr:`outputs` (``mean``, or ``x`` and ``skipped``); the next run overwrites them. The state
    lives in two sets of buffers that swap roles every step (a run reads one and writes the other),
    except the states the graph updates in place (``inplace_states`` in its metadata: the attention
    models' KV caches), which keep one buffer, read and written by the same run.

    Args:
        graph: the ``.onnx`` bytes or a path to them (:func:`export_step`).
        threads: ONNX Runtime intra-op threads (1: the live node's case).
    """

    def __init__(self, graph: bytes | str | Path, threads: int = 1) -> None:
        try:
            import onnxruntime as ort
        except ImportError as exc:
            if _interrupted(exc):  # Ctrl-C while its extension initialises: a stop, not a missing package
                raise KeyboardInterrupt from None
            raise EstimatorError("backend onnxruntime needs the onnxruntime package: pip install onnxruntime") from None
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = max(1, int(threads))
        opts.inter_op_num_threads = 1
        opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        opts.add_session_config_entry("session.intra_op.allow_spinning", "0")  # never spin on a busy core
        model = graph if isinstance(graph, bytes) else Path(graph).read_bytes()
        self.session = ort.InferenceSession(model, opts, providers=["CPUExecutionProvider"])
        dtypes = {
            "tensor(float)": np.float32,
            "tensor(double)": np.float64,
            "tensor(bool)": np.bool_,
            "tensor(int64)": np.int64,
        }

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
        self.metadata = graph_metadata(self.session)
        fills = json.loads(self.metadata.get("initial_fill", "[]")) or [0.0] * len(state_in)
        if len(fills) != len(state_in):
            raise EstimatorError(f"the graph's initial_fill names {len(fills)} states, its inputs {len(state_in)}")
        self._fills = [float(f) for f in fills]
        # states the graph updates in place (models.onnx_step.inplace_states: a KV cache written by
        # one ScatterND): one buffer serves as the step's input and output, so that ONNX Runtime
        # writes only the new rows instead of copying the cache into the other set first
        inplace = self._inplace(len(state_in))
        for k in inplace:
            self._sets[1][k] = self._sets[0][k]
        self.inplace = tuple(inplace)
        bounded = "context_copies" in self.metadata  # K restarted copies in the graph's batch
        self.copies = _copies_of(self.metadata, self._sets[0], self._fills) if bounded else None
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

    def _inplace(self, n_states: int) -> list[int]:
        """The graph's ``inplace_states`` (none in a graph exported before they were recorded)."""
        try:
            found = json.loads(self.metadata.get("inplace_states", "[]"))
            if not (isinstance(found, list) and all(isinstance(k, int) and 0 <= k < n_states for k in found)):
                raise ValueError(found)
        except ValueError:
            raise EstimatorError(
                f"the graph's inplace_states {self.metadata['inplace_states']!r} are not indices of its "
                f"{n_states} states"
            ) from None
        return sorted(set(found))

    @property
    def state(self) -> list[np.ndarray]:
        """The current state buffers (float32, the graph's order)."""
        return self._sets[self._current]

    def reset(self) -> None:
        for buffers in self._sets:
            for a, fill in zip(buffers, self._fills):
                a.fill(fill)
        self._current = 0
        self._t = 0  # steps since reset: which copies restart (a bounded-context graph)

    def run(self) -> None:
        """One step on what :attr:`inputs` hold; the state advances. A bounded-context graph's
        copies due at this step restart first, and the copy served is set (:class:`BoundedCopies`)."""
        if self.copies is not None:
            self.copies.before_step(self._t, self._sets[self._current], self.inputs["copy"])
            self._t += 1
        self._run(self._bindings[self._current])
        self._current ^= 1

    def step(self, z: np.ndarray) -> np.ndarray:
        """A network-only graph: z (1, d_in) -> mean (1, d_out) float32, a view of a buffer the next
        step overwrites (copy it to keep it)."""
        np.copyto(self.inputs["z"], z, casting="same_kind")
        self.run()
        return self.outputs["mean"]


class BoundedCopies:
    """The restarts and the served copy of a bounded-context graph (``export_step(copies=(L, K))``):
    the K copies of :class:`~neural_estimator.serving.context.BatchedCopies` on one stream, copy k
    in row k of every state buffer (along the graph's ``copy_dims``).

    Before step t, each copy that restarts at t has its rows set to the state's starting values
    (``initial_fill``), and the graph's ``copy`` input is set to the copy served at t
    (:func:`~neural_estimator.serving.context.copy_schedule`, the rule the torch copies follow).
    Past step L every copy has started and the schedule repeats every L steps, so it is looked up
    in a table of steps 0 .. 2L - 1 (step t >= L as L + (t - L) mod L): no Python loop per step.
    """

    def __init__(self, length: int, copies: int, dims: list[int], state: list[np.ndarray], fills: list[float]):
        from neural_estimator.serving.context import copy_schedule

        self.length, self.copies = int(length), int(copies)
        if not 1 <= self.copies <= self.length or len(dims) != len(state):
            raise EstimatorError(
                f"the graph's bounded context is malformed: context {length}, {copies} copies, "
                f"copy_dims {dims} for {len(state)} states"
            )
        for a, d in zip(state, dims):
            if not 0 <= d < a.ndim or a.shape[d] != self.copies:
                raise EstimatorError(f"the graph's state of shape {a.shape} has no axis {d} of {self.copies} copies")
        self.table = [copy_schedule(t, self.length, self.copies) for t in range(2 * self.length)]
        # rows[k]: for every state tensor, the index of copy k's rows and that tensor's starting value
        self.rows = [
            [(tuple(k if ax == d else slice(None) for ax in range(a.ndim)), f) for a, d, f in zip(state, dims, fills)]
            for k in range(self.copies)
        ]

    def before_step(self, t: int, state: list[np.ndarray], copy: np.ndarray) -> None:
        """Restart the copies due at step t in the state buffers the step reads; set the served copy."""
        L = self.length
        restarts, served = self.table[t if t < 2 * L else L + (t - L) % L]
        for k in restarts:
            for a, (index, fill) in zip(state, self.rows[k]):
                a[index] = fill
        copy[0] = served


def _copies_of(meta: dict[str, str], state: list[np.ndarray], fills: list[float]) -> BoundedCopies:
    """The graph's bounded context from its metadata (``context``, ``context_copies``, ``copy_dims``)."""
    try:
        length, copies = int(meta["context"]), int(meta["context_copies"])
        dims = [int(d) for d in json.loads(meta.get("copy_dims", "null"))]
    except (KeyError, ValueError, TypeError) as exc:
        raise EstimatorError(f"the graph's bounded-context metadata is malformed ({exc})") from None
    return BoundedCopies(length, copies, dims, state, fills)


class OnnxEstimator(Estimator):
    """A neural model's estimator served by ONNX Runtime over its network-only step graph, batch 1,
    with numpy and onnxruntime only (no torch).

    The arithmetic of :class:`~neural_estimator.serving.neural.NeuralEstimator`'s step: normalise
    [y_k, u_{k-1}] in float64 with the card's statistics (a non-finite y becomes the training mean, or
    NaN for a graph whose metadata says ``missing_observations: nan``, a hybrid that then predicts
    only, and is flagged in ``skipped``), the network in float32, denormalise (angles wrapped; Filterformer's
    covariance as diag(sigma_x) C diag(sigma_x)). Written into the graph's bound buffers, because at
    20-90 us a step every numpy call counts. ``run`` is the base class's loop of :meth:`step`.

    Args:
        scenario: the system served (the caller has checked the card against it).
        step: the network-only graph (:class:`OrtStep`; inputs ``z`` and the state).
        normalizer: the card's normalisation (:class:`~neural_estimator.serving.normalization.Normalizer`).
        method: the method name.
        card: the checkpoint card (provenance; the training warm-up).
        cov_scale: s > 0, the reported covariance is s times the model's (NeuralEstimator's option).
    """

    def __init__(
        self,
        scenario: Any,
        step: OrtStep,
        normalizer: Any,
        method: str,
        card: dict | None = None,
        cov_scale: float = 1.0,
    ) -> None:
        super().__init__(scenario)
        self.method = method
        if step.normalized:
            raise EstimatorError(f"{method}: the ONNX graph has the normalisation inside; serve the network-only one")
        dy, du = scenario.dy, scenario.du
        if step.d_in != dy + du or step.outputs["mean"].shape[1] != scenario.dx:
            raise EstimatorError(
                f"{method}: the ONNX graph maps {step.d_in} inputs to {step.outputs['mean'].shape[1]} states; "
                f"scenario {scenario.name!r} has dy + du = {dy + du}, dx = {scenario.dx}"
            )
        self.ort, self.normalizer, self.card = step, normalizer, dict(card or {})
        self.has_covariance = "cov" in step.outputs
        self.backend = "onnxruntime"
        copies = step.copies  # a recurrent model's bounded context: K restarted copies in the graph's batch
        self.context = copies.length if copies else int(step.metadata.get("window", 0))  # or the attention window
        self.context_by_copies = copies is not None
        self.context_copies = copies.copies if copies else 0
        self._missing_nan = step.metadata.get("missing_observations") == "nan"  # onnx_step.export_step
        self._dims = (dy, du)
        self._u_zero = np.zeros((1, du))
        self._skip_flags = (np.zeros(1, dtype=bool), np.ones(1, dtype=bool))
        f64 = lambda a: np.ascontiguousarray(a, dtype=np.float64)  # noqa: E731 - the kernels' one layout
        self._in_mean, self._in_std = f64(normalizer.in_mean), f64(normalizer.in_std)
        self._out_mean, self._out_std = f64(normalizer.out_mean), f64(normalizer.out_std)
        self.cov_scale = float(cov_scale)
        if not (np.isfinite(self.cov_scale) and self.cov_scale > 0):
            raise EstimatorError(f"cov_scale must be a finite number > 0, got {cov_scale!r}")
        self._cov_scale = self._out_std[:, None] * self._out_std[None, :]  # (dx, dx): sigma_x sigma_x^T
        if self.cov_scale != 1.0:
            self._cov_scale = self.cov_scale * self._cov_scale

    @property
    def untrained_steps(self) -> int:
        """Leading steps the training loss skipped (the card's ``training.recipe.warmup``)."""
        recipe = (self.card.get("training") or {}).get("recipe") or {}
        return int(recipe.get("warmup") or 0)

    def reset(self, batch: int = 1) -> None:
        if int(batch) != 1:
            raise EstimatorError(f"{self.method}: backend onnxruntime steps one stream (batch 1), got {batch}")
        self.ort.reset()
        self.batch = 1
        self.covariance = None
        self.diverged = np.zeros(1, dtype=bool)
        self.skipped = np.zeros(1, dtype=bool)

    def step(self, y: Any, u_prev: Any = None) -> np.ndarray:
        ort, n, (dy, du) = self.ort, self.normalizer, self._dims
        fast = (
            type(y) is np.ndarray
            and y.dtype == np.float64
            and y.shape == (1, dy)
            and self.batch == 1
            and (u_prev is None or (type(u_prev) is np.ndarray and u_prev.dtype == np.float64))
        )
        if not fast:  # anything else gets the full checks (and their errors)
            y, u_prev = self.check_step(y, u_prev)
            if y.shape[0] != 1:
                raise EstimatorError(f"{self.method}: backend onnxruntime steps one stream (batch 1), got {y.shape[0]}")
            self.start_streams_if_none(1)
        if du:
            if u_prev is None:
                u_prev = self._u_zero
            elif u_prev.shape != (1, du) or not np.isfinite(u_prev).all():
                self.check_step(y, u_prev)  # raises its one-line error
        else:
            u_prev = self._u_zero
        skipped = normalize_into(y, u_prev, self._in_mean, self._in_std, ort.inputs["z"])
        if skipped and self._missing_nan:  # a hybrid reads the missing y itself: it predicts only
            ort.inputs["z"][0, :dy] = np.nan
        ort.run()
        x, finite = denormalize(ort.outputs["mean"], self._out_std, self._out_mean)
        if n.angle_states:
            x = wrap_components(x, n.angle_states)
        self.skipped = self._skip_flags[int(skipped)]
        if self.has_covariance:  # diag(sigma_x) C diag(sigma_x) (Normalizer.denormalize_covariance), one product
            self.covariance, cov_finite = denormalize_covariance(ort.outputs["cov"], self._cov_scale)
            finite = finite and cov_finite
        if not finite:
            self.diverged = np.ones(1, dtype=bool)
        return x

    def __repr__(self) -> str:
        return f"OnnxEstimator({self.method!r}, scenario={self.scenario.name!r})"


def onnx_beside(directory: str | Path) -> Path | None:
    """The exported step graph in a checkpoint directory (``step.onnx`` beside its card), or None."""
    path = Path(directory) / ONNX_FILE
    return path if path.is_file() else None


def load_onnx_estimator(
    directory: Path,
    card: dict[str, Any],
    scenario: Any,
    context: int | None = None,
    covariance: bool = True,
    cov_scale: float = 1.0,
    context_copies: int = 0,
) -> OnnxEstimator:
    """The torch-free estimator of a checkpoint whose directory holds ``step.onnx``.

    The caller has read the card and checked it against ``scenario``. The graph must be the
    network-only step of this card's weights and covariance head (:func:`served_files`: a graph left
    from other weights or another head is refused, re-export it) and of the method the card names; an attention model
    serves with the window it was exported with (``context``, when given, must equal it); a
    recurrent model with the context it was exported with: ``context`` steps and ``context_copies``
    restarted copies (0 and 0: unbounded).
    ``covariance`` False ignores the graph's covariance output (the head's, or Filterformer's own).

    Raises:
        EstimatorError: missing onnxruntime, a graph of other weights, head or method;
            :class:`WindowMismatch`: another attention window or bounded context.
    """
    from neural_estimator.serving.normalization import NormalizationError, Normalizer

    path = Path(directory) / ONNX_FILE
    method = str(card["method"])
    try:
        step = OrtStep(path)
    except EstimatorError:
        raise
    except Exception as exc:  # onnxruntime's own errors for a malformed file
        raise EstimatorError(f"{path}: not a readable ONNX graph ({str(exc).splitlines()[0]})") from None
    meta = step.metadata
    expected = served_files(card)
    if meta.get("method") != method or any(meta.get(k, "") != v for k, v in expected.items()):
        raise EstimatorError(
            f"{path} was exported from other weights, another covariance head or another method than "
            f"{directory}'s card ({meta.get('method')!r}, weights {meta.get('weights_sha256', '')[:12] or '?'}): "
            f"export it again with scripts/export_onnx.py --beside"
        )
    if context and table.has(method, context="window") and int(meta.get("window", 0)) != int(context):
        raise WindowMismatch(
            f"{path} serves attention window {meta.get('window')}, not context={context}: "
            f"export it with --context {context}"
        )
    if not table.has(method, context="window"):  # a recurrent graph: unbounded, or K copies of L steps
        _check_copies(step, method, int(context or 0), int(context_copies or 0) if context else 0)
    if not covariance and "cov" in step.outputs:
        step.outputs.pop("cov")  # still computed by the graph, no longer read
    try:
        normalizer = Normalizer.from_dict(card["normalization"])
    except NormalizationError as exc:
        raise EstimatorError(f"{directory}: {exc}") from None
    return OnnxEstimator(scenario, step, normalizer, method, card, cov_scale=cov_scale)


def _check_copies(step: OrtStep, method: str, context: int, copies: int) -> None:
    """Refuse a recurrent model's graph exported with another context than (``context``, ``copies``)."""
    served = (step.copies.length, step.copies.copies) if step.copies else (0, 0)
    if served == (context, copies):
        return
    what = f"a context bounded to {served[0]} steps ({served[1]} copies)" if served[0] else "the unbounded context"
    asked = f"context={context}, context_copies={copies}" if context else "context=0"
    raise WindowMismatch(f"{method}: the exported step serves {what}, not {asked}; backend torch serves that")


def _interrupted(exc: BaseException) -> bool:
    """Whether an ImportError stands for a KeyboardInterrupt: ONNX Runtime's extension reports a Ctrl-C
    during its initialisation as "ImportError: initialization failed", the interrupt in its chain."""
    chain, seen = [], exc.__cause__ or exc.__context__
    while seen is not None and not any(seen is c for c in chain):
        if isinstance(seen, KeyboardInterrupt):
            return True
        chain.append(seen)
        seen = seen.__cause__ or seen.__context__
    return False
