"""What the evaluation protocol prints and writes: the per-scenario table with its departure marks
and legend, and results.json (:data:`RESULTS_SCHEMA`)."""

from __future__ import annotations

import json

import numpy as np
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from neural_estimator.paper import departures as D
from neural_estimator import metrics as M
from neural_estimator.scenarios import Scenario

if TYPE_CHECKING:
    from neural_estimator.evaluation.protocol import MethodResult


def results_table(results: Mapping[str, MethodResult], fmt: str = "markdown", marked: bool = False) -> str:
    """The paper's per-scenario table (median +- IQR over runs) for these results; ``marked``: rows
    and cells that depart from the paper's protocol carry their marks (:func:`departure_marks`)."""
    summaries = {m: r.summary for m, r in results.items()}
    if not marked:
        return M.format_table(summaries, fmt=fmt)
    rows, cells, _ = departure_marks(results)
    named = D.marked_names(summaries, rows)
    return M.format_table(
        {named[m]: s for m, s in summaries.items()}, fmt=fmt, marks={named[m]: c for m, c in cells.items()}
    )


def departure_marks(
    results: Mapping[str, MethodResult],
) -> tuple[dict[str, list[str]], dict[str, dict[str, str]], set[str]]:
    """(row marks {method: [mark]}, cell marks {method: {metric: mark}}, every mark used): [c] for a
    bounded context, [t] / [y] for filters started from the truth / the first observation, [o] on the
    RMSE when the outlier rule decides it (:mod:`neural_estimator.paper.departures`)."""
    rows: dict[str, list[str]] = {}
    cells: dict[str, dict[str, str]] = {}
    used: set[str] = set()
    for m, r in results.items():
        marks = D.row_marks(m, context=r.context, init=r.init)
        if marks:
            rows[m] = marks
            used.update(marks)
        if r.reports:
            s = r.summary
            if D.rests_on_outliers(s["rmse"].median, s["full_rmse"].median):
                cells[m] = {"rmse": D.OUTLIERS}
                used.add(D.OUTLIERS)
    return rows, cells, used


def departure_legend(results: Mapping[str, MethodResult], extra: set[str] = frozenset()) -> list[str]:
    """The legend of the marks :func:`results_table` prints for ``results`` (plus ``extra`` marks)."""
    _, _, used = departure_marks(results)
    return D.legend_text(used | set(extra), [r.context for r in results.values()])


RESULTS_SCHEMA = "neural_estimator.results/2"  # results.json's "schema"; see docs/metrics.md


def results_json(scenario: Scenario, results: Mapping[str, MethodResult], **info: Any) -> dict[str, Any]:
    """Everything measured, strict-JSON-ready (schema :data:`RESULTS_SCHEMA`, docs/metrics.md).

    Every method has the same keys: its ``summary`` has every metric of
    :data:`~neural_estimator.metrics.SCALAR_METRICS` (``applies`` false and null numbers for the
    covariance metrics of a method without covariance), each run in ``runs`` has every report key.
    Beside them (:mod:`~neural_estimator.evaluation.comparison`): ``rmse_components`` (one summary
    per state component, in state order), ``paired`` and ``paired_full`` (the ratio of the RMSE,
    resp. Full RMSE, to the reference's with its 95 % interval), ``instances`` and
    ``reference_row`` (a baseline, never ranked); at the top, the ``components`` and which are
    ``not_estimated``.
    """
    from neural_estimator.evaluation import comparison as C

    pairs, pairs_full = C.paired(results), C.paired(results, full=True)
    return M.to_json(
        {
            "schema": RESULTS_SCHEMA,
            "scenario": scenario.describe(),
            **info,
            "components": list(scenario.state_names),
            "not_estimated": C.not_estimated(results),
            "reference": C.reference_method(results),
            "methods": {
                m: {
                    "summary": r.summary,
                    "runs": r.reports,
                    "cached_runs": r.cached,
                    "context": r.context,
                    "start": r.init,
                    "marks": D.row_marks(m, context=r.context, init=r.init)
                    + (
                        [D.OUTLIERS]
                        if r.reports and D.rests_on_outliers(r.summary["rmse"].median, r.summary["full_rmse"].median)
                        else []
                    ),
                    "seconds": r.seconds,
                    "trajectory_steps_per_second": r.throughput,
                    "rmse_components": C.component_stats(r),
                    "paired": pairs.get(m),
                    "paired_full": pairs_full.get(m),
                    "reference_row": r.baseline,
                    "model_set": r.model_set,
                    "instances": {
                        "count": r.n_instances,
                        "rmse_per_instance": C.instance_spread(r) if r.reports else [],
                        "checkpoints": r.instance_dirs,
                    },
                }
                for m, r in results.items()
            },
        }
    )


