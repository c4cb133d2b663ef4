"""The estimator interface over a trained sequence model: normalise, run the network, denormalise.

One class serves all six architectures (GRU, LSTM, GPT-2, Filterformer, Mamba, Mamba-2) and the
KalmanNet hybrid (:mod:`neural_estimator.models.kalmannet`). At step k

    z_k   = [y_k, u_{k-1}]                           (the paper's input; u_{-1} = 0)
    z_n   = (z_k - mu_z) / sigma_z                   (training-set statistics, see normalization.py)
    x_n, state = model.step(z_n, state)              (torch.inference_mode, eval mode, float32)
    x_hat = mu_x + sigma_x x_n                       (float64 numpy, angles wrapped to (-pi, pi])

:meth:`NeuralEstimator.run` uses the model's parallel form over whole sequences instead (chunked
over the batch to bound memory); a test holds it equal to a loop of :meth:`NeuralEstimator.step`.
A non-finite observation row is replaced by the training mean (0 after normalisation) and flagged in
``skipped``; a model that reads missing observations itself (``reads_missing_observations``: the
KalmanNet hybrid, which then predicts without an update) gets NaN there instead. Filterformer also
returns a covariance from its geometric-attention head, and any model with a fitted covariance head
(:mod:`neural_estimator.serving.uncertainty.heads`) returns that head's; both are mapped back to
state units as diag(sigma_x) C_n diag(sigma_x).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import nn

from neural_estimator.methods import table
from neural_estimator.methods.interface import Estimates, Estimator, EstimatorError, previous_controls
from neural_estimator.serving.context import BatchedCopies, bounded_forward
from neural_estimator.serving.normalization import Normalizer
from neural_estimator.core.options import OptionError, parse_bool, parse_value
from neural_estimator.scenarios import Scenario

BACKENDS = ("torch", "onnxruntime")  # how step() runs the network (run() always uses torch's parallel form)

CHUNK_TIMESTEPS = 1 << 16  # sequences x steps per parallel forward in run(): bounds activation memory


def resolve_device(device: str | torch.device | None = "cpu") -> torch.device:
    """``cpu``, ``cuda``, ``cuda:N`` or ``auto`` (cuda when available) as a torch.device.

    Raises:
        EstimatorError: an unknown device, or cuda requested where torch sees no GPU.
    """
    name = "cpu" if device is None else str(device).strip().lower()
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    try:
        dev = torch.device(name)
    except RuntimeError:
        raise EstimatorError(f"unknown device {device!r}; use cpu, cuda, cuda:N or auto") from None
    if dev.type not in ("cpu", "cuda"):
        raise EstimatorError(f"unsupported device {device!r}; use cpu, cuda, cuda:N or auto")
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise EstimatorError(
            f"device {device!r} requested, but torch {torch.__version__} sees no CUDA GPU; use device='cpu'"
        )
    return dev


class NeuralEstimator(Estimator):
    """A trained sequence model behind the :class:`~neural_estimator.methods.interface.Estimator` contract.

    Args:
        scenario: the system the model was trained on (dimensions are checked).
        model: a module of :mod:`neural_estimator.models` (``forward``, ``init_state``, ``step``;
            Filterformer also ``forward_with_cov`` and ``step_with_cov``). A hybrid (KalmanNet) is
            served the same way; it has no covariance (it tracks none).
        normalizer: the training-set statistics.
        method: the method name (a trainable method of the table: the six networks, the hybrid).
        device: ``cpu``, ``cuda``, ``cuda:N`` or ``auto``.
        covariance: report the covariance where the model has one (Filterformer). False skips it,
            which saves (B, T, dx, dx) memory in :meth:`run`.
        card: the checkpoint card (kept as ``self.card`` for provenance).
        chunk_timesteps: at most this many sequences x steps go through one parallel forward.
        compile_step: serve :meth:`step` through ``torch.compile`` of the model's step (fewer Python
            dispatches per message: Mamba-2's p99 goes from ~1.1 ms to ~0.5 ms of CPU on the
            development machine); the first steps pay a one-off compilation of seconds.
        context: bound every estimate's context to this many steps (0: as trained, the paper's
            way). GRU, LSTM, Mamba, Mamba-2: ``context_copies`` copies of the model restart at
            staggered steps, see :mod:`neural_estimator.serving.context`; K times the compute.
            GPT-2, Filterformer: their attention window W becomes ``context`` (``set_window`` on
            ``model`` itself, which then keeps it; the paper's W is 256, and a model trained on
            length-100 windows has never seen more than 100 keys), at no extra compute;
            ``context_copies`` does not apply.
        context_copies: K, the copies (more: contexts closer to ``context``).
        backend: how ``step`` runs the network (``torch`` or ``onnxruntime``).
        cov_scale: s > 0, the reported covariance is s times the model's (a post-hoc calibration
            on top of the one a covariance head carries in its card; 1 reports it as it is).
    """

    def __init__(
        self,
        scenario: Scenario,
        model: nn.Module,
        normalizer: Normalizer,
        method: str,
        device: str | torch.device = "cpu",
        covariance: bool = True,
        card: dict[str, Any] | None = None,
        chunk_timesteps: int = CHUNK_TIMESTEPS,
        compile_step: bool = False,
        context: int = 0,
        context_copies: int = 10,
        backend: str = "torch",
        cov_scale: float = 1.0,
    ) -> None:
        super().__init__(scenario)
        self.method = method  # instance attribute: one class serves the six methods
        n = normalizer
        if (n.dy, n.du, n.dx) != (scenario.dy, scenario.du, scenario.dx):
            raise EstimatorError(
                f"{method}: normalisation statistics are for dy={n.dy}, du={n.du}, dx={n.dx}, but scenario "
                f"{scenario.name!r} has dy={scenario.dy}, du={scenario.du}, dx={scenario.dx}"
            )
        self.normalizer = normalizer
        self.device = resolve_device(device)
        self.model = model.to(self.device).eval()  # serving is always eval mode (no dropout)
        self.dtype = next(self.model.parameters()).dtype
        self.has_covariance = _as_bool(covariance, "covariance") and hasattr(model, "step_with_cov")
        self.cov_scale = _as_positive(cov_scale, "cov_scale")
        self.card = dict(card or {})
        self.chunk_timesteps = int(chunk_timesteps)
        self.context, self.context_copies = _as_int(context, "context", 0), _as_int(context_copies, "context_copies", 1)
        self.context_by_copies = bool(self.context) and table.has(method, context="recurrent")  # restarted copies
        if self.context_by_copies and self.context_copies > self.context:
            raise EstimatorError(f"context_copies ({self.context_copies}) must not exceed context ({self.context})")
        if self.context and not self.context_by_copies:
            if not hasattr(self.model, "set_window"):
                raise EstimatorError(
                    f"{method}: context applies to {', '.join(table.names(context='recurrent'))} (restarted "
                    f"copies) and to the attention models {', '.join(table.names(context='window'))} (their window)"
                )
            self.model.set_window(self.context)  # the attention models: the window is the bound
        self._state: Any = None
        self._t = 0  # steps since reset (bounded context: which copies restart)
        self._copies: BatchedCopies | None = None  # the restarted copies (context by copies), made by reset
        step_fn = model.step_with_cov if self.has_covariance else model.step
        self._step_fn = torch.compile(step_fn, dynamic=False) if _as_bool(compile_step, "compile_step") else step_fn
        self.backend = str(backend)
        if self.backend not in BACKENDS:
            raise EstimatorError(f"{method}: backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
        self._ort = self._onnx_step() if self.backend == "onnxruntime" else None

    def _onnx_step(self):
        """The batch-1 step exported from this model and served by ONNX Runtime (models/onnx_step.py);
        with a bounded context by restarted copies, the K copies' step as one batch."""
        from neural_estimator.models.onnx_step import OnnxError, export_step
        from neural_estimator.serving.onnx_runtime import OnnxEstimator, OrtStep

        if not table.has(self.method, exportable=True) or self.dtype != torch.float32:
            raise EstimatorError(
                f"{self.method}: backend onnxruntime serves {', '.join(table.names(exportable=True))} in float32"
            )
        copies = (self.context, self.context_copies) if self.context_by_copies else None
        try:
            graph = OrtStep(export_step(self.model, self.method, covariance=self.has_covariance, copies=copies))
        except OnnxError as exc:
            raise EstimatorError(str(exc)) from None
        return OnnxEstimator(self.scenario, graph, self.normalizer, self.method, self.card, cov_scale=self.cov_scale)

    @property
    def untrained_steps(self) -> int:
        """How many leading steps of a trajectory the model's training loss skipped (the paper's
        warm-up, the card's ``training.recipe.warmup``; 0 when the card does not say). Its estimates
        there were never optimised and can be far off (the ballistic Mamba-2: 13.7 km over steps 0-9,
        0.027 after); the metrics leave those steps out, and the estimator node says so at start-up."""
        recipe = (self.card.get("training") or {}).get("recipe") or {}
        return int(recipe.get("warmup") or 0)

    # ---- streaming -------------------------------------------------------------------------------
    def reset(self, batch: int = 1) -> None:
        batch = int(batch)
        if batch < 1:
            raise EstimatorError(f"{self.method}: batch must be >= 1, got {batch}")
        self.model.eval()
        if self._ort is not None:
            self._ort.reset(batch)
        with torch.inference_mode():
            self._state = self.model.init_state(batch, device=self.device, dtype=self.dtype)
        self._copies = None
        if self.context_by_copies:  # the K copies' states, one batch of K x batch rows
            with torch.inference_mode():
                self._copies = BatchedCopies(
                    self.model, self.context, self.context_copies, batch, self.device, self.dtype
                )
            self._state = None
        self._t = 0
        self.batch = batch
        self.covariance = None
        self.diverged = np.zeros(batch, dtype=bool)
        self.skipped = np.zeros(batch, dtype=bool)

    def step(self, y: np.ndarray, u_prev: np.ndarray | None = None) -> np.ndarray:
        if self._ort is not None:
            return self._step_onnx(y, u_prev)
        y, u_prev = self.check_step(y, u_prev)
        self.start_streams_if_none(y.shape[0])  # the first step after construction starts y's batch
        z, self.skipped = self._inputs(y, u_prev)  # (B, d_in), (B,)
        z_t = torch.as_tensor(z, dtype=self.dtype, device=self.device)
        with torch.inference_mode():
            if self.context_by_copies:
                mean, cov = self._bounded_step(z_t)
            elif self.has_covariance:
                mean, cov, self._state = self._step_fn(z_t, self._state)  # (B, dx), (B, dx, dx)
            else:
                mean, self._state = self._step_fn(z_t, self._state)
        self._t += 1
        x = self.normalizer.denormalize_states(mean.cpu().double().numpy())  # (B, dx) float64
        bad = ~np.all(np.isfinite(x), axis=-1)
        if self.has_covariance:
            self.covariance = self._denormalize_cov(cov)
            bad |= ~np.all(np.isfinite(self.covariance), axis=(-2, -1))
        self.diverged = self.diverged | bad
        return x

    def _step_onnx(self, y: Any, u_prev: Any) -> np.ndarray:
        """:meth:`step` on ONNX Runtime: the torch-free estimator over the exported step does it (one
        arithmetic for both), its flags and covariance mirrored here."""
        ort = self._ort
        x = ort.step(y, u_prev)
        self._t += 1
        self.batch, self.skipped, self.diverged, self.covariance = ort.batch, ort.skipped, ort.diverged, ort.covariance
        return x

    def _bounded_step(self, z_t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """One step of the K copies as one batch (:class:`~neural_estimator.serving.context.BatchedCopies`:
        a copy restarts from a fresh state at o_k + j L); the mean of the copy with the oldest
        restart, s(t) of :mod:`neural_estimator.serving.context`, and that copy's covariance (None
        without one). A covariance head runs on the served copy's rows only."""
        copies = self._copies
        if self.has_covariance and hasattr(self.model, "cov_head"):
            k, (h,) = copies.step(z_t, self._t, self.model.trunk.step_features)
            h = h[copies.rows(k)]
            return self.model.mean_of(h), self.model.cov_head(h)
        k, outs = copies.step(z_t, self._t, self._step_fn)  # (mean,) or (mean, cov) of every row
        rows = copies.rows(k)
        return outs[0][rows], (outs[1][rows] if len(outs) > 1 else None)

    # ---- whole sequences -------------------------------------------------------------------------
    def run(self, Y: np.ndarray, U: np.ndarray | None = None) -> Estimates:
        """Parallel form over whole sequences: Y (B, T, dy), U (B, T, du) -> :class:`Estimates`.

        Equals ``reset(B)`` and a loop of :meth:`step` to float32 round-off. Leaves no open streams
        (call :meth:`reset` before stepping again).
        """
        Y, U = self.check_sequences(Y, U)
        B, T, _ = Y.shape
        dx = self.scenario.dx
        Z, skipped = self._inputs(Y, previous_controls(U))  # (B, T, d_in), (B, T)
        xs = np.empty((B, T, dx))
        covs = np.empty((B, T, dx, dx)) if self.has_covariance else None
        self.model.eval()
        chunk = max(1, self.chunk_timesteps // max(T, 1))
        if T > 0:
            with torch.inference_mode():
                for b0 in range(0, B, chunk):
                    z = torch.as_tensor(Z[b0 : b0 + chunk], dtype=self.dtype, device=self.device)
                    if covs is not None:
                        mean, cov = self._forward_with_cov(z)  # (b, T, dx), (b, T, dx, dx)
                        covs[b0 : b0 + chunk] = self._denormalize_cov(cov)
                    elif self.context_by_copies:
                        mean = bounded_forward(self.model, z, self.context, self.context_copies)  # (b, T, dx)
                    else:
                        mean = self.model(z)  # (b, T, dx)
                    xs[b0 : b0 + chunk] = self.normalizer.denormalize_states(mean.cpu().double().numpy())
        diverged = ~np.all(np.isfinite(xs), axis=(1, 2))
        if covs is not None:
            diverged |= ~np.all(np.isfinite(covs), axis=(1, 2, 3))
        self._state, self._copies, self.batch = None, None, 0
        self.diverged = diverged.copy()
        self.skipped = skipped[:, -1] if T else np.zeros(B, dtype=bool)
        self.covariance = covs[:, -1] if covs is not None and T else None
        return Estimates(xs, covs, diverged)

    def _inputs(self, y: np.ndarray, u_prev: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The normalised z and the skipped flags; an unusable y row is NaN for a model that reads
        missing observations itself (a hybrid predicts without an update), the training mean 0 else."""
        z, skipped = self.normalizer.normalize_inputs(y, u_prev)
        if skipped.any() and getattr(self.model, "reads_missing_observations", False):
            z[skipped, : self.normalizer.dy] = np.nan
        return z, skipped

    def _denormalize_cov(self, cov: torch.Tensor) -> np.ndarray:
        """The model's covariance in state units, times ``cov_scale``."""
        P = self.normalizer.denormalize_covariance(cov.cpu().double().numpy())
        return P if self.cov_scale == 1.0 else self.cov_scale * P

    def _forward_with_cov(self, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The model's mean and covariance over z (b, T, d_in), within the bounded context if set
        (both read from the same copy, as :meth:`step` does)."""
        if not self.context_by_copies:
            return self.model.forward_with_cov(z)
        dx = self.scenario.dx

        def packed(zz: torch.Tensor) -> torch.Tensor:  # mean and covariance side by side: (b, t, dx + dx^2)
            m, c = self.model.forward_with_cov(zz)
            return torch.cat([m, c.flatten(-2)], dim=-1)

        out = bounded_forward(packed, z, self.context, self.context_copies)
        return out[..., :dx], out[..., dx:].unflatten(-1, (dx, dx))

    def __repr__(self) -> str:
        return f"NeuralEstimator({self.method!r}, scenario={self.scenario.name!r}, device={str(self.device)!r})"


def _as_int(v: Any, name: str, minimum: int) -> int:
    try:
        n = parse_value(v, 0, name)
    except OptionError as exc:
        raise EstimatorError(str(exc)) from None
    if n < minimum:
        raise EstimatorError(f"{name} must be >= {minimum}, got {n}")
    return n


def _as_positive(v: Any, name: str) -> float:
    try:
        x = float(parse_value(v, 1.0, name))
    except OptionError as exc:
        raise EstimatorError(str(exc)) from None
    if not (np.isfinite(x) and x > 0):
        raise EstimatorError(f"{name} must be a finite number > 0, got {v!r}")
    return x


def _as_bool(v: Any, name: str = "option") -> bool:
    """Options may arrive as strings from a command line or a node parameter (the package's grammar)."""
    try:
        return parse_bool(v, name)
    except OptionError as exc:
        raise EstimatorError(str(exc)) from None
