"""Paired comparisons of two methods on the same trajectories: the ratio of their RMSE and its
bootstrap interval.

Every method of an evaluation sees the same trajectories, so the fair question "is A better than
B?" is asked of the *pair* (A's error, B's error) on each trajectory. The per-trajectory squared
errors of one run are kept as :class:`TrajectoryErrors`; :func:`paired_ratio` then resamples
trajectories (the same draw for both methods: the pairing) and, where a method has several trained
instances, instances too.

With runs r = (set j, instance k), each run's RMSE over its kept trajectories K_r is

    RMSE_r = sqrt( sum_{n in K_r} c_n M_{r,n} / sum_{n in K_r} c_n )

where M_{r,n} is trajectory n's mean squared error (over steps and the components asked for) and
c_n = 1 on the data (a bootstrap replicate draws N trajectories with replacement, c_n the times
trajectory n is drawn: c ~ Multinomial(N, 1/N), one draw per set shared by every method). The
summary is the paper's: the median of RMSE_r over runs. The ratio is median_r RMSE_r(A) /
median_r RMSE_r(B); its 95 % interval is the 2.5 and 97.5 percentiles of the ratio over
replicates (percentile bootstrap). Which trajectories a run keeps (the outlier rule) is the run's
own and is not re-decided in a replicate; ``full=True`` scores every trajectory (the Full RMSE).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from neural_estimator.core.angles import wrap_components
from neural_estimator.metrics.checks import MetricsError, check_pair

BOOTSTRAP_REPLICATES = 1000
BOOTSTRAP_SEED = 0  # the replicates' stream: fixed, so a table is reproducible to the digit
CONFIDENCE = 0.95
# A component is "estimated" when some method's RMSE on it is below this share of the open-loop
# baseline's (better by 10 %); otherwise no method does better than a model without sensors.
ESTIMATED_BELOW = 0.9


@dataclass(frozen=True, eq=False)
class TrajectoryErrors:
    """One run's per-trajectory errors: ``mse`` (N, dx) the mean over scored steps of each
    component's squared error, ``kept`` (N,) the trajectories the outlier rule keeps."""

    mse: np.ndarray
    kept: np.ndarray

    def values(self, components: Sequence[int] | None = None) -> np.ndarray:
        """(N,) M_n over ``components`` (all when None)."""
        m = self.mse if components is None else self.mse[:, list(components)]
        with np.errstate(over="ignore", invalid="ignore"):
            return m.mean(axis=1)


def trajectory_errors(
    x_true: np.ndarray,
    x_hat: np.ndarray,
    angle_states: Sequence[int],
    outlier_idx: np.ndarray,
    warmup: int = 0,
    labelled: np.ndarray | None = None,
) -> TrajectoryErrors:
    """:class:`TrajectoryErrors` of one run: errors after ``warmup`` steps (angles wrapped),
    kept = not in ``outlier_idx`` (the report's, diverged included). ``labelled`` (N, T) bool:
    each trajectory's MSE over its labelled steps (:mod:`neural_estimator.metrics.labelled`); a
    trajectory with none after the warm-up is not kept (that report did not score it)."""
    x_true, x_hat = check_pair(x_true, x_hat)
    e = wrap_components(x_hat[:, warmup:] - x_true[:, warmup:], tuple(angle_states))
    kept = np.ones(x_true.shape[0], dtype=bool)
    if labelled is not None and not np.all(labelled):
        m = np.asarray(labelled, dtype=bool)[:, warmup:]
        count = m.sum(axis=1)
        with np.errstate(over="ignore", invalid="ignore"):
            mse = np.where(m[..., None], e * e, 0.0).sum(axis=1) / np.maximum(count, 1)[:, None]
        kept &= count > 0
    else:
        with np.errstate(over="ignore", invalid="ignore"):
            mse = np.mean(e * e, axis=1)  # (N, dx)
    kept[np.asarray(outlier_idx, dtype=np.int64)] = False
    return TrajectoryErrors(mse, kept)


def run_rmse(errors: TrajectoryErrors, components: Sequence[int] | None = None, full: bool = False) -> float:
    """The run's RMSE on the data (no resampling): equal to the report's ``rmse`` (``full``: its
    ``full_rmse``), or to ``rmse_components[d]`` for ``components=[d]``."""
    m = errors.values(components)
    keep = np.ones_like(errors.kept) if full else errors.kept
    if not keep.any():
        return math.inf
    with np.errstate(over="ignore", invalid="ignore"):
        return float(np.sqrt(m[keep].mean()))


