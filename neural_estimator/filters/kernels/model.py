"""The record of one scenario's compiled kernels, its constants bound (:class:`CompiledModel`), which
each scenario's kernel module builds (its ``bind(scenario)``) and the filters consume."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

Predict = Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray, tuple], None]
LogLikelihood = Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], None]
Transition = Callable[[np.ndarray, np.ndarray], np.ndarray]


@dataclass(frozen=True)
class CompiledModel:
    """The kernels of one scenario instance, its constants bound.

    predict(X, u, L, sd, key): X (b, P, n) <- normalize_state(f(X, u) + w) in place, u (b, du)
        the streams' controls u_{k-1}, key = (seed, k,
        phase, first_stream) of the keyed generators; None: numpy f, compiled noise.
    log_likelihood(X, y, inv_sd, logw): logw (b, P) += log N(y; h(x_i), diag(sd^2)) up to a
        constant, innovations wrapped where h is an angle; None: the generic linear kernel or numpy.
    transition(X, u): f(X, u) as a new array, no noise (the EnKF's members); None: numpy f. Set
        where numpy's f costs most: Lorenz 96 and ballistic (bit-equal to f), N-link (a few ulp).
    ekf_model, enkf_model: the model constants the compiled EKF and EnKF (:mod:`.ekf`, :mod:`.enkf`)
        take after their own arguments; their predict steps hold Lorenz 96's field, so only
        Lorenz 96 sets them. None: the filter's batched numpy path.
    """

    predict: Predict | None = None
    log_likelihood: LogLikelihood | None = None
    transition: Transition | None = None
    ekf_model: tuple | None = None
    enkf_model: tuple | None = None


def in_place_rows(kernel, *args) -> Transition:
    """f(X, u) -> a new array from an in-place kernel on (M, n) rows (the EnKF's members)."""

    def transition(X: np.ndarray, u: np.ndarray) -> np.ndarray:
        Y = np.array(X, dtype=np.float64, order="C")
        kernel(Y.reshape(-1, Y.shape[-1]), *args)
        return Y

    return transition
