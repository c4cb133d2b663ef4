"""The tables of the reproduce report: our numbers beside the paper's (:mod:`neural_estimator.paper`), and its
figures (:mod:`neural_estimator.paper.reproduce.report` writes report.md from them).

Table cells read ``ours · paper`` (the paper's value after the dot; ``—`` where the paper has no
value, e.g. a scenario or method it lacks). Ours are medians (± IQR where the paper gives one)
over the evaluation sets, as in the paper's tables.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from neural_estimator.paper import departures as D
from neural_estimator import metrics as M
from neural_estimator.methods import table
from neural_estimator.paper.expected_failures import MARK, expected_to_fail, notes
from neural_estimator.paper.results import paper_value
from neural_estimator.metrics.plots import new_figure, save_figure

PAPER_NAMES = table.paper_names()  # {method: the paper's spelling}, the paper's ten in its row order
EXTENDED = M.TABLE_COLUMNS[:8]  # the paper's eight extended-table columns (RMSE ... Drift)
SEP = " · "  # between ours and the paper's


def num(x: Any, decimals: int = 3) -> str:
    """A cell number: inf as ∞, missing as N/A, large values with one decimal."""
    if x is None:
        return "N/A"
    x = float(x)
    if math.isnan(x):
        return "N/A"
    if math.isinf(x):
        return "∞"
    if abs(x) >= 1000:
        return f"{x:,.1f}"
    return f"{x:.{decimals}f}"


def stat_cell(st: M.Stat | None, decimals: int, iqr: bool) -> str:
    if st is None or not st.applies:
        return "N/A"
    if iqr and math.isfinite(st.median) and math.isfinite(st.iqr):
        return f"{num(st.median, decimals)}±{num(st.iqr, decimals)}"
    return num(st.median, decimals)


def paper_cell(v: Any, decimals: int) -> str:
    if isinstance(v, dict):
        return f"{num(v['median'], decimals)}±{num(v['iqr'], decimals)}"
    return num(v, decimals)


def side(ours: str, paper: Any, decimals: int, in_paper: bool) -> str:
    return ours + SEP + (paper_cell(paper, decimals) if in_paper else "—")


def _row(cells: Sequence[str]) -> str:
    return "| " + " | ".join(cells) + " |"


def _header(cols: Sequence[str]) -> list[str]:
    return [_row(cols), _row(["---"] * len(cols))]


def summaries(runs: Mapping[str, Mapping[str, list[dict[str, Any]]]]) -> dict[str, dict[str, dict[str, M.Stat]]]:
    """{scenario: {method: {metric: Stat}}} over the runs (report dicts) of each pair."""
    return {s: {m: M.summarize(rs) for m, rs in by_m.items() if rs} for s, by_m in runs.items()}


def _in_paper(s: str, m: str) -> bool:
    return paper_value("accuracy_main", s, m) is not None


def cell_start(s: str, m: str, init: str = "prior", starts=None) -> str:
    """The start the filter ``m`` really got on ``s``: ``starts[s][m]`` when recorded (``--init observation``
    is the prior where h determines nothing), else the run's ``init``."""
    return (starts or {}).get(s, {}).get(m, init)


def rmse_marks(summ, s: str, m: str, contexts=None, init: str = "prior", starts=None) -> list[str]:
    """The marks of the RMSE cell of ``m`` on ``s``: [c] (bounded context, ``contexts[s][m]`` > 0), [t] / [y]
    (a filter started from the truth / the first observation) and [o] (the outlier rule decides it:
    :func:`neural_estimator.paper.departures.rests_on_outliers`)."""
    st = summ.get(s, {}).get(m)
    marks = [D.BOUNDED] if (contexts or {}).get(s, {}).get(m) else []
    start = D.start_mark(m, cell_start(s, m, init, starts))
    if start:
        marks.append(start)
    if st is not None and D.rests_on_outliers(st["rmse"].median, st["full_rmse"].median):
        marks.append(D.OUTLIERS)
    return marks


