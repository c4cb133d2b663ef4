"""Read the paper's result tables out of its LaTeX source into plain data.

The paper's published numbers ship as ``paper_results.json`` (see :mod:`neural_estimator.paper`);
this module is how that file was made and how the test suite checks it still matches the LaTeX:

    python -m neural_estimator.paper.transcribe /path/to/paper.tex > neural_estimator/paper/paper_results.json

Cells: a number, ``$\\infty$`` -> the string ``"inf"`` (strict JSON has no infinity), ``N/A`` ->
``null``; ``a$\\pm$b`` -> ``{"median": a, "iqr": b}``; bold and italics are dropped. Method and
scenario names are mapped to the package's ids (``Mamba-2`` -> ``mamba2``, ``L96`` -> ``lorenz96``).
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path
from typing import Any

from neural_estimator.paper.results import PAPER_SCENARIOS

METHOD_IDS = {
    "EKF": "ekf",
    "UKF": "ukf",
    "EnKF": "enkf",
    "PF": "pf",
    "GRU": "gru",
    "LSTM": "lstm",
    "GPT-2": "gpt2",
    "Filterformer": "filterformer",
    "Mamba": "mamba",
    "Mamba-2": "mamba2",
}
SCENARIOS = PAPER_SCENARIOS  # the paper's column order
EXTENDED_LABELS = {
    "ballistic": "ballistic_reentry_extended",
    "bearings": "bearings_only_tracking_extended",
    "lorenz96": "l96_extended",
    "nlink": "nlink_pendulum_extended",
    "quadrotor": "planar_quadrotor_extended",
}
EXTENDED_COLUMNS = ("rmse", "full_rmse", "nrmse", "mae", "medae", "auc", "outlier_ratio", "drift_ratio")
DATA_RATIOS = ("20", "10", "5", "1")
TABLES = (
    "accuracy_main",
    "relative_score",
    "data_ratio_main",
    "runtime_summary",
    *EXTENDED_LABELS.values(),
    "nrmse_avg_all",
    "stability_summary_app",
    "runtime_full_app",
)


class TranscriptionError(ValueError):
    """The LaTeX does not have the table layout this module reads."""


def table_source(tex: str, label: str) -> str:
    """The text of the table environment holding ``\\label{tab:<label>}``."""
    at = tex.find(f"\\label{{tab:{label}}}")
    if at < 0:
        raise TranscriptionError(f"no table labelled tab:{label}")
    start = tex.rfind("\\begin{table}", 0, at)
    end = tex.find("\\end{table}", at)
    if start < 0 or end < 0:
        raise TranscriptionError(f"tab:{label} is not inside a table environment")
    return tex[start : end + len("\\end{table}")]


def _rows(table: str) -> list[list[str]]:
    """Body rows between \\midrule and \\bottomrule, split on & (rows may span lines)."""
    body = table[table.find("\\midrule") : table.find("\\bottomrule")]
    rows = []
    for raw in body.split("\\\\"):
        text = " ".join(line for line in raw.splitlines() if not line.strip().startswith(("\\midrule", "\\cmidrule")))
        text = text.replace("\\midrule", "").strip()
        if not text or text.startswith("\\multicolumn"):
            continue
        rows.append([c.strip() for c in text.split("&")])
    return rows


def _strip(cell: str) -> str:
    cell = re.sub(r"\\text(bf|it)\{(.*)\}", r"\2", cell.strip())
    return cell.replace("$", "").strip()


def cell_value(cell: str) -> Any:
    """One LaTeX cell as a number, "inf", None (N/A) or {"median", "iqr"}."""
    c = _strip(cell)
    if "\\pm" in c:
        med, iqr = (cell_value(part) for part in c.split("\\pm"))
        return {"median": med, "iqr": iqr}
    if c == "\\infty":
        return "inf"
    if c == "N/A":
        return None
    try:
        return float(c)
    except ValueError:
        raise TranscriptionError(f"cell {cell!r} is not a number, \\infty or N/A") from None


def _method(name: str) -> str:
    name = _strip(name)
    if name not in METHOD_IDS:
        raise TranscriptionError(f"unknown method row {name!r}")
    return METHOD_IDS[name]


def _by_method(table: str, width: int) -> dict[str, list[Any]]:
    out = {}
    for row in _rows(table):
        if len(row) != width + 1:
            raise TranscriptionError(f"row {row[0]!r} has {len(row) - 1} cells, expected {width}")
        out[_method(row[0])] = [cell_value(c) for c in row[1:]]
    return out


def transcribe(tex: str) -> dict[str, Any]:
    """Every result table of the paper as nested dicts keyed by scenario and method ids."""
    t = {label: table_source(tex, label) for label in TABLES}
    acc = _by_method(t["accuracy_main"], 10)
    rel = _by_method(t["relative_score"], 5)
    ratio = _by_method(t["data_ratio_main"], 4)
    rt = _by_method(t["runtime_summary"], 3)
    stab = _by_method(t["stability_summary_app"], 10)
    avg_rows = _rows(t["nrmse_avg_all"])
    if len(avg_rows) != 2 or len(avg_rows[0]) != 11:
        raise TranscriptionError("tab:nrmse_avg_all: expected a Median NRMSE row and an (IQR) row of 10 methods")
    avg_methods = [METHOD_IDS[m] for m in METHOD_IDS]  # the table's column order is the paper's method order
    runtime_full: dict[str, dict[str, dict[str, Any]]] = {
        "cpu": {s: {} for s in SCENARIOS},
        "gpu": {s: {} for s in SCENARIOS},
    }
    for row in _rows(t["runtime_full_app"]):
        if len(row) != 7:
            raise TranscriptionError(f"tab:runtime_full_app row {row[:2]} has {len(row) - 2} cells, expected 5")
        device, method = _strip(row[0]).lower(), _method(row[1])
        for s, c in zip(SCENARIOS, row[2:]):
            runtime_full[device][s][method] = cell_value(c)
    extended = {}
    for s, label in EXTENDED_LABELS.items():
        extended[s] = {m: dict(zip(EXTENDED_COLUMNS, v)) for m, v in _by_method(t[label], 8).items()}
    return {
        "source": "paper.tex",
        "methods": list(METHOD_IDS.values()),
        "scenarios": list(SCENARIOS),
        "accuracy_main": {
            s: {m: {"rmse": v[2 * i], "nrmse": v[2 * i + 1]} for m, v in acc.items()} for i, s in enumerate(SCENARIOS)
        },
        "relative_score": {s: {m: v[i] for m, v in rel.items()} for i, s in enumerate(SCENARIOS)},
        "extended": extended,
        "nrmse_avg_all": {
            m: {"median": cell_value(a), "iqr": cell_value(b.strip("() "))}
            for m, a, b in zip(avg_methods, avg_rows[0][1:], avg_rows[1][1:])
        },
        "stability": {
            s: {m: {"outlier_ratio": v[i], "drift_ratio": v[5 + i]} for m, v in stab.items()}
            for i, s in enumerate(SCENARIOS)
        },
        "data_ratio_main": {r: {m: v[i] for m, v in ratio.items()} for i, r in enumerate(DATA_RATIOS)},
        "runtime_summary": {m: {"cpu": v[0], "gpu": v[1], "cpu_gpu_ratio": v[2]} for m, v in rt.items()},
        "runtime_full": runtime_full,
    }


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1:
        print("usage: python -m neural_estimator.paper.transcribe PAPER.tex > paper_results.json", file=sys.stderr)
        return 2
    print(json.dumps(transcribe(Path(argv[0]).read_text()), indent=1, allow_nan=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
