"""The four classical nonlinear filters, batched over B streams (numpy, float64).

>>> from neural_estimator.filters import UnscentedKalmanFilter
>>> ukf = UnscentedKalmanFilter(scenario, alpha=1e-3)     # options are hyperparameter fields
>>> est = ukf.run(Y, U)                                   # (B, T, dy), (B, T, du) -> Estimates

One file per filter (``ekf``, ``ukf``, ``enkf``, ``pf``), each with a hyperparameter dataclass
whose defaults are the paper's (Table hparams); :mod:`~neural_estimator.filters.base` holds the
step cycle, divergence handling and ``run``; :mod:`~neural_estimator.filters.numerics` the
batched linear algebra and particle-weight helpers.
"""

from neural_estimator.filters.base import ClassicalFilter
from neural_estimator.filters.ekf import EKFHyperParams, ExtendedKalmanFilter
from neural_estimator.filters.enkf import EnKFHyperParams, EnsembleKalmanFilter
from neural_estimator.filters.pf import ParticleFilter, PFHyperParams
from neural_estimator.filters.ukf import UKFHyperParams, UnscentedKalmanFilter

__all__ = [
    "ClassicalFilter",
    "EKFHyperParams",
    "EnKFHyperParams",
    "EnsembleKalmanFilter",
    "ExtendedKalmanFilter",
    "PFHyperParams",
    "ParticleFilter",
    "UKFHyperParams",
    "UnscentedKalmanFilter",
]
