"""The reliability figures: curves are the median over runs, only of methods with a covariance, and
the figure is written."""

import numpy as np
from conftest import load_script

from neural_estimator.metrics.consistency import RELIABILITY_LEVELS
from neural_estimator.metrics.plots import plot_reliability


def test_curves_are_medians_over_runs_of_methods_with_a_covariance(tmp_path):
    script = load_script("scripts/reliability_figures.py")
    q = list(RELIABILITY_LEVELS)
    results = {
        "methods": {
            "ekf": {"runs": [{"coverage_curve": q}, {"coverage_curve": [v / 2 for v in q]}, {"coverage_curve": q}]},
            "gru": {"runs": [{"coverage_curve": None}]},  # no covariance: no curve
        }
    }
    curves = script.curves_of(results)
    assert set(curves) == {"ekf"} and np.allclose(curves["ekf"], q)
    path = plot_reliability(curves, RELIABILITY_LEVELS, tmp_path / "r.png", title="t")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
