"""Writing ``step.onnx`` beside a checkpoint's card: the graph the per-message estimators serve
without torch (the estimator nodes and replay, backend ``auto``).

``train`` calls :func:`export_beside` when it saves a model, the covariance-head fitting when it
changes the head, and ``scripts/export_onnx.py --beside`` on demand; the zoo ships its results. The
graph is :func:`neural_estimator.models.onnx_step.export_step` of the checkpoint as it serves by
default, with the digests of the files it was made from in its metadata, so a graph older than its
card is refused at load rather than served.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from neural_estimator.methods import table
from neural_estimator.methods.interface import EstimatorError
from neural_estimator.models.onnx_step import OnnxError, export_step
from neural_estimator.scenarios import ScenarioError, scenario_from_description
from neural_estimator.serving.card import read_card
from neural_estimator.serving.load import load_neural_estimator
from neural_estimator.serving.onnx_runtime import ONNX_FILE, served_files


def export_beside(directory: str | Path, scenario: Any = None) -> Path | None:
    """Write ``step.onnx`` beside a checkpoint's card: the network-only step of the configuration the
    checkpoint serves by default, the covariance head included where the card has one, with the
    digests of the files it was made from (:func:`~neural_estimator.serving.onnx_runtime.served_files`).

    A recurrent model validated with a bounded context (the card's ``val_context``, L steps by K
    restarted copies) gets the step of its K copies as one batch (``export_step(copies=(L, K))``),
    which the torch-free estimator restarts and reads as torch's copies do.

    Returns its path, or None (a stale ``step.onnx`` removed) where that configuration is not one
    exported step (:func:`torch_only_reason` says why): a hybrid whose system's f or h has no ONNX
    form (N-link's linear solve).

    Args:
        directory: the checkpoint directory.
        scenario: the scenario it serves (default: rebuilt from the card; a model trained on recorded
            data passes its own).

    Raises:
        OnnxError: the step cannot be exported (the message says why).
    """
    directory = Path(directory)
    out = directory / ONNX_FILE
    try:
        _, card = read_card(directory)
        scenario = scenario_from_description(card["scenario"]) if scenario is None else scenario
        est = load_neural_estimator(card["method"], scenario, directory, backend="torch")
    except (EstimatorError, ScenarioError) as exc:
        raise OnnxError(f"{directory}: {exc}") from None
    if torch_only_reason(est) is not None or not table.has(card["method"], exportable=True):
        out.unlink(missing_ok=True)
        return None
    tmp = directory / (ONNX_FILE + ".tmp")
    copies = (est.context, est.context_copies) if est.context_by_copies else None
    export_step(est.model, est.method, tmp, covariance=est.has_covariance, metadata=served_files(card), copies=copies)
    tmp.replace(out)
    return out


def torch_only_reason(est: Any) -> str | None:
    """Why a loaded estimator's default serving configuration has no exported step (so its
    per-message backend is torch), or None where it has one."""
    return getattr(est.model, "onnx_blocker", None)  # a hybrid's system without an ONNX form
