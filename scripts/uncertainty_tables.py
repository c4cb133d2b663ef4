#!/usr/bin/env python3
"""The consistency tables of docs/uncertainty.md from `neural-estimator evaluate --out DIR` folders.

Each DIR holds a results.json; one markdown row per (scenario, method) with the RMSE, the 95 %
coverage, NEES mean and median per state dimension, the calibration error of the median reliability
curve and the verdict (neural_estimator.metrics.consistency), plus the reliability curves.

    python scripts/uncertainty_tables.py /tmp/eval/lorenz96 /tmp/eval/nlink --label "with head"
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from neural_estimator.metrics import consistency as C


def rows(directory: Path, label: str | None = None) -> list[str]:
    d = json.loads((directory / "results.json").read_text())
    scenario = d["scenario"]["scenario"]
    dx = len(d["scenario"]["state_names"])
    out = []
    for method, entry in d["methods"].items():
        s = entry["summary"]
        if not s["nees"]["applies"]:
            continue
        summary = {
            k: (None if s[k]["median"] is None else float(s[k]["median"]))
            for k in ("nees_median", "nees", "coverage95")
        }
        curves = [r["coverage_curve"] for r in entry["runs"] if r.get("coverage_curve")]
        curve = np.median(np.asarray(curves, dtype=float), axis=0) if curves else None
        r = C.consistency_row({k: (float("inf") if v is None else v) for k, v in summary.items()}, dx, curve)
        rmse = s["rmse"]["median"]
        cells = [
            scenario,
            method + (f" ({label})" if label else ""),
            "inf" if rmse is None else f"{rmse:.4g}",
            _num(r["coverage95"], 3),
            _num(r["nees_mean_per_dim"], 2),
            _num(r["nees_median_per_dim"], 2),
            _num(r["calibration_error"], 3),
            r["verdict"],
        ]
        out.append("| " + " | ".join(cells) + " |")
    return out


def _num(v, dec: int) -> str:
    if v is None:
        return "—"
    if not np.isfinite(v):
        return "inf" if v > 0 else "N/A"
    return f"{v:.2e}" if abs(v) >= 1e4 else f"{v:.{dec}f}"


HEADER = [
    "| scenario | method | RMSE | 95% cov. | NEES mean/dx | NEES med./dx | Cal. err. | verdict |",
    "|---|---|---:|---:|---:|---:|---:|---|",
]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dirs", nargs="+", type=Path)
    ap.add_argument("--label", default=None, help="appended to every method name (e.g. calibrated)")
    ap.add_argument("--no-header", action="store_true")
    args = ap.parse_args(argv)
    lines = [] if args.no_header else list(HEADER)
    for d in args.dirs:
        lines += rows(d, args.label)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
