"""Uncertainty: covariance heads for the neural models and their calibration.

- :mod:`~neural_estimator.serving.uncertainty.heads`: a Gaussian (Cholesky) covariance head on the frozen
  trunk of a trained model, served through ``step`` and ``run`` (the estimate is unchanged), and
  its storage beside the checkpoint's weights.
- :mod:`~neural_estimator.serving.uncertainty.fit`: fitting a head and its calibration scale on validation
  data (``scripts/fit_covariance_heads.py`` does it for the shipped models).
- :mod:`~neural_estimator.serving.uncertainty.calibrated`: the classical filters' calibrated settings
  (``scripts/calibrate_covariances.py`` chose them on validation data).

The figures they are judged by (NEES, coverage, the reliability curve, the calibration scale) are
:mod:`neural_estimator.metrics.consistency`; every method also takes a ``cov_scale`` option (the classical
filters and the neural models alike) that multiplies the covariance it reports.
"""