def accuracy_table(
    summ,
    scenarios,
    methods,
    mark_expected: bool = False,
    *,
    init: str = "prior",
    contexts=None,
    every_step=None,
    starts=None,
) -> list[str]:
    """The main table, every departure from the paper's protocol marked where the number is printed.

    Columns per scenario: RMSE (the scored steps), RMSE over every step (``every_step[s][m]``: the
    median over runs; N/A where not measured), NRMSE. Marks (:mod:`neural_estimator.paper.departures`):
    [c] on a bounded-context cell (``contexts[s][m]`` > 0), [o] with the Full RMSE beside an RMSE
    the outlier rule decides, [t] / [y] on a filter started from the truth / the first observation
    (``starts[s][m]``, else ``init``); with ``mark_expected`` the RMSE of an expected failure under that start
    (:mod:`neural_estimator.paper.expected_failures`) ends with its mark, just before the paper's value.
    """
    cols = ["Method"] + [f"{s} {k}" for s in scenarios for k in ("RMSE", "RMSE all steps", "NRMSE")]
    lines = _header(cols)
    for m in methods:
        cells = [table.label(m)]
        for s in scenarios:
            st = summ.get(s, {}).get(m)
            ours = stat_cell(st and st["rmse"], 3, False)
            marks = rmse_marks(summ, s, m, contexts, init, starts)
            if marks:
                ours += " " + " ".join(marks)
            if D.OUTLIERS in marks:
                ours += f" (full {num(st['full_rmse'].median)})"
            if mark_expected and expected_to_fail(s, m, cell_start(s, m, init, starts)):
                ours += f" {MARK}"
            cells.append(side(ours, paper_value("accuracy_main", s, m, "rmse"), 3, _in_paper(s, m)))
            every = (every_step or {}).get(s, {}).get(m)
            cells.append(side(num(every), None, 3, False))
            cells.append(
                side(
                    stat_cell(st and st["nrmse"], 3, False),
                    paper_value("accuracy_main", s, m, "nrmse"),
                    3,
                    _in_paper(s, m),
                )
            )
        lines.append(_row(cells))
    return lines


def used_marks(
    summ, scenarios, methods, *, init: str = "prior", contexts=None, mark_expected: bool = False, starts=None
) -> set[str]:
    """Every mark :func:`accuracy_table` prints for these arguments (for the legend)."""
    used = {mk for s in scenarios for m in methods for mk in rmse_marks(summ, s, m, contexts, init, starts)}
    if mark_expected and any(
        expected_to_fail(s, m, cell_start(s, m, init, starts)) for s in scenarios for m in methods
    ):
        used.add(MARK)
    return used


def marks_legend(used: set[str], contexts=None) -> list[str]:
    """The legend of the marks in ``used``, one bullet each."""
    ctx = [c for by_m in (contexts or {}).values() for c in by_m.values()]
    return [f"- {line}" for line in D.legend(used, ctx)]


def expected_failure_notes(scenarios, methods, init: str = "prior", starts=None) -> list[str]:
    """One bullet per expected failure (under the start each cell got) or caveat in the table, with its reason."""
    lines = [
        f"- {s}: {note}"
        for s in scenarios
        for note in notes(s, methods, {m: cell_start(s, m, init, starts) for m in methods})
    ]
    return lines + [""] if lines else []


def relative_scores(summ, scenarios, methods) -> dict[str, dict[str, float]]:
    """score(m, s) = 100 RMSE(Mamba-2, s) / RMSE(m, s) (the paper's eq. relative_score); NaN without Mamba-2."""
    out: dict[str, dict[str, float]] = {}
    for s in scenarios:
        ref = summ.get(s, {}).get("mamba2")
        for m in methods:
            st = summ.get(s, {}).get(m)
            if ref is None or st is None:
                v = math.nan
            else:
                r, x = ref["rmse"].median, st["rmse"].median
                v = 0.0 if math.isinf(x) else (100 * r / x if x > 0 else math.nan)
            out.setdefault(s, {})[m] = v
    return out


def relative_table(summ, scenarios, methods) -> list[str]:
    scores = relative_scores(summ, scenarios, methods)
    lines = _header(["Method"] + list(scenarios))
    for m in methods:
        lines.append(
            _row(
                [table.label(m)]
                + [
                    side(num(scores[s][m], 1), paper_value("relative_score", s, m), 1, _in_paper(s, m))
                    for s in scenarios
                ]
            )
        )
    return lines


