"""The registry of the ten methods: :func:`make_estimator` builds any of them by name.

It sits above both families (:mod:`neural_estimator.filters`, :mod:`neural_estimator.models`), which
implement the interface of :mod:`neural_estimator.estimator`; that interface is re-exported here, so
``from neural_estimator.registry import Estimator, EstimatorError, METHODS`` keeps working for the
layers above.
"""

from __future__ import annotations

import inspect
from pathlib import Path
from typing import TYPE_CHECKING, Any

from neural_estimator.estimator import (  # noqa: F401  re-exported: the interface, for the layers above
    CLASSICAL_METHODS,
    METHODS,
    NEURAL_METHODS,
    Estimates,
    Estimator,
    EstimatorError,
    check_method,
    previous_controls,
)
from neural_estimator.filters.ekf import ExtendedKalmanFilter
from neural_estimator.filters.enkf import EnsembleKalmanFilter
from neural_estimator.filters.pf import ParticleFilter
from neural_estimator.filters.ukf import UnscentedKalmanFilter
from neural_estimator.scenarios import Scenario
from neural_estimator.core.options import did_you_mean

if TYPE_CHECKING:
    from neural_estimator.serving.card import Checkpoint

CLASSICAL_FILTERS: dict[str, type[Estimator]] = {
    "ekf": ExtendedKalmanFilter,
    "ukf": UnscentedKalmanFilter,
    "enkf": EnsembleKalmanFilter,
    "pf": ParticleFilter,
}
assert tuple(CLASSICAL_FILTERS) == CLASSICAL_METHODS


PER_MESSAGE_BACKEND = "auto"  # a neural model stepped one message at a time: step.onnx without torch where shipped


def per_message_options(method: str, options: dict[str, Any]) -> dict[str, Any]:
    """``options`` of an estimator stepped one message at a time (the estimator nodes, replay): a
    neural method's backend defaults to ``auto``, ONNX Runtime over the checkpoint's ``step.onnx``
    (no torch in the process) where it serves the request, torch otherwise
    (:func:`~neural_estimator.serving.load.per_message_backend`). Batched evaluation and training
    keep torch (``make_estimator``'s own default). The live node and replay share this default, so
    replay gives the live node's estimates."""
    options = dict(options)
    if check_method(method) in NEURAL_METHODS:
        options.setdefault("backend", PER_MESSAGE_BACKEND)
    return options


def make_estimator(
    method: str,
    scenario: Scenario,
    *,
    checkpoint: str | Path | Checkpoint | None = None,
    device: str = "cpu",
    seed: int = 0,
    **options: Any,
) -> Estimator:
    """Build one of the ten methods for ``scenario``.

    Classical filters take their settings from ``options`` (paper defaults otherwise) and ``seed``
    for their random draws. Neural models load ``checkpoint`` (a directory or its ``.json`` card, or a
    :class:`~neural_estimator.serving.card.Checkpoint` already resolved),
    or the model shipped with the package for (scenario, method) when ``checkpoint`` is None;
    their ``options`` go to :func:`~neural_estimator.serving.load.load_neural_estimator`
    (``covariance=False`` skips the Filterformer's per-step covariance).
    """
    m = check_method(method)
    if m in CLASSICAL_FILTERS:
        return CLASSICAL_FILTERS[m](scenario, seed=seed, **options)
    # Imported here, not at the top: the neural side imports torch (1-2 s), which a process that
    # only runs filters (an EKF node, a classical evaluate) should not pay.
    from neural_estimator.serving.load import load_neural_estimator

    # an unknown option is the caller's one-line error, not a TypeError from deep inside
    valid = [
        n
        for n in inspect.signature(load_neural_estimator).parameters
        if n not in ("method", "scenario", "checkpoint", "device")
    ]
    unknown = sorted(set(options) - set(valid))
    if unknown:
        raise EstimatorError(
            f"{m}: unknown option(s) {', '.join(unknown)}{did_you_mean(unknown[-1], valid)}; valid: {', '.join(valid)}"
            + (" (torch threads: the threads setting, not an option)" if "threads" in unknown else "")
        )
    return load_neural_estimator(m, scenario, checkpoint=checkpoint, device=device, **options)
