"""The paper's extended-metrics table: one row per method, always the same columns, as markdown, text
or csv."""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Mapping
from typing import Any

from neural_estimator.metrics.checks import MetricsError
from neural_estimator.metrics.definitions import SCALAR_METRICS, MetricReport
from neural_estimator.metrics.summary import Stat, _as_stat


# ---- output -------------------------------------------------------------------------------------------

# (metric key, header, decimals, show IQR). The paper's eight columns first (it prints Out. and
# Drift without "± IQR"), then ours. Every table has all of them, for every scenario and method.
TABLE_COLUMNS = (
    ("rmse", "RMSE", 3, True),
    ("full_rmse", "Full RMSE", 3, True),
    ("nrmse", "NRMSE", 3, True),
    ("mae", "MAE", 3, True),
    ("medae", "MedAE", 3, True),
    ("auc", "AUC", 1, True),
    ("outlier_ratio", "Out.", 3, False),
    ("drift_ratio", "Drift", 3, False),
    ("diverged_ratio", "Div.", 3, False),
    ("nees_median", "NEES med.", 2, True),
    ("nees", "NEES mean", 2, False),
    ("coverage95", "95%", 3, True),
    ("cov_degenerate", "Degen.", 3, False),
)
NOT_APPLICABLE = "—"  # table cell of a metric that does not apply (NEES of a method without covariance)
DEGENERATE = "degen."  # table cell of a NEES made infinite by degenerate covariances


def format_table(
    rows: Mapping[str, Mapping[str, Any]],
    fmt: str = "markdown",
    iqr_everywhere: bool = False,
    marks: Mapping[str, Mapping[str, str]] | None = None,
) -> str:
    """The paper's extended-metrics table, one row per method, always the same columns.

    Columns :data:`TABLE_COLUMNS`: the appendix tables' RMSE, Full RMSE, NRMSE, MAE, MedAE, AUC,
    Out., Drift, then Div. (diverged share) and the covariance columns NEES med., NEES mean, 95%,
    Degen. Cells are "median±IQR" with 3 decimals (AUC 1, NEES 2); Out., Drift, Div., NEES mean and
    Degen. show the median only unless ``iqr_everywhere``. An infinite median prints "inf" (the
    paper's infinity; in a NEES column "degen.": most covariances were degenerate), NaN prints
    "N/A", a metric that does not apply to the method "—". The csv format is for machines: every
    metric of :data:`SCALAR_METRICS` as a median and an IQR column (``rmse``, ``rmse_iqr``, ...),
    full precision, "inf" and "nan" as Python prints them, empty where the metric does not apply.

    Args:
        rows: {method: summary}; a summary maps metric keys to :class:`Stat`, (median, iqr) or a
            plain number (IQR 0), e.g. the output of :func:`summarize` or ``report.scalars()``;
            a key that is absent or None does not apply.
        fmt: "markdown", "text" or "csv".
        iqr_everywhere: also print the IQR of the median-only columns.
        marks: {method: {metric key: mark}}: a mark printed after that cell (markdown and text;
            :mod:`neural_estimator.paper.departures`), e.g. ``{"pf": {"rmse": "[o]"}}``.
    """
    if fmt not in ("markdown", "text", "csv"):
        raise MetricsError(f"fmt must be 'markdown', 'text' or 'csv', got {fmt!r}")
    stats = {m: {k: _as_stat(s.get(k)) for k in SCALAR_METRICS} for m, s in rows.items()}

    if fmt == "csv":
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(["method"] + [h for key in SCALAR_METRICS for h in (key, key + "_iqr")])
        for method, s in stats.items():
            cells = [method]
            for key in SCALAR_METRICS:
                st = s[key]
                cells += [repr(st.median), repr(st.iqr)] if st.applies else ["", ""]
            w.writerow(cells)
        return buf.getvalue()

    cols = TABLE_COLUMNS
    header = ["Method"] + [h for _, h, _, _ in cols]
    body = []
    for method, s in stats.items():
        cells = [method]
        for key, _, dec, show_iqr in cols:
            cell = _cell(s[key], dec, show_iqr or iqr_everywhere, nees=key.startswith("nees"))
            mark = ((marks or {}).get(method) or {}).get(key)
            cells.append(f"{cell} {mark}" if mark else cell)
        body.append(cells)
    if fmt == "markdown":
        lines = ["| " + " | ".join(header) + " |", "|" + "|".join(["---"] + ["---:"] * len(cols)) + "|"]
        lines += ["| " + " | ".join(r) + " |" for r in body]
        return "\n".join(lines) + "\n"
    widths = [max(len(r[i]) for r in [header] + body) for i in range(len(header))]

    def aligned(r: list[str]) -> str:  # method name left, numbers right
        return "  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths))).rstrip()

    return "\n".join(aligned(r) for r in [header] + body) + "\n"


def format_reports(
    reports: Mapping[str, MetricReport], fmt: str = "text", marks: Mapping[str, Mapping[str, str]] | None = None
) -> str:
    """:func:`format_table` of one run per method: one run has no spread, so the IQR is NaN and the
    cells show the value alone (no fake "±0.000"); ``marks`` as in :func:`format_table`."""
    rows = {m: {k: (None if v is None else (v, math.nan)) for k, v in r.scalars().items()} for m, r in reports.items()}
    return format_table(rows, fmt=fmt, marks=marks)


def _cell(st: Stat, decimals: int, show_iqr: bool, nees: bool = False) -> str:
    if not st.applies:
        return NOT_APPLICABLE
    if math.isnan(st.median):
        return "N/A"
    if math.isinf(st.median):
        if nees:
            return DEGENERATE
        return "inf" if st.median > 0 else "-inf"
    med = _number(st.median, decimals)
    if not show_iqr or math.isnan(st.iqr) or (st.n == 1 and st.iqr == 0):
        return med  # one value (a single evaluation set) has no spread: no fake "±0.000"
    iqr = "inf" if math.isinf(st.iqr) else _number(st.iqr, decimals)
    return f"{med}±{iqr}"


def _number(x: float, decimals: int) -> str:
    """Fixed decimals, or 3 significant digits from 1e6 up (an overconfident filter's NEES of
    7e10 reads better than 71662836828.73)."""
    return f"{x:.3g}" if abs(x) >= 1e6 else f"{x:.{decimals}f}"
