"""The registry: :func:`make_estimator` builds any method of the table by name.

The table (:mod:`neural_estimator.methods.table`) names each method's factory as ``"module:attribute"``
text; :func:`make_estimator` resolves it with importlib when a method is built, so this module
imports nothing above its layer (the filters, or the models and serving, are imported then: a
process that runs an EKF never imports torch). The interface of
:mod:`neural_estimator.methods.interface` is re-exported here, so ``from neural_estimator.methods.registry
import Estimator, EstimatorError, METHODS`` keeps working for the layers above.
"""

from __future__ import annotations

import inspect
from pathlib import Path
from typing import Any

from neural_estimator.methods import table
from neural_estimator.methods.interface import (  # noqa: F401  re-exported: the interface, for the layers above
    CLASSICAL_METHODS,
    METHODS,
    NEURAL_METHODS,
    Estimates,
    Estimator,
    EstimatorError,
    check_method,
    previous_controls,
)
from neural_estimator.core.options import did_you_mean
from neural_estimator.scenarios import Scenario


PER_MESSAGE_BACKEND = "auto"  # a neural model stepped one message at a time: step.onnx without torch where shipped


def per_message_options(method: str, options: dict[str, Any]) -> dict[str, Any]:
    """``options`` of an estimator stepped one message at a time (the estimator nodes, replay): a
    trained method's (a network's, the hybrid's) backend defaults to ``auto``, ONNX Runtime over
    the checkpoint's ``step.onnx`` (no torch in the process) where it serves the request, torch otherwise
    (:func:`~neural_estimator.serving.load.per_message_backend`). Batched evaluation and training
    keep torch (``make_estimator``'s own default). The live node and replay share this default, so
    replay gives the live node's estimates."""
    options = dict(options)
    if table.has(check_method(method), trainable=True):  # the networks and the hybrid: checkpoints
        options.setdefault("backend", PER_MESSAGE_BACKEND)
    return options


def make_estimator(
    method: str,
    scenario: Scenario,
    *,
    checkpoint: str | Path | Any | None = None,  # Any: a serving.card.Checkpoint (layer 6, not imported)
    device: str = "cpu",
    seed: int = 0,
    **options: Any,
) -> Estimator:
    """Build method ``method`` of the table for ``scenario``, with the factory its spec names.

    Classical filters take their settings from ``options`` (paper defaults otherwise) and ``seed``
    for their random draws. Neural models load ``checkpoint`` (a directory or its ``.json`` card, or a
    :class:`~neural_estimator.serving.card.Checkpoint` already resolved),
    or the model shipped with the package for (scenario, method) when ``checkpoint`` is None;
    their ``options`` go to :func:`~neural_estimator.serving.load.load_neural_estimator`
    (``covariance=False`` skips the Filterformer's per-step covariance).
    """
    m = check_method(method)
    spec = table.spec(m)
    # Resolved here, not imported at the top: the neural side imports torch (1-2 s), which a process
    # that only runs filters (an EKF node, a classical evaluate) should not pay.
    factory = table.resolve(spec.factory)
    if not spec.trainable:  # built from the scenario: its settings in options, seed for its random draws
        return factory(scenario, seed=seed, **options)
    # an unknown option is the caller's one-line error, not a TypeError from deep inside
    valid = [
        n for n in inspect.signature(factory).parameters if n not in ("method", "scenario", "checkpoint", "device")
    ]
    unknown = sorted(set(options) - set(valid))
    if unknown:
        raise EstimatorError(
            f"{m}: unknown option(s) {', '.join(unknown)}{did_you_mean(unknown[-1], valid)}; valid: {', '.join(valid)}"
            + (" (torch threads: the threads setting, not an option)" if "threads" in unknown else "")
        )
    return factory(m, scenario, checkpoint=checkpoint, device=device, **options)
