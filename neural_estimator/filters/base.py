"""What the four classical filters share: construction checks, the step cycle, divergence, run.

The step cycle (timing convention of :mod:`neural_estimator.scenarios.base`): at step k a filter
receives y_k (B, dy) and u_{k-1} (B, du) and

    k = 0:   updates the prior (m0, P0) with y_0;
    k >= 1:  predicts with u_{k-1}, then updates with y_k;

then returns the posterior mean (B, dx) and leaves the posterior covariance (B, dx, dx) in
``covariance`` (for the EnKF and PF: the ensemble / weighted particle mean and covariance).

Bad input, per stream (row of the batch), never stopping the others:

- a row of y_k with a NaN or inf is not used: that stream only predicts at step k and
  ``skipped[b]`` is True for that step;
- a stream whose mean or covariance goes non-finite, or (UKF) whose covariance cannot be
  Cholesky-factored even with jitter, is flagged in ``diverged[b]``; from then on its outputs are
  NaN until :meth:`reset`. Internally the stream is parked at the prior so
  the batched linear algebra of the other streams never meets a NaN matrix.

Subclasses implement ``_init_state(B)``, ``_predict(u)``, ``_update(y, skip)``, ``_estimate()``,
``_park(mask)`` and, where needed, ``_after_estimate()`` (the PF resamples there).
"""

from __future__ import annotations

import dataclasses
from abc import abstractmethod
from collections.abc import Callable
from typing import Any, ClassVar

import numpy as np

from neural_estimator.methods.interface import Estimates, Estimator, EstimatorError, previous_controls
from neural_estimator.filters import scheduler
from neural_estimator.filters.numerics import ScenarioOps, gaussian, sqrt_factor, symmetrize
from neural_estimator.filters.scheduler import BlockScheduler
from neural_estimator.core.options import OptionError, did_you_mean, is_optional, parse_value
from neural_estimator.scenarios import Scenario

FILTER_INITS = ("prior", "observation")
"""How a filter starts its streams (the ``init`` argument of :class:`ClassicalFilter`):

- ``"prior"`` (default; the paper's start): from the scenario prior, mean m0 and covariance P0
  (the PF's particles N(m0, init_std^2 I), the EnKF's members N(m0, P0)).
- ``"observation"``: at step 0 the mean is replaced, stream by stream, by the state the first
  observation determines where h is invertible on the observed components
  (:meth:`~neural_estimator.scenarios.base.Scenario.state_from_observation`; Lorenz 96, H = I:
  x = y_0; N-link: the angles from the mass positions), the prior mean elsewhere; the covariance
  P0 and the PF's ``init_std`` are unchanged, and y_0 then updates it as usual. What a
  practitioner does when the prior is climatological: the particles start where the truth is.
"""

# Random draws, keyed by (seed, step, phase, block): see ClassicalFilter.block_rng.
PHASE_INIT, PHASE_PREDICT, PHASE_UPDATE, PHASE_RESAMPLE, PHASE_REJUVENATE, PHASE_REGULARIZE = range(6)


def default_threads() -> int:
    """Worker threads for the blocks of streams: $NEURAL_ESTIMATOR_THREADS, else the usable cores."""
    try:
        return scheduler.default_threads()
    except scheduler.ThreadsError as exc:
        raise EstimatorError(str(exc)) from None


def build_hyperparams(cls: type, method: str, hyperparams: Any, options: dict[str, Any]) -> Any:
    """A ``cls`` dataclass from an optional instance plus keyword ``options`` (strings are parsed).

    Unknown names and invalid values are an :class:`EstimatorError` naming the valid fields.
    """
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(options) - set(fields))
    if unknown:
        hint = did_you_mean(unknown[-1], fields)
        raise EstimatorError(f"{method}: unknown option(s) {', '.join(unknown)}{hint}; valid: {', '.join(fields)}")
    base = hyperparams if hyperparams is not None else cls()
    if not isinstance(base, cls):
        raise EstimatorError(f"{method}: hyperparams must be a {cls.__name__}, got {type(base).__name__}")
    values = {}
    for name, value in options.items():  # text parsed by the field's type (neural_estimator.core.options)
        try:
            values[name] = parse_value(value, getattr(base, name), name, optional=is_optional(fields[name].type))
        except OptionError as exc:
            raise EstimatorError(f"{method}: {exc}") from None
    try:
        hp = dataclasses.replace(base, **values)
        hp.validate()
    except (TypeError, ValueError) as exc:
        raise EstimatorError(f"{method}: {exc}") from None
    return hp


