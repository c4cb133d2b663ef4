"""The paper's published numbers, as data (``paper_results.json``, transcribed from paper.tex).

>>> from neural_estimator.paper import PAPER_SCENARIOS, paper_results
>>> PAPER_SCENARIOS
('ballistic', 'bearings', 'lorenz96', 'nlink', 'quadrotor')
>>> paper_results()["accuracy_main"]["ballistic"]["ekf"]["rmse"]
5.289

Layout (scenario and method ids as in the package; see :mod:`neural_estimator.paper.transcribe`):
``accuracy_main[s][m] = {"rmse", "nrmse"}``; ``relative_score[s][m]``;
``extended[s][m][metric]`` with metric in rmse, full_rmse, nrmse, mae, medae, auc (each
``{"median", "iqr"}``), outlier_ratio, drift_ratio (numbers); ``nrmse_avg_all[m] = {"median", "iqr"}``;
``stability[s][m] = {"outlier_ratio", "drift_ratio"}``; ``data_ratio_main[ratio][m]`` with ratio
"20", "10", "5", "1"; ``runtime_summary[m] = {"cpu", "gpu", "cpu_gpu_ratio"}``;
``runtime_full[device][s][m]`` (iterations per second). :func:`paper_results` turns the file's
``"inf"`` into ``float("inf")``; ``None`` is the paper's N/A.
"""

from __future__ import annotations

import copy
import json
from functools import lru_cache
from pathlib import Path
from typing import Any

RESULTS_FILE = Path(__file__).with_name("paper_results.json")

# The paper's five systems, in its column order: everything that belongs to the paper rather than to
# every built-in scenario (presets v3/v4, the calibrated filter settings, the sample bags, the zoo's
# folders, the published tables, the reproduce runs) iterates this list. A built-in scenario is
# registered in neural_estimator.scenarios and need not be one of these.
PAPER_SCENARIOS = ("ballistic", "bearings", "lorenz96", "nlink", "quadrotor")


def _decode(value: Any) -> Any:
    if value == "inf":
        return float("inf")
    if isinstance(value, dict):
        return {k: _decode(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_decode(v) for v in value]
    return value


@lru_cache(maxsize=1)
def _load() -> dict[str, Any]:
    return _decode(json.loads(RESULTS_FILE.read_text()))


def paper_results() -> dict[str, Any]:
    """A fresh copy of every published table (callers may modify it)."""
    return copy.deepcopy(_load())


def paper_value(table: str, *keys: str) -> Any:
    """One published number, or None where the paper has none (N/A, or a method/scenario it lacks)."""
    node: Any = _load().get(table)
    for k in keys:
        if not isinstance(node, dict) or k not in node:
            return None
        node = node[k]
    return copy.deepcopy(node)