def extended_table(summ, s, methods, *, init: str = "prior", contexts=None, starts=None) -> list[str]:
    """One scenario's extended table; the RMSE cell carries the main table's [c] / [t] / [y] / [o] marks
    (the Full RMSE is the next column)."""
    lines = _header(["Method"] + [h for _, h, _, _ in EXTENDED])
    for m in methods:
        st = summ.get(s, {}).get(m)
        marks = " ".join(rmse_marks(summ, s, m, contexts, init, starts))
        cells = []
        for k, _, d, iqr in EXTENDED:
            ours = stat_cell(st and st[k], d, iqr)
            if k == "rmse" and marks:
                ours += f" {marks}"
            cells.append(side(ours, paper_value("extended", s, m, k), d, _in_paper(s, m)))
        lines.append(_row([table.label(m)] + cells))
    return lines


def components_table(runs, s: str, methods, names: Sequence[str], instances=None) -> list[str]:
    """Beyond the paper: one scenario's RMSE per state component (its own units), the median over
    sets x instances of each run's ``rmse_components``, and the number of trained instances of each
    network (``instances`` {method: count}; "1 instance" where one, "—" for a filter)."""
    lines = _header(["Method"] + list(names) + ["instances"])
    for m in methods:
        comps = [r["rmse_components"] for r in runs.get(s, {}).get(m, []) if r.get("rmse_components")]
        if not comps:
            continue
        # a run whose component count is not the scenario's (a result of other constants) gives N/A
        meds = [
            M.median_iqr(math.inf if v[d] is None else v[d] for v in comps if len(v) > d)[0] for d in range(len(names))
        ]
        cells = [f"{x:.4g}" if math.isfinite(x) else num(x) for x in meds]  # 4 digits: components span 1e-3..1e3
        k = (instances or {}).get(m)
        count = "—" if k is None else "1 instance" if k == 1 else f"{k} instances"
        lines.append(_row([table.label(m)] + cells + [count]))
    return lines


def nrmse_avg_table(summ, scenarios, methods) -> list[str]:
    """Median and IQR over the scenario-level median NRMSEs (the paper's tab:nrmse_avg_all)."""
    lines = _header(["Method", "Median NRMSE", "(IQR)", "scenarios"])
    for m in methods:
        vals = [summ[s][m]["nrmse"].median for s in scenarios if m in summ.get(s, {})]
        med, iqr = M.median_iqr(vals) if vals else (math.nan, math.nan)
        paper = paper_value("nrmse_avg_all", m) or {}
        known = m in PAPER_NAMES
        lines.append(
            _row(
                [
                    table.label(m),
                    side(num(med), paper.get("median"), 3, known),
                    side(num(iqr), paper.get("iqr"), 3, known),
                    str(len(vals)),
                ]
            )
        )
    return lines


def stability_table(summ, scenarios, methods) -> list[str]:
    cols = ["Method"] + [f"Out. {s}" for s in scenarios] + [f"Drift {s}" for s in scenarios]
    lines = _header(cols)
    for m in methods:
        cells = [table.label(m)]
        for k in ("outlier_ratio", "drift_ratio"):
            for s in scenarios:
                st = summ.get(s, {}).get(m)
                cells.append(
                    side(stat_cell(st and st[k], 3, False), paper_value("stability", s, m, k), 3, _in_paper(s, m))
                )
        lines.append(_row(cells))
    return lines


def covariance_table(summ, scenarios, methods) -> list[str]:
    """Beyond the paper: NEES (median) and 95 % coverage where a method reports a covariance."""
    cols = ["Method"] + [f"{s} {k}" for s in scenarios for k in ("NEES med.", "95%")]
    lines = _header(cols)
    for m in methods:
        cells, any_applies = [table.label(m)], False
        for s in scenarios:
            st = summ.get(s, {}).get(m)
            for k, d in (("nees_median", 2), ("coverage95", 3)):
                applies = st is not None and st[k].applies
                any_applies |= applies
                cells.append(stat_cell(st[k], d, True) if applies else M.NOT_APPLICABLE)
        if any_applies:
            lines.append(_row(cells))
    return lines