def paired_ratio(
    method: Sequence[Sequence[TrajectoryErrors]],
    reference: Sequence[Sequence[TrajectoryErrors]],
    components: Sequence[int] | None = None,
    full: bool = False,
    replicates: int = BOOTSTRAP_REPLICATES,
    seed: int = BOOTSTRAP_SEED,
    confidence: float = CONFIDENCE,
) -> tuple[float, tuple[float, float]]:
    """(ratio, (lo, hi)): median-over-runs RMSE of ``method`` over that of ``reference``, and its
    paired percentile-bootstrap interval (see the module docstring).

    Args:
        method, reference: ``[set j][instance k]`` runs; both have the same sets, in the same order,
            on the same trajectories (the pairing).
        components: the state components scored (None: all, the paper's aggregate).
        full: score every trajectory (the Full RMSE) instead of the kept ones.

    A method whose RMSE is infinite (it diverged: every trajectory dropped, or ``full`` with a
    diverged one) against a finite reference gives (inf, (inf, inf)), judged "worse"; a zero or
    infinite reference gives NaN and the interval (NaN, NaN).
    """
    point, ratios = _paired(method, reference, components, full, replicates, seed)
    return point, _interval(point, ratios, confidence)


def paired_geometric_ratio(
    method: Sequence[Sequence[TrajectoryErrors]],
    reference: Sequence[Sequence[TrajectoryErrors]],
    components: Sequence[int],
    full: bool = False,
    replicates: int = BOOTSTRAP_REPLICATES,
    seed: int = BOOTSTRAP_SEED,
    confidence: float = CONFIDENCE,
) -> tuple[float, tuple[float, float]]:
    """(G, (lo, hi)): the geometric mean over ``components`` E of the per-component ratios,

        G = exp( 1/|E| sum_{d in E} log( RMSE_d(method) / RMSE_d(reference) ) ),

    each RMSE_d the median over runs of component d's RMSE, with its paired percentile-bootstrap
    interval: every replicate draws the same trajectories and instances for every component (the
    draws depend on the seed and the sizes only), so G is formed per replicate. Unlike the RMSE over
    those components together, G weighs each component alike whatever its units: an altitude error
    in metres does not drown a velocity error in m/s. One component gives :func:`paired_ratio`'s.

    A component on which the method diverged and the reference did not makes G infinite; one
    without a ratio (a zero or infinite reference) makes it NaN."""
    if not components:
        raise MetricsError("a geometric mean of component ratios needs at least one component")
    points, columns = [], []
    for d in components:
        point, ratios = _paired(method, reference, [d], full, replicates, seed)
        points.append(point)
        columns.append(ratios)
    if any(math.isnan(p) for p in points):
        return math.nan, (math.nan, math.nan)
    if any(p == math.inf for p in points):
        return math.inf, (math.inf, math.inf)
    point = float(np.exp(np.mean(np.log(points))))
    with np.errstate(divide="ignore", invalid="ignore"):
        logs = np.log(np.stack(columns))  # (|E|, B): each replicate's ratios, aligned over components
    return point, _interval(point, np.exp(logs.mean(axis=0)), confidence)


def _paired(method, reference, components, full: bool, replicates: int, seed: int) -> tuple[float, np.ndarray]:
    """The ratio on the data and its (B,) replicates (empty where the ratio is not finite; a
    diverged method against a finite reference: inf and no replicates)."""
    if len(method) != len(reference) or not method:
        raise MetricsError(f"paired runs need the same sets: {len(method)} against {len(reference)}")
    for a, b in zip(method, reference):
        if not a or not b or a[0].mse.shape[0] != b[0].mse.shape[0]:
            raise MetricsError("paired runs need at least one run per set, on the same trajectories")
    for side in (method, reference):
        # a replicate draws its instances once for every set, so each set must hold the same ones
        if len({len(instances) for instances in side}) != 1:
            counts = [len(instances) for instances in side]
            raise MetricsError(f"paired runs need the same trained instances in every set, got {counts} per set")
    num, den = _median_rmse(method, components, full, None, None), _median_rmse(reference, components, full, None, None)
    point = num / den if den > 0 else math.nan  # a perfect reference (RMSE 0) has no ratio
    if point == math.inf and math.isfinite(den):  # the method diverged where the reference did not
        return math.inf, np.empty(0)
    if not math.isfinite(point):
        return math.nan, np.empty(0)
    counts = _trajectory_draws(tuple(s[0].mse.shape[0] for s in method), replicates, seed)
    rng = np.random.default_rng([seed, 1])  # the instance draws: their own stream, after the trajectories'
    pick_a = rng.integers(0, len(method[0]), size=(replicates, len(method[0])))
    pick_b = rng.integers(0, len(reference[0]), size=(replicates, len(reference[0])))
    with np.errstate(divide="ignore", invalid="ignore"):
        ratios = _median_rmse(method, components, full, counts, pick_a) / _median_rmse(
            reference, components, full, counts, pick_b
        )
    return point, ratios