def write_evaluation(
    out: Path, scenario: Scenario, results, info: dict[str, Any], expected_runs: dict[str, int], plot: bool
) -> None:
    """table.md, table.csv, decision.md, consistency.md and results.json of the runs so far in ``out``
    (``complete`` says whether all
    ``expected_runs`` {method: runs} are in), and with ``plot`` the RMSE-time figure."""

    done = {m: r for m, r in results.items() if r.reports}
    complete = all(len(results[m].reports) == n for m, n in expected_runs.items())
    out.mkdir(parents=True, exist_ok=True)
    _, _, used = departure_marks(done)
    legend = [f"- {line}" for line in D.legend(used, [r.context for r in done.values()])]
    (out / "table.md").write_text(
        results_table(done, fmt="markdown", marked=True)
        + "".join(f"\n{line}" for line in legend)
        + f"\n\n{D.scored_steps(info.get('warmup', 0))}\n"
    )
    (out / "table.csv").write_text(_with_model(results_table(done, fmt="csv"), scenario, done))
    from neural_estimator.evaluation.decision import decision_notes, decision_table

    decision = decision_table(scenario, done, fmt="markdown")
    if decision:
        (out / "decision.md").write_text(
            decision + "".join(f"\n- {line}" for line in decision_notes(scenario, done)) + "\n"
        )
    consistency = consistency_table(done, scenario.dx)
    if consistency:
        (out / "consistency.md").write_text(consistency)
    payload = results_json(scenario, done, complete=complete, **info)
    tmp = out / "results.json.tmp"
    tmp.write_text(json.dumps(payload, indent=1, allow_nan=False))
    tmp.replace(out / "results.json")
    if plot:
        from neural_estimator.metrics.plots import plot_rmse_over_time

        plot_rmse_over_time(
            {m: [rep.rmse_t for rep in r.reports] for m, r in done.items()},
            out / "rmse_over_time.png",
            title=scenario.name,
            dt=scenario.dt,
            first_step=info.get("warmup", 0),
        )


def _with_model(csv: str, scenario: Scenario, results: Mapping[str, MethodResult]) -> str:
    """The table's CSV with two more columns: the data scenario's ``preset`` and the ``model_set``
    each method was built with (``name=value`` items joined by ``;``; empty: the true model)."""
    lines = csv.splitlines()
    if not lines:
        return csv
    preset = str(scenario.describe().get("preset", "custom"))
    out = [lines[0] + ",preset,model_set"]
    for line in lines[1:]:
        r = results.get(line.split(",", 1)[0])
        told = ";".join(f"{k}={v}" for k, v in (r.model_set if r is not None else {}).items())
        out.append(f"{line},{preset},{told}")
    return "\n".join(out) + "\n"


def consistency_table(results: Mapping[str, MethodResult], dx: int, fmt: str = "markdown") -> str | None:
    """The consistency table beside :func:`results_table` (:mod:`neural_estimator.metrics.consistency`):
    NEES median and mean per state dimension, 95 % coverage (medians over runs), the calibration
    error of the runs' median reliability curve, the 50/90/99 % coverage, the 95 % coverage over
    every trajectory (outliers included) and a verdict; None when no method reports a covariance."""
    from neural_estimator.metrics import consistency as C

    rows = {}
    for m, r in results.items():
        if not r.reports or not r.reports[0].has_covariance:
            continue
        curves = [rep.coverage_curve for rep in r.reports if rep.coverage_curve is not None]
        curve = np.median(np.asarray(curves, dtype=np.float64), axis=0) if curves else None
        alls = [rep.coverage_curve_all for rep in r.reports if rep.coverage_curve_all is not None]
        curve_all = np.median(np.asarray(alls, dtype=np.float64), axis=0) if alls else None
        every = [rep.nees_median_all for rep in r.reports if rep.nees_median_all is not None]
        summary = dict(r.summary, nees_median_all=M.median_iqr(every)[0] if every else None)
        rows[m] = C.consistency_row(summary, dx, curve, curve_all)
    if not rows:
        return None
    return C.format_consistency_table(rows, fmt=fmt)