def check_covariance(name: str, method: str, cov: Any, n: int, definite: bool = False) -> np.ndarray:
    """A finite, symmetric, positive semi-definite (or definite) (n, n) matrix, else EstimatorError."""
    cov = np.asarray(cov, dtype=np.float64)
    if cov.shape != (n, n):
        raise EstimatorError(f"{method}: {name} must be ({n}, {n}), got {cov.shape}")
    if not np.all(np.isfinite(cov)):
        raise EstimatorError(f"{method}: {name} contains NaN or inf")
    scale = max(float(np.abs(cov).max()), 1e-300)
    if np.abs(cov - cov.T).max() > 1e-9 * scale:
        raise EstimatorError(f"{method}: {name} is not symmetric")
    eig = np.linalg.eigvalsh(symmetrize(cov))
    if eig[0] < -1e-9 * max(abs(eig[-1]), 1e-300):
        raise EstimatorError(f"{method}: {name} is not positive semi-definite (smallest eigenvalue {eig[0]:.3g})")
    if definite and eig[0] <= 0.0:
        raise EstimatorError(f"{method}: {name} must be positive definite (smallest eigenvalue {eig[0]:.3g})")
    return symmetrize(cov)


def check_cov_scale(method: str, value: Any) -> float:
    """The ``cov_scale`` option as a float > 0 (text accepted), else a one-line EstimatorError."""
    from neural_estimator.core.options import OptionError, parse_value

    try:
        s = float(parse_value(value, 1.0, "cov_scale"))
    except OptionError as exc:
        raise EstimatorError(f"{method}: {exc}") from None
    if not (np.isfinite(s) and s > 0):
        raise EstimatorError(f"{method}: cov_scale must be a finite number > 0, got {value!r}")
    return s