def _interval(point: float, ratios: np.ndarray, confidence: float) -> tuple[float, float]:
    """The percentile interval of the finite replicates; (inf, inf) for a diverged method, NaN
    where no replicate is finite."""
    if point == math.inf:
        return math.inf, math.inf
    ratios = ratios[np.isfinite(ratios)]
    if not math.isfinite(point) or ratios.size == 0:
        return math.nan, math.nan
    tail = 50.0 * (1.0 - confidence)
    lo, hi = np.percentile(ratios, [tail, 100.0 - tail])
    return float(lo), float(hi)


@functools.lru_cache(maxsize=4)
def _trajectory_draws(sizes: tuple[int, ...], replicates: int, seed: int) -> tuple[np.ndarray, ...]:
    """The replicates' trajectory counts, (B, N) float64 per set: Multinomial(N, 1/N) draws from
    ``seed``. Kept for the next call: every method of a table is compared on the same draws, and
    drawing them is most of a comparison's cost (B N numbers per set)."""
    rng = np.random.default_rng(seed)
    out = []
    for n in sizes:
        # N draws with replacement per replicate, counted: the multinomial counts, 20x faster than
        # Generator.multinomial over N categories
        idx = rng.integers(0, n, size=(replicates, n)) + (np.arange(replicates) * n)[:, None]
        c = np.bincount(idx.ravel(), minlength=replicates * n).reshape(replicates, n).astype(np.float64)
        c.flags.writeable = False
        out.append(c)
    return tuple(out)


def _median_rmse(runs, components, full: bool, counts, picks):
    """Median over runs of the RMSE, on the data (``counts`` None: a float) or per replicate
    (``counts[j]`` (B, N) per set, ``picks`` (B, K) instance draws: a (B,) array)."""
    per_set = []
    for j, instances in enumerate(runs):
        vals = []
        for run in instances:
            m = run.values(components)
            keep = np.ones_like(run.kept) if full else run.kept
            m = np.where(keep, m, 0.0)
            if counts is None:
                with np.errstate(over="ignore", invalid="ignore"):
                    vals.append(np.sqrt(m.sum() / keep.sum()) if keep.any() else np.inf)
            else:
                c = counts[j]
                with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
                    vals.append(np.sqrt((c @ m) / (c @ keep.astype(np.float64))))
        per_set.append(vals)
    if counts is None:
        return float(np.median([v for vals in per_set for v in vals]))
    # (B, J, K): instance k of a replicate is the drawn one, the same draw on every set
    stacked = np.stack([np.stack(vals, axis=1) for vals in per_set], axis=1)  # (B, J, K)
    chosen = np.take_along_axis(stacked, picks[:, None, :].repeat(stacked.shape[1], axis=1), axis=2)
    return np.median(chosen.reshape(chosen.shape[0], -1), axis=1)


def verdict(ci95: tuple[float, float]) -> str:
    """ "better" when the whole interval is below 1, "worse" when above, "tied" when it holds 1
    (and "unknown" without an interval)."""
    lo, hi = ci95
    if lo == math.inf:  # a diverged method against a finite reference
        return "worse"
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return "unknown"
    if hi < 1.0:
        return "better"
    if lo > 1.0:
        return "worse"
    return "tied"


def estimated_components(component_rmse: dict[str, Sequence[float]], baseline: Sequence[float]) -> list[bool]:
    """Per component, whether some method's RMSE (``component_rmse`` {method: [RMSE_d]}, the
    baselines left out by the caller) is below :data:`ESTIMATED_BELOW` x the open-loop baseline's."""
    out = []
    for d, b in enumerate(baseline):
        best = min((float(v[d]) for v in component_rmse.values()), default=math.inf)
        out.append(bool(math.isfinite(b) and best < ESTIMATED_BELOW * b))
    return out
