"""The classical filters' calibrated settings: the options ``scripts/calibrate_covariances.py`` chose
on validation data (docs/uncertainty.md), beside the paper's settings, which stay the defaults.

    opts = calibrated_options("lorenz96", "enkf")      # {"inflation": 1.2, "cov_scale": 1.2278}
    make_estimator("enkf", scenario, **opts)
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

CALIBRATED_FILE = Path(__file__).with_name("calibrated_filters.json")


def calibrated_options(scenario: str, method: str, path: str | Path = CALIBRATED_FILE) -> dict[str, Any]:
    """The calibrated options of ``method`` on ``scenario`` (the scenario's default constants), or {}
    where none were chosen (a neural model: its calibration is in its card)."""
    table = json.loads(Path(path).read_text())
    return dict(((table.get(str(scenario)) or {}).get(str(method)) or {}).get("options") or {})