class ClassicalFilter(Estimator):
    """Base of the EKF, UKF, EnKF and PF: batched over B streams, float64.

    Args:
        scenario: the system (f, h, Jacobians, Q, R = ``obs_cov()``, prior, angle handling).
        seed: seed of the filter's random draws (EnKF, PF); equal inputs give equal outputs.
        hyperparams: a ``HyperParams`` instance; ``options`` override its fields by name.
        init: how the streams start, ``"prior"`` or ``"observation"`` (:data:`FILTER_INITS`).
        threads: worker threads over blocks of streams (None: :func:`default_threads`). Not a
            hyperparameter: results do not depend on it (see :meth:`block_rng`).
        cov_scale: s > 0, the reported covariance is s P (the filter itself runs on P): a post-hoc
            calibration fitted on validation data (:mod:`neural_estimator.metrics.consistency`,
            ``scripts/calibrate_covariances.py``); 1, the paper's, reports P as it is.

    Blocks and threads. The B streams are processed in blocks of ``block_size`` consecutive
    streams, and the blocks of one phase of a step (predict, update, estimate) run concurrently
    on ``threads`` threads by :class:`~neural_estimator.filters.scheduler.BlockScheduler`, which
    knows nothing of filtering. B = 1, the live node's case, is one block on the calling thread.
    """

    has_covariance: ClassVar[bool] = True
    HyperParams: ClassVar[type]
    require_definite_R: ClassVar[bool] = False
    # Streams are processed in blocks whose largest per-step array (sigma points, members,
    # particles or covariances) holds about this many float64 numbers (1 MiB): the memory-bound
    # elementwise work then runs in cache, about twice as fast at B = 8000 as one pass over the
    # whole batch, and the blocks are the unit of work of the threads.
    block_elements: int = 2**17

    def __init__(
        self,
        scenario: Scenario,
        seed: int = 0,
        hyperparams: Any = None,
        threads: int | str | None = None,
        init: str = "prior",
        cov_scale: float = 1.0,
        **options: Any,
    ) -> None:
        super().__init__(scenario)
        self.init = check_filter_init(self.method, scenario, init)
        self.cov_scale = check_cov_scale(self.method, cov_scale)
        self.hp = build_hyperparams(self.HyperParams, self.method, hyperparams, options)
        self.seed = int(seed)
        self.threads = default_threads() if threads is None else _check_threads(self.method, threads)
        self.ops = ScenarioOps(scenario)
        n, m = scenario.dx, scenario.dy
        m0, P0 = scenario.prior()
        m0 = np.asarray(m0, dtype=np.float64)
        if m0.shape != (n,) or not np.all(np.isfinite(m0)):
            raise EstimatorError(f"{self.method}: prior mean must be {n} finite numbers, got {m0!r}")
        self.m0 = m0
        self.P0 = check_covariance("prior covariance P0", self.method, P0, n)
        self.Q = check_covariance("process noise covariance Q", self.method, scenario.process_cov(), n)
        self.R = check_covariance(
            "observation noise covariance R", self.method, scenario.obs_cov(), m, definite=self.require_definite_R
        )
        q_inflation = getattr(self.hp, "q_inflation", 1.0)
        if q_inflation != 1.0:  # additive inflation: the filter assumes a larger process noise
            self.Q = self.Q * float(q_inflation)
        self._sqrt_Q, self._sd_Q = sqrt_factor(self.Q)
        self._k = 0

    def _start_from_observation(self, y: np.ndarray, finite: np.ndarray) -> None:
        """``init="observation"``, step 0: restart the streams whose y_0 is finite at the state it
        determines (the other components, and the other streams, keep their starting mean)."""
        x, observed = self.scenario.state_from_observation(y)  # (B, n), (n,)
        use = finite[:, None] & observed[None, :] & np.isfinite(x)
        if not use.any():
            return
        self._init_mean = self.ops.normalize_state(np.where(use, x, self._init_mean))
        self._init_state(self.batch)

    # ---- the Estimator contract --------------------------------------------------------------
    def reset(
        self, batch: int = 1, initial_mean: np.ndarray | None = None, initial_cov: np.ndarray | None = None
    ) -> None:
        """Start ``batch`` streams from the prior; the random draws start again from ``seed``.

        ``initial_mean`` (B, n), optional, replaces the prior mean m0 stream by stream (the
        offline protocol's ``init="truth"`` passes the true x_0 there); the prior covariance P0,
        and the PF's ``init_std`` spread, are unchanged. None: every stream starts at m0.
        ``initial_cov`` (B, n, n), optional, replaces P0 (and the PF's spread) stream by stream: the
        EKF/UKF start at it, the EnKF's members and the PF's particles are drawn from
        N(initial mean, initial_cov) (``set_pose`` passes a pose message's covariance there).
        """
        B = int(batch)
        if B < 1:
            raise EstimatorError(f"{self.method}: batch must be >= 1, got {batch}")
        self._init_mean = self._check_initial_mean(initial_mean, B)
        self._init_cov = self._check_initial_cov(initial_cov, B)
        self.batch = B
        self._k = 0
        self.diverged = np.zeros(B, dtype=bool)
        self.skipped = np.zeros(B, dtype=bool)
        self.covariance = None
        self._scheduler = BlockScheduler(B, self.block_size, self.threads, self.seed)
        self._blocks = self._scheduler.blocks
        self._init_state(B)

    def _check_initial_cov(self, initial_cov: np.ndarray | None, B: int) -> np.ndarray | None:
        """(B, n, n) symmetric positive semi-definite starting covariances, or None (P0)."""
        if initial_cov is None:
            return None
        n = self.scenario.dx
        P = np.asarray(initial_cov, dtype=np.float64)
        if P.shape != (B, n, n):
            raise EstimatorError(f"{self.method}: initial_cov must be ({B}, {n}, {n}), got {P.shape}")
        if not np.all(np.isfinite(P)):
            raise EstimatorError(f"{self.method}: initial_cov contains NaN or inf")
        # halves first: P + P^T overflows to inf for entries above 8.9e307 (a finite input)
        P = 0.5 * P + 0.5 * np.swapaxes(P, -1, -2)
        try:
            low = np.linalg.eigvalsh(P)[..., 0]
        except np.linalg.LinAlgError:  # LAPACK gives up on entries near the float range's edge
            raise EstimatorError(f"{self.method}: initial_cov eigenvalues did not converge") from None
        if np.any(~np.isfinite(low)) or np.any(low < -1e-9 * np.maximum(1.0, np.abs(P).max(axis=(-1, -2)))):
            raise EstimatorError(f"{self.method}: initial_cov is not positive semi-definite")
        return P

    def _initial_draws(self, phase: int, N: int, L0: np.ndarray, d0: np.ndarray | None) -> np.ndarray:
        """(B, N, n) zero-mean starting draws of the members / particles: covariance L0 L0^T (the
        prior's), or each stream's ``initial_cov`` when one was given (the same standard normals)."""
        from neural_estimator.filters.numerics import gaussian

        if self._init_cov is None:
            return self._draw_blockwise(phase, lambda rng, rows: gaussian(rng, (rows, N), L0, d0))
        from neural_estimator.scenarios import psd_sqrt

        z = self._draw_blockwise(phase, lambda rng, rows: rng.standard_normal((rows, N, L0.shape[0])))
        L = np.stack([psd_sqrt(P) for P in self._init_cov])  # (B, n, n)
        return np.einsum("bij,bkj->bki", L, z)

    def _initial_cov(self, B: int) -> np.ndarray:
        """(B, n, n) starting covariances: P0, or the ``initial_cov`` given to reset."""
        if self._init_cov is not None:
            return self._init_cov.copy()
        n = self.scenario.dx
        return np.broadcast_to(self.P0, (B, n, n)).copy()

    def _check_initial_mean(self, initial_mean: np.ndarray | None, B: int) -> np.ndarray:
        """(B, n) starting means: m0 for every stream, or ``initial_mean`` checked (finite, shape)."""
        n = self.scenario.dx
        if initial_mean is None:
            return np.broadcast_to(self.m0, (B, n))
        m = np.asarray(initial_mean, dtype=np.float64)
        if m.shape != (B, n):
            raise EstimatorError(f"{self.method}: initial_mean must be ({B}, {n}), got {m.shape}")
        if not np.all(np.isfinite(m)):
            raise EstimatorError(f"{self.method}: initial_mean contains NaN or inf")
        return self.ops.normalize_state(m)

    @property
    def block_size(self) -> int:
        """Streams per block: ``block_elements`` over the largest per-stream array, at least 1.

        It does not depend on B, so stream b always falls in block b // block_size.
        """
        return max(1, int(self.block_elements) // max(1, int(self._stream_elements())))

    def block_rng(self, block: int, phase: int) -> np.random.Generator:
        """The generator of one block's draws in one phase of the current step.

        Keyed by (seed, step k, phase, block index) through a SeedSequence, so the numbers do not
        depend on the order in which threads run the blocks, nor on how many threads there are.
        Draws of shape (rows, ...) fill row after row, so stream b receives the same numbers in a
        batch of any size B > b: a stream's result depends on the seed and its index only.
        (SFC64: the fastest of numpy's generators for normal draws, a fifth faster than PCG64 here.)
        """
        return self._scheduler.rng(self._k, phase, block)

    def _draw_blockwise(self, phase: int, draw: Callable[[np.random.Generator, int], np.ndarray]) -> np.ndarray:
        """(B, ...) draws assembled from ``draw(rng, rows)`` block by block (on the calling thread)."""
        return self._scheduler.draw(self._k, phase, draw)

    def step(self, y: np.ndarray, u_prev: np.ndarray | None = None) -> np.ndarray:
        """One step for B streams: (B, dy) y_k and (B, du) u_{k-1} -> (B, dx) posterior mean.

        With no streams started, it first resets to the batch size of ``y`` (the interface's rule).
        """
        y, u = self.check_step(y, u_prev)
        self.start_streams_if_none(y.shape[0])
        mean, cov = self._advance(np.ascontiguousarray(y), np.ascontiguousarray(u))
        self.covariance = cov if self.cov_scale == 1.0 else self.cov_scale * cov
        return mean

    def run(self, Y: np.ndarray, U: np.ndarray | None = None, initial_mean: np.ndarray | None = None) -> Estimates:
        """Filter whole sequences (B, T, dy), (B, T, du): equal to ``reset`` and a loop of ``step``.

        Inputs are validated once for the whole sequence, and the estimates are written straight
        into the output arrays; the arithmetic per step is the very same as :meth:`step`'s.
        ``initial_mean`` (B, n) goes to :meth:`reset` (None: start from the prior mean).
        """
        Y, U = self.check_sequences(Y, U)
        B, T, _ = Y.shape
        n = self.scenario.dx
        self.reset(B, initial_mean)
        Uprev = previous_controls(U)
        xs = np.empty((B, T, n))
        covs = np.empty((B, T, n, n))
        for k in range(T):
            mean, cov = self._advance(np.ascontiguousarray(Y[:, k]), np.ascontiguousarray(Uprev[:, k]))
            xs[:, k] = mean
            covs[:, k] = cov
            self.covariance = covs[:, k]
        if self.cov_scale != 1.0:
            covs *= self.cov_scale
        return Estimates(xs, covs, self.diverged.copy())

    # ---- one step ------------------------------------------------------------------------------
    def _advance(self, y: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # A diverging stream overflows by definition; it is reported through ``diverged``, so
        # numpy's floating-point warnings (from the filter and the scenario's f and h) are off.
        with np.errstate(over="ignore", invalid="ignore", divide="ignore", under="ignore"):
            return self._advance_checked(y, u)

    def _advance_checked(self, y: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        finite = np.isfinite(y).all(axis=1)
        skip = None
        if not finite.all():
            skip = ~finite
            y = np.where(finite[:, None], y, 0.0)  # placeholder; these rows' updates are discarded
        self.skipped = ~finite
        if self._k == 0 and self.init == "observation":
            self._start_from_observation(y, finite)
        ok = self._predict_update(u, y, skip)
        self._k += 1
        mean, cov = self._estimate()
        # One pass each: a sum is non-finite iff an entry is (or the entries reach ~1e308, which
        # counts as divergence too).
        bad = ~(np.isfinite(mean.sum(axis=1)) & np.isfinite(cov.sum(axis=(1, 2))))
        if ok is not None:
            bad |= ~ok
        if bad.any():
            self.diverged |= bad
            self._park(bad)
        self._after_estimate()
        if self.diverged.any():
            d = self.diverged
            mean = np.where(d[:, None], np.nan, mean)
            cov = np.where(d[:, None, None], np.nan, cov)
        else:
            mean = mean.copy()
        cov.flags.writeable = False  # the filter's own array: read it, copy it, never write it
        return mean, cov

    # ---- scheduling: the block scheduler of the current batch (filters/scheduler.py) -------------
    def _for_blocks(self, kernel: Callable[[int, slice], Any]) -> list:
        return self._scheduler.for_each(kernel)

    def _blockwise(self, kernel, *arrays: np.ndarray, phase: int | None = None) -> tuple:
        """:meth:`BlockScheduler.blockwise`; with ``phase`` the kernel gets the block's generator of
        that phase of this step (:meth:`block_rng`) as ``rng=``."""
        rng_for = None if phase is None else (lambda i: self.block_rng(i, phase))
        return self._scheduler.blockwise(kernel, *arrays, rng_for=rng_for)

    def _stream_elements(self) -> int:
        """float64 numbers in the largest per-stream array of a step (sets the block size)."""
        n = self.scenario.dx
        return n * max(n, self.scenario.dy)

    def _predict_update(self, u: np.ndarray, y: np.ndarray, skip: np.ndarray | None) -> np.ndarray | None:
        """Predict (k >= 1), then update the rows not in ``skip``; per-stream ok flags or None.

        A filter may override it to do both in one pass over the blocks (the UKF does).
        """
        ok = None
        if self._k > 0:
            ok = _and(ok, self._predict(u))
        if skip is None or not skip.all():
            ok = _and(ok, self._update(y, skip))
        return ok

    @abstractmethod
    def _init_state(self, B: int) -> None:
        """Set the internal state of B streams to the prior."""

    @abstractmethod
    def _predict(self, u: np.ndarray) -> np.ndarray | None:
        """Time update with u_{k-1} (B, du); returns per-stream ok flags (B,) or None (all ok)."""

    @abstractmethod
    def _update(self, y: np.ndarray, skip: np.ndarray | None) -> np.ndarray | None:
        """Measurement update with y_k (B, dy); rows with ``skip`` keep their predicted state.

        Returns per-stream ok flags (B,) or None (all ok); skipped rows count as ok.
        """

    @staticmethod
    def _keep(skip: np.ndarray | None, old: np.ndarray, new: np.ndarray) -> np.ndarray:
        """``new`` with the rows of ``skip`` taken from ``old`` (any trailing shape)."""
        if skip is None:
            return new
        return np.where(skip.reshape((-1,) + (1,) * (new.ndim - 1)), old, new)

    @abstractmethod
    def _estimate(self) -> tuple[np.ndarray, np.ndarray]:
        """Current posterior mean (B, n) and covariance (B, n, n)."""

    @abstractmethod
    def _park(self, mask: np.ndarray) -> None:
        """Reset the internal state of the streams in ``mask`` (B,) to finite prior values."""

    def _after_estimate(self) -> None:
        """Hook after the estimate of a step is taken (the PF resamples here)."""

    def _broadcast_u(self, u: np.ndarray, N: int) -> np.ndarray:
        """u (B, du) as a (B, N, du) view for members, particles or sigma points."""
        return np.broadcast_to(u[:, None, :], (u.shape[0], N, u.shape[1]))


def compiled_applies(limit: int | None, batch: int) -> bool:
    """Whether a filter's compiled kernels run a batch of ``batch`` streams under its
    ``compiled_max_batch`` ``limit``: None, every batch; an int k, batches of at most k (0: never)."""
    return limit is None or batch <= limit


def observation_determines_state(scenario: Scenario) -> bool:
    """True when one observation determines some state components (``init="observation"`` applies)."""
    m0 = np.asarray(scenario.prior()[0], dtype=np.float64)
    with np.errstate(all="ignore"):
        return scenario.state_from_observation(scenario.h(m0[None])) is not None


def check_filter_init(method: str, scenario: Scenario, init: str) -> str:
    """``init`` if it is one of :data:`FILTER_INITS` and usable on ``scenario``, else a one-line
    EstimatorError (``"observation"`` needs an h invertible on some observed component)."""
    if init not in FILTER_INITS:
        raise EstimatorError(f"{method}: init must be one of {', '.join(FILTER_INITS)}, got {init!r}")
    if init == "observation" and not observation_determines_state(scenario):
        raise EstimatorError(
            f"{method}: init=observation needs an observation that determines some state components; "
            f"{scenario.name}'s h is invertible on none (use init=prior)"
        )
    return init


def _check_threads(where: str, threads: int | str) -> int:
    """``threads`` as an int >= 1 (strings from the command line parse), else EstimatorError."""
    try:
        return scheduler.check_threads(where, threads)
    except scheduler.ThreadsError as exc:
        raise EstimatorError(str(exc)) from None


def check_inflation(inflation: float, q_inflation: float) -> None:
    """Multiplicative (``inflation``) and additive (``q_inflation``) covariance inflation factors:
    finite numbers > 0 (1 = none; < 1 deflates, allowed for experiments); else ValueError."""
    for name, value in (("inflation", inflation), ("q_inflation", q_inflation)):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 < value < float("inf"):
            raise ValueError(f"{name} must be a finite number > 0, got {value!r}")


def _and(ok: np.ndarray | None, new: np.ndarray | None) -> np.ndarray | None:
    if new is None:
        return ok
    return new if ok is None else ok & new


class MemberFilter(ClassicalFilter):
    """Shared part of the sampling filters (EnKF members, PF particles): ``self._X`` (B, N, dx)
    propagated through the model with process noise, N = ``self.N``."""

    N: int

    def _stream_elements(self) -> int:
        s = self.scenario
        return max(self.N * max(s.dx, s.dy), s.dx * s.dx)

    def _predict(self, u: np.ndarray) -> None:
        self._X, _ = self._blockwise(self._predict_block, self._X, u, phase=PHASE_PREDICT)

    def _predict_block(self, X: np.ndarray, u: np.ndarray, rng: np.random.Generator):
        """x^i_{k+1} = f(x^i_k, u_k) + w^i_k,  w^i_k ~ N(0, Q), for every member i."""
        X = self.scenario.f(X, self._broadcast_u(u, self.N))
        X += gaussian(rng, X.shape[:2], self._sqrt_Q, self._sd_Q)
        return self.ops.normalize_state(X), None
