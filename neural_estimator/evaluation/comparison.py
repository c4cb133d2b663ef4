"""What a team decides on, from one evaluation's results: the error of every state component, the
reference (the best filter), each method's paired RMSE ratio to it with a 95 % interval, and which
components any method estimates at all.

- **Components.** ``rmse_components``: per state component, the median over runs of the run's
  RMSE on that component (in its own units), the same summary as the aggregate ``rmse``.
- **Reference.** The classical filter with the smallest median RMSE (the paper's aggregate; when
  ``full`` the Full RMSE); with no filter evaluated, the best of the ranked methods. Baselines are
  reference rows, never ranked and never the reference.
- **Paired ratio.** :func:`~neural_estimator.metrics.paired_ratio` of each method to the
  reference, over trajectories (and instances); verdict better / tied / worse by whether the
  interval lies below 1, holds 1, or lies above 1.
- **Estimated components.** A component is "not estimated" when no ranked method's RMSE on it is
  below 0.9 x the open-loop baseline's (:data:`~neural_estimator.metrics.paired.ESTIMATED_BELOW`);
  known only when ``openloop`` was evaluated.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from neural_estimator import metrics as M
from neural_estimator.methods import table

if TYPE_CHECKING:
    from neural_estimator.evaluation.protocol import MethodResult


def component_stats(result: MethodResult) -> list[M.Stat] | None:
    """Median and IQR over runs of each component's RMSE (None when no run carries them)."""
    runs = [r.rmse_components for r in result.reports if r.rmse_components is not None]
    if not runs:
        return None
    out = []
    for d in range(len(runs[0])):
        med, iqr = M.median_iqr(v[d] for v in runs)
        finite = [v[d] for v in runs if not math.isnan(v[d])]
        out.append(M.Stat(median=med, iqr=iqr, n=len(finite), max=max(finite) if finite else math.nan))
    return out


def ranked(results: Mapping[str, MethodResult]) -> dict[str, MethodResult]:
    """The methods that are ranked: every result but the baselines, with runs."""
    return {m: r for m, r in results.items() if r.reports and not r.baseline}


def reference_method(results: Mapping[str, MethodResult], full: bool = False) -> str | None:
    """The best classical filter by median RMSE (``full``: Full RMSE), else the best ranked method;
    None when nothing is ranked or no RMSE is finite."""
    key = "full_rmse" if full else "rmse"
    pool = ranked(results)
    filters = {m: r for m, r in pool.items() if table.has(m, family="classical")}
    pool = filters or pool
    scored = {m: r.summary[key].median for m, r in pool.items()}
    scored = {m: v for m, v in scored.items() if math.isfinite(v)}
    return min(scored, key=scored.get) if scored else None


def paired(
    results: Mapping[str, MethodResult], full: bool = False, components: list[int] | None = None
) -> dict[str, dict[str, Any] | None]:
    """{method: {reference, ratio, ci95: [lo, hi], verdict, instances}} for every method (baselines
    included, as reference rows); None for a method without per-trajectory errors, on other
    sets than the reference, or whose sets do not yet hold the same instances (a partial result,
    written while an evaluation runs)."""
    ref = reference_method(results, full=full)
    out: dict[str, dict[str, Any] | None] = {}
    if ref is None or not results[ref].errors:
        return {m: None for m in results}
    ref_runs = results[ref].runs_by_set()
    for m, r in results.items():
        runs = r.runs_by_set() if r.errors else []
        if len(runs) != len(ref_runs) or any(a[0].mse.shape != b[0].mse.shape for a, b in zip(runs, ref_runs)):
            out[m] = None
            continue
        try:
            ratio, ci = M.paired_ratio(runs, ref_runs, components=components, full=full)
        except M.MetricsError:  # uneven instances: a partial result, paired once it is complete
            out[m] = None
            continue
        out[m] = {
            "reference": ref,
            "ratio": ratio,
            "ci95": list(ci),
            "verdict": "reference" if m == ref else M.verdict(ci),
            "instances": r.n_instances,
        }
    return out


def not_estimated(results: Mapping[str, MethodResult]) -> list[bool] | None:
    """Per component, True when no ranked method beats the open-loop baseline on it by 10 %; None
    without an ``openloop`` result."""
    base = results.get("openloop")
    if base is None or not base.reports:
        return None
    base_stats = component_stats(base)
    rows = {m: component_stats(r) for m, r in ranked(results).items()}
    rows = {m: [s.median for s in v] for m, v in rows.items() if v is not None}
    if base_stats is None or not rows:
        return None
    est = M.estimated_components(rows, [s.median for s in base_stats])
    return [not e for e in est]


def instance_spread(result: MethodResult, key: str = "rmse") -> list[float]:
    """Per trained instance, the median over evaluation sets of ``key``: the spread that the median
    over instances summarises (one value for a single instance)."""
    by_instance: dict[int, list[float]] = {}
    for rep, k in zip(result.reports, result.instance or [0] * len(result.reports)):
        by_instance.setdefault(k, []).append(float(getattr(rep, key)))
    return [M.median_iqr(v)[0] for _, v in sorted(by_instance.items())]


def outlier_rule_flips(results: Mapping[str, MethodResult]) -> bool:
    """True when ranking the ranked methods by RMSE and by Full RMSE gives a different best."""
    return reference_method(results) != reference_method(results, full=True) or _best(results, "rmse") != _best(
        results, "full_rmse"
    )


def _best(results: Mapping[str, MethodResult], key: str) -> str | None:
    scored = {m: r.summary[key].median for m, r in ranked(results).items()}
    scored = {m: v for m, v in scored.items() if math.isfinite(v)}
    return min(scored, key=scored.get) if scored else None
