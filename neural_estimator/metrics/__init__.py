"""Evaluation metrics of the paper, in six modules:

- :mod:`~neural_estimator.metrics.definitions`: one run's metrics (errors, RMSE-time
  curve, AUC, drift, NRMSE, NEES, coverage) and :func:`compute_metrics`;
- :mod:`~neural_estimator.metrics.labelled`: the same on the labelled steps only (recorded data
  whose ground truth has gaps), :func:`compute_labelled_metrics`;
- :mod:`~neural_estimator.metrics.outliers`: the paper's outlier rule (robust z-score of the log MSE);
- :mod:`~neural_estimator.metrics.paired`: per-trajectory errors and the paired bootstrap of RMSE ratios;
- :mod:`~neural_estimator.metrics.summary`: the median and IQR across runs, and the JSON form;
- :mod:`~neural_estimator.metrics.table`: the extended-metrics table.

Their public names are importable from here. The definitions and their reasons: docs/metrics.md.
"""

from neural_estimator.metrics.checks import MetricsError
from neural_estimator.metrics.definitions import (
    COVARIANCE_METRICS,
    COVERAGE_LEVEL,
    DEGENERATE_RCOND,
    EVALUATION_WARMUP,
    SCALAR_METRICS,
    MetricReport,
    auc,
    compute_metrics,
    covariance_metrics,
    diverged_mask,
    drift_ratio,
    errors,
    kept_rmse,
    nees,
    rmse_over_time,
    state_spread,
    trajectory_mean_nrmse,
    trajectory_mse,
)
from neural_estimator.metrics.labelled import compute_labelled_metrics, labelled_metrics, scored_line
from neural_estimator.metrics.outliers import (
    LOG_SCALE_FLOOR,
    MAD_SCALE,
    MEANAD_SCALE,
    OUTLIER_Z,
    outlier_mask,
    robust_zscores,
)
from neural_estimator.metrics.paired import (
    TrajectoryErrors,
    estimated_components,
    paired_geometric_ratio,
    paired_ratio,
    run_rmse,
    trajectory_errors,
    verdict,
)
from neural_estimator.metrics.summary import Stat, median_iqr, summarize, to_json
from neural_estimator.metrics.table import DEGENERATE, NOT_APPLICABLE, TABLE_COLUMNS, format_reports, format_table

__all__ = [
    "COVARIANCE_METRICS",
    "COVERAGE_LEVEL",
    "DEGENERATE",
    "DEGENERATE_RCOND",
    "EVALUATION_WARMUP",
    "LOG_SCALE_FLOOR",
    "MAD_SCALE",
    "MEANAD_SCALE",
    "NOT_APPLICABLE",
    "OUTLIER_Z",
    "SCALAR_METRICS",
    "TABLE_COLUMNS",
    "MetricReport",
    "MetricsError",
    "Stat",
    "TrajectoryErrors",
    "auc",
    "compute_labelled_metrics",
    "compute_metrics",
    "covariance_metrics",
    "diverged_mask",
    "drift_ratio",
    "errors",
    "estimated_components",
    "format_reports",
    "format_table",
    "kept_rmse",
    "labelled_metrics",
    "median_iqr",
    "nees",
    "outlier_mask",
    "paired_geometric_ratio",
    "paired_ratio",
    "rmse_over_time",
    "robust_zscores",
    "run_rmse",
    "scored_line",
    "state_spread",
    "summarize",
    "to_json",
    "verdict",
    "trajectory_mean_nrmse",
    "trajectory_errors",
    "trajectory_mse",
]