def consistency_table(summ, scenarios, methods, dims: Mapping[str, int]) -> list[str]:
    """Beyond the paper: mean NEES per state dimension and the verdict of
    :func:`neural_estimator.metrics.consistency.verdict` (scenario -> dx in ``dims``), where a method
    reports a covariance."""
    from neural_estimator.metrics import consistency as C

    cols = ["Method"] + [f"{s} {k}" for s in scenarios for k in ("NEES mean/dx", "verdict")]
    lines = _header(cols)
    for m in methods:
        cells, any_applies = [table.label(m)], False
        for s in scenarios:
            st = summ.get(s, {}).get(m)
            if st is None or not st["nees"].applies:
                cells += [M.NOT_APPLICABLE, M.NOT_APPLICABLE]
                continue
            any_applies = True
            row = C.consistency_row(st, dims[s])
            cells += [num(row["nees_mean_per_dim"], 2), row["verdict"]]
        if any_applies:
            lines.append(_row(cells))
    return lines


def _family_averages(
    rt_device: Mapping[str, Mapping[str, float]], scenarios, methods
) -> tuple[list[float], list[float]]:
    """(filters, networks): each method's mean it/s over the scenarios it ran on."""
    avg: dict[str, float] = {}
    for m in methods:
        vals = [rt_device.get(s, {}).get(m) for s in scenarios]
        vals = [v for v in vals if v is not None and math.isfinite(v)]
        if vals:
            avg[m] = sum(vals) / len(vals)
    filters = [v for m, v in avg.items() if table.has(m, family="classical")]
    networks = [v for m, v in avg.items() if not table.has(m, family="classical")]
    return filters, networks


def runtime_ordering(
    rt_device: Mapping[str, Mapping[str, float]], scenarios, methods, paper_device: str = "cpu"
) -> str:
    """One sentence: which family is faster in these timings (median over methods of each method's mean
    it/s over the scenarios), and whether that is the paper's ordering on ``paper_device``."""
    filters, networks = _family_averages(rt_device, scenarios, methods)
    if not filters or not networks:
        return "Only one family was timed: no ordering between filters and networks."
    f, n = float(np.median(filters)), float(np.median(networks))
    paper = paper_value("runtime_full", paper_device) or {}
    pf, pn = _family_averages(paper, list(paper), list(PAPER_NAMES))
    ours = "the networks ahead of the filters" if n > f else "the filters ahead of the networks"
    verdict = ""
    if pf and pn:
        paper_f, paper_n = float(np.median(pf)), float(np.median(pn))
        same = (paper_n > paper_f) == (n > f)
        verdict = (
            f"; {'the' if same else 'against the'} paper's ordering "
            f"(paper {paper_device.upper()}: filters {paper_f:,.0f}, networks {paper_n:,.0f})"
        )
    return (
        f"This mode supports {ours}: filters {f:,.0f} it/s, networks {n:,.0f} it/s "
        f"(median over methods of each one's mean over scenarios){verdict}."
    )


def runtime_table(rt: Mapping[str, Mapping[str, Mapping[str, float]]], scenarios, methods, device: str) -> list[str]:
    """Iterations per second at batch 1: {device: {scenario: {method: it/s}}}, beside tab:runtime_full_app."""
    lines = _header(["Method"] + list(scenarios) + ["Avg."])
    paper_device = "gpu" if device != "cpu" else "cpu"
    for m in methods:
        vals = [rt.get(device, {}).get(s, {}).get(m) for s in scenarios]
        if all(v is None for v in vals):
            continue
        known = [v for v in vals if v is not None]
        avg = sum(known) / len(known) if len(known) == len(vals) else None
        cells = [
            side(num(v, 1), paper_value("runtime_full", paper_device, s, m), 1, m in PAPER_NAMES)
            for v, s in zip(vals, scenarios)
        ]
        # the paper's average is over its five scenarios: shown only when we ran those five
        all_five = sorted(scenarios) == sorted(paper_value("runtime_full", "cpu") or {})
        cells.append(
            side(num(avg, 1), paper_value("runtime_summary", m, paper_device), 1, m in PAPER_NAMES and all_five)
        )
        lines.append(_row([table.label(m)] + cells))
    return lines


