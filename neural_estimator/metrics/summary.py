"""Metrics across runs: the paper's "median ± IQR" of each metric (:func:`summarize`) and the
JSON form of reports and summaries (:func:`to_json`)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from neural_estimator.metrics.definitions import SCALAR_METRICS, MetricReport


# ---- across runs ------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Stat:
    """Median and interquartile range of one metric across runs (evaluation sets x instances)."""

    median: float
    iqr: float  # q75 - q25
    n: int  # values that were available (NaN left out)
    max: float  # largest value (shows a divergence that the median hides)
    applies: bool = True  # False: the metric does not apply to the method (no covariance)


def median_iqr(values: Iterable[float]) -> tuple[float, float]:
    """(median, q75 - q25) of ``values``, safe with inf; NaN values are left out.

    Quantiles use linear interpolation between order statistics (numpy's default method), written
    so that inf stays inf: [1, 2, inf] has median 2 and IQR inf, [inf, inf] has median inf and
    IQR 0. With no value left the result is (NaN, NaN).
    """
    v = np.sort(np.array([_as_float(x) for x in values], dtype=np.float64))
    v = v[~np.isnan(v)]
    if v.size == 0:
        return math.nan, math.nan
    q25, med, q75 = (_quantile(v, p) for p in (0.25, 0.5, 0.75))
    return med, (0.0 if q75 == q25 else q75 - q25)


def summarize(reports: Iterable[MetricReport | Mapping[str, Any]]) -> dict[str, Stat]:
    """Median and IQR of each scalar metric across runs, the paper's "median ± IQR".

    Args:
        reports: :class:`MetricReport` objects, or mappings of metric name to value such as the
            output of :func:`to_json` (null is read back as NaN; a key that is null in every run,
            or absent, does not apply).

    Returns:
        {metric: Stat} for every metric of :data:`SCALAR_METRICS`, always the same keys; a metric
        with no value in any run (NEES of a neural method) has ``applies=False`` and NaN numbers.
    """
    rows = [r.scalars() if isinstance(r, MetricReport) else r for r in reports]
    out: dict[str, Stat] = {}
    for key in SCALAR_METRICS:
        vals = [_as_float(r[key]) for r in rows if r.get(key) is not None]
        if not vals:
            out[key] = Stat(median=math.nan, iqr=math.nan, n=0, max=math.nan, applies=False)
            continue
        med, iqr = median_iqr(vals)
        avail = [x for x in vals if not math.isnan(x)]
        out[key] = Stat(median=med, iqr=iqr, n=len(avail), max=max(avail) if avail else math.nan)
    return out


def to_json(obj: Any) -> Any:
    """A JSON-ready copy of a :class:`MetricReport`, :class:`Stat`, summary or nested container.

    Strict JSON (``json.dumps(..., allow_nan=False)`` accepts it): arrays become lists, numpy
    scalars Python scalars, and every non-finite number becomes null. A report always has every
    key (the schema is in docs/metrics.md); null means "no finite value": the metric does not
    apply (covariance metrics of a method without covariance: ``has_covariance`` is false), is
    unavailable (the paper's N/A), or is infinite; which one is told by the report's own fields
    (``n_diverged`` > 0 for an infinite Full RMSE or NRMSE, ``all_diverged`` for the rest,
    ``cov_degenerate`` for an infinite NEES). Never a string.
    """
    if isinstance(obj, MetricReport):
        out = {f.name: to_json(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
        out["has_covariance"] = obj.has_covariance
        return out
    if isinstance(obj, Stat):
        return {f.name: to_json(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, Mapping):
        return {str(k): to_json(v) for k, v in obj.items()}
    if isinstance(obj, np.ndarray):
        return to_json(obj.tolist())
    if isinstance(obj, (list, tuple)):
        return [to_json(v) for v in obj]
    if isinstance(obj, np.generic):
        return to_json(obj.item())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def _quantile(v: np.ndarray, p: float) -> float:
    """Linear-interpolation quantile of sorted, NaN-free ``v``; inf-safe."""
    h = (v.size - 1) * p
    lo, hi = math.floor(h), math.ceil(h)
    a, b, w = float(v[lo]), float(v[hi]), h - lo
    if w == 0 or a == b:
        return a
    return a + w * (b - a)


def _as_float(x) -> float:
    """Metric value as float: None -> NaN, "inf"/"-inf"/"nan" strings (older results files) as floats."""
    if x is None:
        return math.nan
    return float(x)


def _as_stat(v) -> Stat:
    if v is None:
        return Stat(median=math.nan, iqr=math.nan, n=0, max=math.nan, applies=False)
    if isinstance(v, Stat):
        return v
    if isinstance(v, (tuple, list)):
        med, iqr = _as_float(v[0]), _as_float(v[1])
        return Stat(median=med, iqr=iqr, n=1, max=med)
    x = _as_float(v)
    return Stat(median=x, iqr=0.0, n=1, max=x)
