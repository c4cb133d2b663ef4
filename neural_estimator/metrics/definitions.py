"""Evaluation metrics of the paper (Section "Evaluation Metrics", Appendix "Full Evaluation Metrics"):
the per-run definitions (errors, outlier rule, RMSE-time curve, AUC, drift, NRMSE, NEES, coverage)
and :func:`compute_metrics`, which makes one :class:`MetricReport` of a run.

Shapes, one convention everywhere:
    x_true, x_hat   (N, T, dx)       N trajectories, T timesteps, dx state components
    e               (N, T, dx)       estimation errors x_hat - x_true, angles wrapped to (-pi, pi]
    P_hat           (N, T, dx, dx)   estimated error covariances (optional)
    M               (N,)             trajectory-level MSE
    rmse_t          (T,)             RMSE-time curve

The definitions where the paper is silent, the scored steps (:data:`EVALUATION_WARMUP`) and the
reasons for each reading are in docs/metrics.md; each is documented again where it is computed.
Summaries across runs are in :mod:`neural_estimator.metrics.summary`, tables in
:mod:`neural_estimator.metrics.table`.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from neural_estimator.core.angles import wrap_components
from neural_estimator.metrics.checks import MetricsError, check_curve, check_errors, check_pair
from neural_estimator.metrics.outliers import OUTLIER_Z, outlier_mask

COVERAGE_LEVEL = 0.95
_NEES_CHUNK = 1 << 16  # (n, t) pairs per batched Cholesky, bounds the temporaries
# A covariance whose smallest conditional-to-marginal variance ratio (1 - R^2 of one component on
# the ones before it) is below this is numerically singular: its inverse is round-off. Scale-free,
# so components in different units (ballistic: km and a drag coefficient) do not trip it.
DEGENERATE_RCOND = 1e-10
# Leading timesteps the evaluation protocol does not score (the paper's warm-up; see the module
# docstring, "Effective trajectory length"). Equal to neural_estimator.data.protocol.WARMUP_STEPS.
EVALUATION_WARMUP = 10

# Scalar metrics of a report, in table order. Keys are used by summarize, format_table and to_json.
SCALAR_METRICS = (
    "rmse",
    "full_rmse",
    "nrmse",
    "nrmse_spread",
    "mae",
    "medae",
    "auc",
    "outlier_ratio",
    "drift_ratio",
    "diverged_ratio",
    "nees_median",
    "nees",
    "coverage95",
    "cov_degenerate",
)
# Metrics that only apply to methods that report a covariance (None for the others).
COVARIANCE_METRICS = ("nees_median", "nees", "coverage95", "cov_degenerate")


# ---- errors and per-trajectory quantities ---------------------------------------------------------


def errors(x_true: np.ndarray, x_hat: np.ndarray, angle_states: Sequence[int] = ()) -> np.ndarray:
    """Estimation errors e = x_hat - x_true with the angle components wrapped to (-pi, pi].

    An angle error of 2 pi - 0.1 is an error of -0.1. Non-finite estimates give non-finite errors
    (NaN or inf) without warnings; they mark the trajectory as diverged downstream.

    Args:
        x_true: (N, T, dx) true states, finite.
        x_hat: (N, T, dx) estimates; may hold NaN or inf.
        angle_states: components of the last axis that are angles.

    Returns:
        (N, T, dx) float64 errors.
    """
    x_true, x_hat = check_pair(x_true, x_hat)
    with np.errstate(invalid="ignore", over="ignore"):
        return wrap_components(x_hat - x_true, tuple(angle_states))  # (N, T, dx)


def diverged_mask(x_hat: np.ndarray) -> np.ndarray:
    """(N,) True for trajectories with any non-finite estimate (NaN or +-inf) at any step."""
    x_hat = np.asarray(x_hat)
    if x_hat.ndim != 3:
        raise MetricsError(f"x_hat must be (N, T, dx), got shape {x_hat.shape}")
    return ~np.isfinite(x_hat).all(axis=(1, 2))


def trajectory_mse(e: np.ndarray) -> np.ndarray:
    """Trajectory-level MSE, the paper's M_n: M_n = (1 / (T dx)) sum_t sum_d e_{n,t,d}^2.

    Args:
        e: (N, T, dx) errors.

    Returns:
        (N,) M_n; inf or NaN for diverged trajectories (overflow gives inf, no warning).
    """
    e = check_errors(e)
    with np.errstate(over="ignore", invalid="ignore"):
        return np.mean(e * e, axis=(1, 2))


def rmse_over_time(e: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """RMSE-time curve: RMSE_t = sqrt( (1 / (|K| dx)) sum_{n in K} sum_d e_{n,t,d}^2 ).

    Args:
        e: (N, T, dx) errors.
        mask: (N,) bool, True for the trajectories K to average over (default: all).

    Returns:
        (T,) RMSE_t; NaN everywhere if the mask selects no trajectory.
    """
    e = check_errors(e)
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != e.shape[:1]:
            raise MetricsError(f"mask must be ({e.shape[0]},), got {mask.shape}")
        e = e[mask]
    if e.shape[0] == 0:
        return np.full(e.shape[1], np.nan)
    with np.errstate(over="ignore", invalid="ignore"):
        return np.sqrt(np.mean(e * e, axis=(0, 2)))  # (T,)


# ---- outlier rule -----------------------------------------------------------------------------------


def drift_ratio(rmse_t: np.ndarray) -> float:
    """Mean RMSE over the last quarter divided by the mean over the first quarter.

    Paper: "To measure long-horizon error accumulation, we compute a drift ratio from the RMSE-time
    curve. Let T be the effective trajectory length and RMSE_t the per-timestep RMSE. We divide the
    trajectory into quarters and compare the mean RMSE in the final quarter to that in the first
    quarter. With q = max(1, floor(T/4)),

        drift_ratio = ( (1/q) sum_{t=T-q+1}^{T} RMSE_t ) / ( (1/q) sum_{t=1}^{q} RMSE_t )."

    A zero denominator gives inf (or NaN when the numerator is 0 too), without warnings.

    Args:
        rmse_t: (T,) RMSE-time curve, T >= 1.
    """
    rmse_t = check_curve(rmse_t)
    q = max(1, rmse_t.shape[0] // 4)
    with np.errstate(divide="ignore", invalid="ignore"):
        return float(np.float64(rmse_t[-q:].mean()) / np.float64(rmse_t[:q].mean()))


def auc(rmse_t: np.ndarray) -> float:
    """Area under the RMSE-time curve: trapezoid rule with a unit timestep.

    AUC = sum_{t=1}^{T-1} (RMSE_t + RMSE_{t+1}) / 2 = sum_t RMSE_t - (RMSE_1 + RMSE_T) / 2,
    0 for T = 1. The unit is "RMSE x steps", which matches the paper's tables (AUC ~ T x RMSE).

    Args:
        rmse_t: (T,) RMSE-time curve, T >= 1.
    """
    rmse_t = check_curve(rmse_t)
    return float(np.sum(0.5 * (rmse_t[1:] + rmse_t[:-1])))


def state_spread(x_true: np.ndarray) -> np.ndarray:
    """Per-component spread of the true state, the NRMSE normaliser.

    s_d = population standard deviation of x_true[n, t, d] over all trajectories n and times t.
    Angle components are taken as stored, in (-pi, pi].

    Args:
        x_true: (N, T, dx) true states.

    Returns:
        (dx,) s_d.
    """
    x_true = np.asarray(x_true, dtype=np.float64)
    if x_true.ndim != 3:
        raise MetricsError(f"x_true must be (N, T, dx), got shape {x_true.shape}")
    return x_true.std(axis=(0, 1))


def nees(e: np.ndarray, P_hat: np.ndarray) -> np.ndarray:
    """Normalised estimation error squared, eps_{n,t} = e_{n,t}^T P_{n,t}^{-1} e_{n,t}.

    Computed as ||L^{-1} e||^2 with P = L L^T (Cholesky of the symmetrised P), never with an
    inverse. For a consistent estimator with Gaussian errors eps ~ chi^2(dx), so its mean is dx.
    A *degenerate* covariance gives eps = inf: not finite, not positive definite, or numerically
    singular, i.e. min_i L_ii^2 / P_ii < DEGENERATE_RCOND. L_ii^2 / P_ii is the variance of
    component i given components 0..i-1 over its own variance (the Cholesky pivots of the
    correlation matrix D^-1/2 P D^-1/2, D = diag P); it is 0 exactly when component i is a linear
    function of the earlier ones, as for a particle cloud collapsed onto fewer than dx + 1 points.
    Such a matrix's "inverse" is round-off, and the NEES it gives (1e12 and more) says nothing.

    Args:
        e: (N, T, dx) errors.
        P_hat: (N, T, dx, dx) estimated error covariances.

    Returns:
        (N, T) NEES values.
    """
    e = check_errors(e)
    P_hat = np.asarray(P_hat, dtype=np.float64)
    n, t, dx = e.shape
    if P_hat.shape != (n, t, dx, dx):
        raise MetricsError(f"P_hat must be {(n, t, dx, dx)}, got {P_hat.shape}")
    e_flat = e.reshape(n * t, dx)  # (K, dx)
    P_flat = P_hat.reshape(n * t, dx, dx)  # (K, dx, dx)
    out = np.full(n * t, np.inf)
    for start in range(0, n * t, _NEES_CHUNK):
        sl = slice(start, start + _NEES_CHUNK)
        out[sl] = _nees_chunk(e_flat[sl], P_flat[sl])
    return out.reshape(n, t)


def _nees_chunk(e: np.ndarray, P: np.ndarray) -> np.ndarray:
    """NEES of (K, dx) errors under (K, dx, dx) covariances; inf where P is unusable."""
    res = np.full(e.shape[0], np.inf)
    ok = np.isfinite(P).all(axis=(1, 2)) & np.isfinite(e).all(axis=1)
    if not ok.any():
        return res
    P_ok = 0.5 * (P[ok] + np.swapaxes(P[ok], -1, -2))
    e_ok = e[ok]
    try:
        L = np.linalg.cholesky(P_ok)  # (K', dx, dx)
        res[ok] = np.where(_singular(L, P_ok), np.inf, _whitened_sq(L, e_ok))
    except np.linalg.LinAlgError:
        # Some matrix is not positive definite: find which, one at a time (rare, slow path).
        vals = np.full(e_ok.shape[0], np.inf)
        for k in range(e_ok.shape[0]):
            try:
                L = np.linalg.cholesky(P_ok[k])
            except np.linalg.LinAlgError:
                continue
            if not _singular(L[None], P_ok[k][None])[0]:
                vals[k] = _whitened_sq(L[None], e_ok[k][None])[0]
        res[ok] = vals
    return res


def _singular(L: np.ndarray, P: np.ndarray) -> np.ndarray:
    """(K,) True where min_i L_ii^2 / P_ii < DEGENERATE_RCOND (see :func:`nees`)."""
    d = np.diagonal(L, axis1=-2, axis2=-1)  # (K, dx)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = d * d / np.diagonal(P, axis1=-2, axis2=-1)
    return ~(ratio.min(axis=-1) >= DEGENERATE_RCOND)  # NaN (P_ii = 0) counts as singular


def _whitened_sq(L: np.ndarray, e: np.ndarray) -> np.ndarray:
    """||L^{-1} e||^2 for (K, dx, dx) lower-triangular L and (K, dx) e."""
    w = np.linalg.solve(L, e[..., None])[..., 0]  # (K, dx)
    return np.sum(w * w, axis=-1)


# ---- one evaluation ---------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class MetricReport:
    """Metrics of one method on one evaluation set. See the module docstring for definitions.

    Scalars are plain Python floats; inf marks divergence, NaN an unavailable statistic.
    """

    rmse: float  # sqrt(mean e^2) over kept trajectories, all t, d
    full_rmse: float  # same over all trajectories; inf if any diverged
    nrmse: float  # mean over all trajectories of the per-trajectory RMSE of e_d / s_d; inf if any diverged
    nrmse_spread: float  # RMSE of e_d / s_d over kept trajectories (the previous NRMSE)
    mae: float  # mean |e| over kept trajectories, all t, d
    medae: float  # median |e| over kept trajectories, all t, d
    auc: float  # trapezoid area under rmse_t, unit timestep
    drift_ratio: float  # last-quarter / first-quarter mean of rmse_t
    outlier_ratio: float  # flagged (diverged included) / N
    diverged_ratio: float  # diverged / N
    n_trajectories: int
    n_outliers: int  # diverged included
    n_diverged: int
    all_diverged: bool
    rmse_t: np.ndarray  # (T,) RMSE-time curve over kept trajectories
    spread: np.ndarray  # (dx,) NRMSE normaliser s_d
    outlier_idx: np.ndarray  # (n_outliers,) trajectory indices, diverged included
    diverged_idx: np.ndarray  # (n_diverged,) trajectory indices
    # Covariance metrics: None when the method reports no covariance (does not apply).
    nees_median: float | None = None  # median e^T P^-1 e over kept (n, t); degenerate P count as inf
    nees: float | None = None  # mean e^T P^-1 e over kept (n, t) with a usable P; inf if none is usable
    coverage95: float | None = None  # share of kept (n, t) with NEES <= chi2_{dx}(0.95); degenerate P: not covered
    cov_degenerate: float | None = None  # share of kept (n, t) whose P is degenerate (see nees())
    warmup: int = 0  # leading timesteps not evaluated: rmse_t[k] is the RMSE of step warmup + k
    # RMSE over every step (warm-up included, the outlier rule applied on every step's M_n): the
    # figure beside ``rmse`` when steps are left out; equal to ``rmse`` when warmup = 0. None:
    # a result stored before this field existed.
    rmse_every_step: float | None = None
    # Reliability curve: coverage of the chi-square region at each nominal level of
    # neural_estimator.metrics.consistency.RELIABILITY_LEVELS (None without covariance, or a
    # result stored before this field existed).
    coverage_curve: tuple[float, ...] | None = None
    # RMSE of each state component over the kept trajectories, in the component's own units:
    # sqrt( (1 / (|K| T)) sum_{n in K, t} e_{n,t,d}^2 ), so rmse^2 = mean_d rmse_components[d]^2.
    # None: a result stored before this field existed.
    rmse_components: tuple[float, ...] | None = None
    # The reliability curve over every trajectory, outliers and diverged ones included (a step with
    # a non-finite NEES counts as not covered): the coverage a user gets, beside the kept-only
    # ``coverage_curve`` the paper's outlier rule gives. None without covariance.
    coverage_curve_all: tuple[float, ...] | None = None
    nees_median_all: float | None = None  # median NEES over every (n, t), outliers included (non-finite: inf)
    # Partial ground truth (metrics.labelled): the (n, t) after the warm-up scored and those without
    # ground truth, not scored. None: every step labelled.
    scored_steps: int | None = None
    unlabelled_steps: int | None = None

    @property
    def has_covariance(self) -> bool:
        return self.nees_median is not None

    def scalars(self) -> dict[str, float | None]:
        """Every metric of :data:`SCALAR_METRICS`, None for the covariance ones without P_hat."""
        return {k: getattr(self, k) for k in SCALAR_METRICS}


def compute_metrics(
    x_true: np.ndarray,
    x_hat: np.ndarray,
    angle_states: Sequence[int] = (),
    spread: np.ndarray | float | None = None,
    P_hat: np.ndarray | None = None,
    diverged: np.ndarray | None = None,
    threshold: float = OUTLIER_Z,
    nees_values: np.ndarray | None = None,
    warmup: int = 0,
) -> MetricReport:
    """All metrics of one method on one evaluation set.

    With e the errors (angles wrapped), M_n the trajectory MSE, K the kept trajectories (not
    flagged by :func:`outlier_mask`; diverged ones are always flagged) and |K| their number:

        RMSE      = sqrt( (1 / (|K| T dx)) sum_{n in K, t, d} e_{n,t,d}^2 )
        Full RMSE = sqrt( (1 / (N T dx))   sum_{n, t, d}       e_{n,t,d}^2 ),  inf if any diverged
        NRMSE     = (1 / N) sum_n sqrt( (1 / (T dx)) sum_{t, d} (e_{n,t,d} / s_d)^2 ),  inf if any diverged
        NRMSE_spread = sqrt( (1 / (|K| T dx)) sum_{n in K, t, d} (e_{n,t,d} / s_d)^2 )
        MAE       = mean   { |e_{n,t,d}| : n in K }
        MedAE     = median { |e_{n,t,d}| : n in K }
        RMSE_t    = sqrt( (1 / (|K| dx)) sum_{n in K, d} e_{n,t,d}^2 )
        RMSE_d    = sqrt( (1 / (|K| T)) sum_{n in K, t} e_{n,t,d}^2 ),  so RMSE^2 = (1/dx) sum_d RMSE_d^2
        AUC       = sum_{t=1}^{T-1} (RMSE_t + RMSE_{t+1}) / 2
        drift     = mean(RMSE_{T-q+1..T}) / mean(RMSE_{1..q}),  q = max(1, floor(T/4))
        NEES med. = median { eps_{n,t} = e^T P^{-1} e : n in K, all t },  ~dx for a consistent estimator
        NEES      = mean { eps_{n,t} : n in K, P_{n,t} usable }
        95%       = share of kept (n, t) with eps_{n,t} <= chi2_{dx}^{-1}(0.95)
        coverage_curve_all = the same share at each reliability level over every (n, t), outliers included
        Degen.    = share of kept (n, t) whose P_{n,t} is degenerate (eps = inf, see :func:`nees`)

    T, t and the sums run over the evaluated steps, warmup..T_total-1 (``warmup`` = 0: every
    step). s_d is :func:`state_spread` of the evaluated ``x_true`` unless ``spread`` is given.

    Args:
        x_true: (N, T, dx) true states, finite.
        x_hat: (N, T, dx) estimates; NaN or inf marks a diverged trajectory.
        angle_states: components that are angles (errors wrapped to (-pi, pi]).
        spread: (dx,) or scalar NRMSE normaliser, positive; default :func:`state_spread`.
        P_hat: (N, T, dx, dx) estimated covariances, for NEES and coverage.
        diverged: (N,) extra divergence flags (e.g. ``Estimates.diverged``), OR-ed with the
            non-finite test; a flagged trajectory is excluded like any diverged one.
        threshold: the outlier z-score threshold (paper: 6).
        nees_values: (N, T) precomputed e^T P^-1 e (see :func:`nees`), instead of ``P_hat``: lets a
            caller evaluate chunk by chunk without holding (N, T, dx, dx) covariances.
        warmup: leading timesteps left out of every metric (the protocol uses
            :data:`EVALUATION_WARMUP`); 0 <= warmup < T. Divergence is still judged on every step.

    Returns:
        A :class:`MetricReport`. If every trajectory diverged: RMSE, NRMSE, MAE, MedAE, AUC and the
        curve are inf, drift ratio, outlier ratio and the covariance metrics NaN, ``all_diverged``.

    Raises:
        MetricsError: wrong shapes, non-finite ground truth, a spread that is not positive, or a
            warm-up that leaves no step to evaluate.
    """
    x_true, x_hat = check_pair(x_true, x_hat)
    warmup, every_step, x_true, x_hat, P_hat, nees_values, diverged = _cut_warmup(
        warmup, x_true, x_hat, angle_states, P_hat, nees_values, diverged, threshold
    )
    n, t, dx = x_true.shape
    if not np.isfinite(x_true).all():
        raise MetricsError("x_true holds non-finite values; ground truth must be finite")
    s = _resolve_spread(x_true, spread)  # (dx,)

    e = errors(x_true, x_hat, angle_states)  # (N, T, dx)
    with np.errstate(over="ignore", invalid="ignore"):
        sq = e * e  # (N, T, dx)
        Md = sq.mean(axis=1)  # (N, dx) per-trajectory, per-component MSE
    M = Md.mean(axis=1)  # (N,) the paper's M_n
    div, out = _flags(x_hat, M, diverged, threshold)
    kept = ~out
    common = report_fields(M, Md, s, div, out, warmup, every_step)
    if not kept.any():  # every trajectory diverged: explicit inf / NaN, no crash
        return all_diverged_report(t, dx, P_hat is not None or nees_values is not None, common)

    msd = Md[kept].mean(axis=0)  # (dx,) MSE per component over kept trajectories (rmse = rmse_kept)
    abs_e = np.abs(e[kept])  # (|K|, T, dx)
    rmse_t = np.sqrt(sq[kept].mean(axis=(0, 2)))  # (T,)
    return MetricReport(
        rmse=float(np.sqrt(msd.mean())),
        nrmse_spread=float(np.sqrt(np.mean(msd / s**2))),
        mae=float(abs_e.mean()),
        medae=float(np.median(abs_e)),
        auc=auc(rmse_t),
        drift_ratio=drift_ratio(rmse_t),
        outlier_ratio=int(out.sum()) / n,
        rmse_t=rmse_t,
        rmse_components=tuple(float(v) for v in np.sqrt(msd)),
        **_covariance_part(e, P_hat, nees_values, kept),
        **common,
    )


def _cut_warmup(warmup, x_true, x_hat, angle_states, P_hat, nees_values, diverged, threshold) -> tuple:
    """The warm-up checked and left out: (warmup, the every-step RMSE or None, x_true, x_hat, P_hat,
    nees_values, diverged) from step ``warmup`` on (see :func:`_after_warmup`)."""
    t = x_true.shape[1]
    if isinstance(warmup, bool) or int(warmup) != warmup or not 0 <= int(warmup) < t:
        raise MetricsError(f"warmup must be an integer in [0, {t}) for {t} timesteps, got {warmup!r}")
    warmup = int(warmup)
    if not warmup:
        return warmup, None, x_true, x_hat, P_hat, nees_values, diverged
    every_step = kept_rmse(errors(x_true, x_hat, angle_states), diverged, threshold)
    return (warmup, every_step, *_after_warmup(warmup, x_true, x_hat, P_hat, nees_values, diverged))


def _flags(x_hat: np.ndarray, M: np.ndarray, diverged, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """(diverged, outlier) masks (N,): non-finite estimates, overflowing M_n or a caller's flag
    diverge; a diverged trajectory is always an outlier."""
    n = M.shape[0]
    div = diverged_mask(x_hat) | ~np.isfinite(M)  # overflowing squared errors are divergence too
    if diverged is not None:
        extra = np.asarray(diverged, dtype=bool)
        if extra.shape != (n,):
            raise MetricsError(f"diverged must be ({n},), got {extra.shape}")
        div = div | extra
    M_rule = np.where(div, np.inf, M)  # diverged -> non-finite -> always flagged
    return div, outlier_mask(M_rule, threshold)


def report_fields(M, Md, s, div, out, warmup: int, every_step: float | None) -> dict:
    """The report's fields computed alike whether or not any trajectory is kept (``M`` (N,) the M_n,
    ``Md`` (N, dx), ``s`` the spread, ``div`` and ``out`` the diverged and outlier masks); the
    in-memory and the streaming scorer share them."""
    n, kept, n_div = M.shape[0], ~out, int(div.sum())
    rmse_kept = math.inf if not kept.any() else float(np.sqrt(Md[kept].mean(axis=0).mean()))
    return dict(
        full_rmse=math.inf if n_div else float(np.sqrt(M.mean())),
        nrmse=math.inf if n_div else trajectory_mean_nrmse(Md, s),
        diverged_ratio=n_div / n,
        n_trajectories=n,
        n_outliers=int(out.sum()),
        n_diverged=n_div,
        all_diverged=n_div == n,
        spread=s,
        outlier_idx=np.flatnonzero(out),
        diverged_idx=np.flatnonzero(div),
        warmup=warmup,
        rmse_every_step=rmse_kept if every_step is None else every_step,
    )


def all_diverged_report(t: int, dx: int, has_p: bool, common: dict) -> MetricReport:
    """The report when no trajectory is kept: inf errors, NaN ratios (covariance metrics NaN if any)."""
    na = math.nan if has_p else None
    return MetricReport(
        rmse=math.inf,
        nrmse_spread=math.inf,
        mae=math.inf,
        medae=math.inf,
        auc=math.inf,
        drift_ratio=math.nan,
        outlier_ratio=math.nan,
        rmse_t=np.full(t, np.inf),
        nees_median=na,
        nees=na,
        coverage95=na,
        cov_degenerate=na,
        rmse_components=(math.inf,) * dx,
        **common,
    )


def _covariance_part(e: np.ndarray, P_hat, nees_values, kept: np.ndarray) -> dict[str, float | None]:
    """The covariance metrics from ``P_hat`` or precomputed ``nees_values`` (all None without either)."""
    n, t, dx = e.shape
    cov_metrics: dict[str, float | None] = dict.fromkeys(COVARIANCE_METRICS)
    if P_hat is not None:
        P_hat = np.asarray(P_hat, dtype=np.float64)
        if P_hat.shape != (n, t, dx, dx):
            raise MetricsError(f"P_hat must be {(n, t, dx, dx)}, got {P_hat.shape}")
        nees_values = nees(e, P_hat) if nees_values is None else nees_values
    if nees_values is not None:
        nees_values = np.asarray(nees_values, dtype=np.float64)
        if nees_values.shape != (n, t):
            raise MetricsError(f"nees_values must be {(n, t)}, got {nees_values.shape}")
        cov_metrics = covariance_metrics(nees_values[kept], dx)
        every = np.where(np.isnan(nees_values), np.inf, nees_values)  # a step without a NEES is not covered
        cov_metrics["coverage_curve_all"] = _coverage_curve(every, dx)
        cov_metrics["nees_median_all"] = float(np.median(every))
    return cov_metrics


def _after_warmup(warmup: int, x_true, x_hat, P_hat, nees_values, diverged) -> tuple:
    """(x_true, x_hat, P_hat, nees_values, diverged) from step ``warmup`` on. A trajectory that
    diverged during the warm-up stays diverged; then steps warmup.. only are scored."""
    n, t, dx = x_true.shape
    early = diverged_mask(x_hat[:, :warmup])
    diverged = early if diverged is None else (np.asarray(diverged, dtype=bool) | early)
    if diverged.shape != (n,):
        raise MetricsError(f"diverged must be ({n},), got {diverged.shape}")
    if P_hat is not None:
        P_hat = np.asarray(P_hat)
        if P_hat.shape != (n, t, dx, dx):
            raise MetricsError(f"P_hat must be {(n, t, dx, dx)}, got {P_hat.shape}")
        P_hat = P_hat[:, warmup:]
    if nees_values is not None:
        nees_values = np.asarray(nees_values)
        if nees_values.shape != (n, t):
            raise MetricsError(f"nees_values must be {(n, t)}, got {nees_values.shape}")
        nees_values = nees_values[:, warmup:]
    return x_true[:, warmup:], x_hat[:, warmup:], P_hat, nees_values, diverged


def kept_rmse(e: np.ndarray, diverged: np.ndarray | None = None, threshold: float = OUTLIER_Z) -> float:
    """The main RMSE of errors ``e`` (N, T, dx) on their own steps: sqrt of the mean M_n over the
    trajectories the outlier rule keeps (``diverged`` (N,) and non-finite M_n always flagged);
    inf when none is kept. :func:`compute_metrics` uses it for ``rmse_every_step``."""
    e = check_errors(e)
    with np.errstate(over="ignore", invalid="ignore"):
        M = np.mean(e * e, axis=(1, 2))  # (N,)
    div = ~np.isfinite(M)
    if diverged is not None:
        extra = np.asarray(diverged, dtype=bool)
        if extra.shape != M.shape:
            raise MetricsError(f"diverged must be ({M.shape[0]},), got {extra.shape}")
        div = div | extra
    kept = ~outlier_mask(np.where(div, np.inf, M), threshold)
    return float(np.sqrt(M[kept].mean())) if kept.any() else math.inf


def trajectory_mean_nrmse(Md: np.ndarray, spread: np.ndarray) -> float:
    """The paper-matching NRMSE: (1/N) sum_n sqrt( mean_d Md[n, d] / s_d^2 ).

    Args:
        Md: (N, dx) per-trajectory, per-component MSE (1/T) sum_t e_{n,t,d}^2, all trajectories.
        spread: (dx,) s_d > 0.

    Returns:
        The mean over trajectories of each one's spread-normalised RMSE (see the module docstring
        for why a mean over all trajectories and not an RMS over the kept ones).
    """
    with np.errstate(over="ignore", invalid="ignore"):
        per_traj = np.sqrt(np.mean(Md / spread**2, axis=1))  # (N,)
    return float(per_traj.mean())


def covariance_metrics(eps: np.ndarray, dx: int) -> dict[str, float]:
    """NEES median, NEES mean over usable covariances, 95 % coverage and degenerate share.

    Args:
        eps: (K, T) NEES of the kept trajectories, inf where the covariance is degenerate.
        dx: state dimension (the chi-square degrees of freedom).
    """
    from scipy.special import chdtri  # chi2.ppf(q, k) = chdtri(k, 1 - q); scipy.stats takes seconds to import

    usable = np.isfinite(eps)
    return dict(
        nees_median=float(np.median(eps)),  # inf only when over half the steps are degenerate
        nees=float(eps[usable].mean()) if usable.any() else math.inf,
        coverage95=float(np.mean(eps <= chdtri(dx, 1.0 - COVERAGE_LEVEL))),
        cov_degenerate=float(1.0 - usable.mean()),
        coverage_curve=_coverage_curve(eps, dx),
    )


def _coverage_curve(eps: np.ndarray, dx: int) -> tuple[float, ...]:
    """Coverage at every reliability level (:mod:`neural_estimator.metrics.consistency`)."""
    from neural_estimator.metrics.consistency import coverage_curve

    return tuple(float(c) for c in coverage_curve(eps, dx))


# ---- helpers ------------------------------------------------------------------------------------------


def _resolve_spread(x_true: np.ndarray, spread) -> np.ndarray:
    dx = x_true.shape[-1]
    s = state_spread(x_true) if spread is None else np.broadcast_to(np.asarray(spread, dtype=np.float64), (dx,))
    bad = ~(np.isfinite(s) & (s > 0))
    if bad.any():
        where = "given spread" if spread is not None else "true state (pass spread= explicitly)"
        raise MetricsError(
            f"NRMSE spread must be positive and finite; components {np.flatnonzero(bad).tolist()} of the {where}"
        )
    return np.array(s)