def runtime_table_not_measured(scenarios, methods, paper_device: str, why: str) -> list[str]:
    """The paper's iterations per second on ``paper_device`` beside "not measured (``why``)" for every
    method and scenario: the paper's column stays in the report where this run has no such device."""
    lines = _header(["Method"] + list(scenarios) + ["Avg."])
    all_five = sorted(scenarios) == sorted(paper_value("runtime_full", "cpu") or {})
    ours = f"not measured ({why})"
    for m in methods:
        if m not in PAPER_NAMES:
            continue
        cells = [side(ours, paper_value("runtime_full", paper_device, s, m), 1, True) for s in scenarios]
        cells.append(side(ours, paper_value("runtime_summary", m, paper_device), 1, all_five))
        lines.append(_row([table.label(m)] + cells))
    return lines


def data_ratio_table(
    nrmse: Mapping[str, Mapping[str, Mapping[float, list[float]]]], scenarios, methods, ratios: Sequence[float]
) -> list[str]:
    """Median across scenarios of each scenario's median NRMSE (over sets x instances), per ratio,
    beside tab:data_ratio_main: ``nrmse[scenario][method][ratio] = [NRMSE of each run]``."""
    lines = _header(["Method"] + [f"{r:g}:1" for r in ratios])
    for m in methods:
        cells = [table.label(m)]
        for r in ratios:
            per_s = [M.median_iqr(nrmse[s][m][r])[0] for s in scenarios if nrmse.get(s, {}).get(m, {}).get(r)]
            ours = M.median_iqr(per_s)[0] if per_s else math.nan
            paper = paper_value("data_ratio_main", f"{r:g}", m)
            cells.append(side(num(ours), paper, 3, paper is not None))
        lines.append(_row(cells))
    return lines


def plot_data_ratio(by_method: Mapping[str, Mapping[float, list[float]]], path: Path, title: str) -> Path:
    """Grouped bars: median NRMSE per architecture at each data-to-parameter ratio (IQR as error bars)."""
    methods = [m for m, v in by_method.items() if v]
    ratios = sorted({r for m in methods for r in by_method[m]}, reverse=True)
    fig, ax = new_figure((8, 4.5))
    width = 0.8 / max(1, len(ratios))
    for k, r in enumerate(ratios):
        med, lo, hi = [], [], []
        for m in methods:
            v = np.asarray(by_method[m].get(r, []), float)
            v = v[np.isfinite(v)]
            q = np.percentile(v, [25, 50, 75]) if v.size else [np.nan] * 3
            med.append(q[1]), lo.append(q[1] - q[0]), hi.append(q[2] - q[1])
        x = np.arange(len(methods)) + (k - (len(ratios) - 1) / 2) * width
        ax.bar(x, med, width, yerr=[lo, hi], capsize=2, label=f"{r:g}:1")
    ax.set_xticks(np.arange(len(methods)), [table.label(m) for m in methods])
    ax.set_ylabel("NRMSE (median over sets x instances)")
    ax.set_title(title)
    ax.grid(True, axis="y", alpha=0.3)
    ax.legend(title="data : parameters", fontsize=8)
    return save_figure(fig, path)


def data_ratio_paper_table() -> list[str]:
    lines = _header(["Method", "20:1", "10:1", "5:1", "1:1"])
    for m in table.paper_methods(family="neural"):
        lines.append(
            _row([PAPER_NAMES[m]] + [num(paper_value("data_ratio_main", r, m)) for r in ("20", "10", "5", "1")])
        )
    return lines


def plot_noise(curves: Mapping[str, Mapping[float, list[float]]], path: Path, title: str) -> Path:
    """RMSE against the observation-noise scale, median over sets with the IQR shaded, per method."""
    fig, ax = new_figure((8, 4.5))
    for m, by_scale in curves.items():
        xs = sorted(by_scale)
        stats = [M.median_iqr(by_scale[x]) for x in xs]
        q = [
            (np.nanpercentile(np.asarray(by_scale[x], float), 25), np.nanpercentile(np.asarray(by_scale[x], float), 75))
            if np.isfinite(by_scale[x]).any()
            else (np.nan, np.nan)
            for x in xs
        ]
        (line,) = ax.plot(xs, [st[0] for st in stats], marker="o", label=table.label(m))
        ax.fill_between(xs, [a for a, _ in q], [b for _, b in q], color=line.get_color(), alpha=0.2)
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    ax.set_xlabel("observation-noise scale (x nominal; models trained at 1)")
    ax.set_ylabel("RMSE")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, ncol=2)
    return save_figure(fig, path)
