"""Serving a checkpoint: the shipped zoo, the scenario check, and the estimator a checkpoint makes.

Loading for a scenario checks that the checkpoint belongs to it: same scenario name, same
dimensions, same state/observation/control names and angles, same constants. Two constants may
differ, because they describe an evaluation rather than the system: ``noise_scale`` (the paper's
robustness study evaluates at observation-noise levels beyond training) and ``horizon``. A model
scenario (``--model-set``, :mod:`neural_estimator.scenarios.model`) may also differ in the constants
its model set names: a hybrid trained on the true system is then run with a model that is wrong on
purpose, and the difference is recorded (its description's ``model_set``, in every output).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from neural_estimator.methods import table
from neural_estimator.methods.interface import EstimatorError, check_method
from neural_estimator.serving.card import Checkpoint, default_checkpoint, resolve_checkpoint  # noqa: F401 (the zoo)
from neural_estimator.core.options import OptionError, parse_bool, parse_value
from neural_estimator.serving.onnx_runtime import WindowMismatch, load_onnx_estimator, onnx_beside
from neural_estimator.scenarios import EVALUATION_CONSTANTS, Scenario
from neural_estimator.scenarios.model import model_set_of

SERVING_BACKENDS = ("auto", "torch", "onnxruntime")


def _dims(desc: dict[str, Any]) -> tuple[int, int, int]:
    return len(desc.get("state_names", ())), len(desc.get("obs_names", ())), len(desc.get("control_names", ()))


def check_scenario(desc: dict[str, Any], scenario: Scenario, where: str) -> None:
    """Refuse a checkpoint trained on another scenario, other dimensions or other constants.

    Args:
        desc: the checkpoint's scenario description.
        scenario: the scenario it is to serve.
        where: how to name the checkpoint in messages.
    """
    ours = scenario.describe()
    dx, dy, du = _dims(desc)
    if desc.get("scenario") != ours["scenario"]:
        raise EstimatorError(
            f"checkpoint {where} was trained on scenario {desc.get('scenario')!r} (dx={dx}, dy={dy}, du={du}), "
            f"not {ours['scenario']!r} (dx={scenario.dx}, dy={scenario.dy}, du={scenario.du})"
        )
    theirs_cfg, ours_cfg = desc.get("config", {}), ours["config"]
    told = set(ours.get("model_set", {}))  # constants made wrong on purpose (--model-set): not refused
    diffs = [
        f"{k}={theirs_cfg.get(k, '<absent>')!r} (checkpoint) vs {ours_cfg.get(k, '<absent>')!r} (requested)"
        for k in sorted(set(theirs_cfg) | set(ours_cfg))
        if k not in EVALUATION_CONSTANTS and k not in told and theirs_cfg.get(k) != ours_cfg.get(k)
    ]
    if (dx, dy, du) != (scenario.dx, scenario.dy, scenario.du):
        raise EstimatorError(
            f"checkpoint {where} was trained on scenario {ours['scenario']!r} with dx={dx}, dy={dy}, du={du}, "
            f"but the requested one has dx={scenario.dx}, dy={scenario.dy}, du={scenario.du}"
            + (f" (constants differ: {'; '.join(diffs)})" if diffs else "")
        )
    for key in ("state_names", "obs_names", "control_names", "angle_states", "angle_obs"):
        if list(desc.get(key, [])) != list(ours[key]):
            raise EstimatorError(
                f"checkpoint {where} was trained on scenario {ours['scenario']!r} with {key}={desc.get(key)}, "
                f"but the requested one has {key}={ours[key]}"
            )
    if diffs:
        preset = type(scenario).preset_of(theirs_cfg)
        hint = f" (preset {preset}: --preset {preset})" if preset not in (None, "custom") else ""
        raise EstimatorError(
            f"checkpoint {where} was trained on scenario {ours['scenario']!r} with other constants: "
            f"{'; '.join(diffs)}. Use the checkpoint's constants{hint}, or train a model for these "
            f"(only {', '.join(EVALUATION_CONSTANTS)} may differ)"
        )


def per_message_backend(
    directory: Path,
    card: dict[str, Any],
    device: Any = "cpu",
    context: Any = None,
    compile_step: Any = False,
    context_copies: Any = None,
) -> str:
    """The ``auto`` backend's choice for a per-message (batch-1) estimator: ``onnxruntime`` where the
    checkpoint directory holds ``step.onnx`` and the request is what that graph serves (the cpu, no
    ``compile_step``, a recurrent model's context as the card validated it, the graph ``train``
    writes: unbounded, or L steps by K restarted copies); ``torch`` otherwise. An attention model's
    ``context`` other than the exported window, or a graph exported with another context than
    its card's, falls back to torch at load."""
    if onnx_beside(directory) is None or str(device).strip().lower() != "cpu":
        return "torch"
    try:
        if parse_bool(compile_step, "compile_step"):
            return "torch"
        asked = requested_context(card, context, context_copies)
    except OptionError as exc:
        raise EstimatorError(str(exc)) from None
    if table.has(card["method"], context="window"):
        return "onnxruntime"
    return "onnxruntime" if asked == requested_context(card, None, None) else "torch"


def requested_context(card: dict[str, Any], context: Any = None, context_copies: Any = None) -> tuple[int, int]:
    """(L, K): the bounded context a request asks of a checkpoint, as the torch load resolves it
    (None: the card's validated one; K 10 when only ``context`` is given), (0, 0) unbounded.

    Raises:
        OptionError: a malformed ``context`` or ``context_copies``.
    """
    if context is None:
        validated = validated_context(card)
        context = validated.get("context", 0)
        context_copies = validated.get("context_copies") if context_copies is None else context_copies
    length = parse_value(context, 0, "context")
    if not length:
        return 0, 0
    return length, 10 if context_copies is None else parse_value(context_copies, 10, "context_copies")


def validated_context(card: dict[str, Any]) -> dict[str, int]:
    """The bounded context a checkpoint was validated with, as ``NeuralEstimator`` keywords
    (``context``, ``context_copies``), or {} for a model validated the paper's way (continuously):
    the context it serves with by default (``training.recipe.val_context``)."""
    recipe = (card.get("training") or {}).get("recipe") or {}
    if not recipe.get("val_context"):
        return {}
    return {"context": recipe["val_context"], "context_copies": recipe.get("val_context_copies", 10)}


def load_neural_estimator(
    method: str,
    scenario: Scenario,
    checkpoint: str | Path | Checkpoint | None = None,
    device: str = "cpu",
    covariance: bool = True,
    compile_step: bool = False,
    context: int | None = None,
    context_copies: int | None = None,
    backend: str = "torch",
    cov_scale: float = 1.0,
):
    """A :class:`~neural_estimator.serving.neural.NeuralEstimator` of ``method`` for ``scenario``.

    Args:
        method: gru, lstm, gpt2, filterformer, mamba or mamba2.
        scenario: the system to serve; the checkpoint must have been trained on it.
        checkpoint: a checkpoint directory or its ``card.json``, or a
            :class:`~neural_estimator.serving.card.Checkpoint` already resolved; None -> the shipped
            default at ``neural_estimator/serving/zoo/<scenario>-<method>/``.
        device: cpu, cuda, cuda:N or auto.
        covariance: report the covariance: the fitted covariance head's where the card has one
            (``covariance_head``, :mod:`neural_estimator.serving.uncertainty.heads`), else Filterformer's
            own; False reports none (and saves memory in ``run``).
        compile_step: serve ``step`` through ``torch.compile`` (see NeuralEstimator).
        context, context_copies: bound every estimate's context (GRU, LSTM, Mamba, Mamba-2; see
            :mod:`neural_estimator.serving.context`); 0 = unbounded, the paper's way. None: as the
            model was validated (the card's ``training.recipe.val_context`` and
            ``val_context_copies``; unbounded for a model validated the paper's way), copies 10
            when only ``context`` is given.
        backend: ``torch`` or ``onnxruntime``: ``step`` runs the model's step exported to ONNX
            (:mod:`neural_estimator.models.onnx_step`; GRU, LSTM, Mamba, Mamba-2 unbounded or with
            their restarted copies as one batch, GPT-2 and Filterformer with their window). Where the
            checkpoint directory holds ``step.onnx`` (written by ``train``, shipped beside the zoo models, or
            ``scripts/export_onnx.py --beside``) that graph is served without torch
            (:class:`~neural_estimator.serving.onnx_runtime.OnnxEstimator`, batch 1, ``run`` a loop of
            ``step``); otherwise the step is exported at load and ``run`` keeps torch's parallel form.
            ``auto`` (the per-message default of the estimator nodes and replay, see
            :func:`per_message_backend`): ``step.onnx`` without torch where the checkpoint has one
            that serves the request, torch otherwise. A hybrid's graph holds the f and h it was
            trained with: told another model (a model scenario, ``--model-set``) it is served by
            torch under ``auto`` and refused under ``onnxruntime``.
        cov_scale: the reported covariance is ``cov_scale`` times the model's (see NeuralEstimator).

    Raises:
        EstimatorError: no shipped default (the message gives the command that trains one), a
            checkpoint of another method or scenario, missing or corrupt files.
    """
    m = check_method(method)
    ckpt = resolve_checkpoint(checkpoint, scenario.name, m)  # the card read once; the weights hashed where loaded
    directory, card = ckpt.directory, ckpt.card
    if card["method"] != m:
        raise EstimatorError(f"checkpoint {directory} holds a {card['method']!r} model, not {m!r}")
    check_scenario(card["scenario"], scenario, str(directory))
    if backend not in SERVING_BACKENDS:
        raise EstimatorError(f"{m}: backend must be one of {', '.join(SERVING_BACKENDS)}, got {backend!r}")
    auto = backend == "auto"
    if auto:
        backend = per_message_backend(directory, card, device, context, compile_step, context_copies)
    onnx = backend == "onnxruntime" and onnx_beside(directory) is not None
    if onnx and _told_another_model(m, card, scenario, auto):
        backend = "torch"  # torch builds the hybrid around the told model's f and h
    if backend == "onnxruntime" and onnx_beside(directory) is not None:  # served without torch
        options = _onnx_options(m, card, device, context, context_copies, covariance, cov_scale)
        (ctx, copies), covariance, cov_scale = options
        try:
            return load_onnx_estimator(directory, card, scenario, ctx, covariance, cov_scale, copies)
        except WindowMismatch:
            if not auto:
                raise
            backend = "torch"  # another window than the exported one: torch sets it
    # torch from here on: imported only where a model is loaded into it
    from neural_estimator.serving.checkpoint import load_checkpoint
    from neural_estimator.serving.neural import NeuralEstimator

    model, normalizer, card = load_checkpoint(ckpt, device, scenario)
    if covariance and card.get("covariance_head"):  # a fitted covariance head (replaces Filterformer's own)
        from neural_estimator.serving.uncertainty.heads import attach_head

        model = attach_head(model, directory, card["covariance_head"])
    if context is None:  # as the checkpoint was chosen: bounded if its validation was
        validated = validated_context(card)
        context = validated.get("context", 0)
        context_copies = validated.get("context_copies") if context_copies is None else context_copies
    if context_copies is None:
        context_copies = 10
    return NeuralEstimator(
        scenario,
        model,
        normalizer,
        m,
        device=device,
        covariance=covariance,
        card=card,
        compile_step=compile_step,
        context=context,
        context_copies=context_copies,
        backend=backend,
        cov_scale=cov_scale,
    )


def _told_another_model(method: str, card: dict[str, Any], scenario: Scenario, auto: bool) -> bool:
    """Whether a model-based method (the hybrid) is asked to serve with another model than the one
    its card was trained with (a ``--model-set``/``model_set`` other than its recipe's): its exported
    step has the trained model's f and h in the graph, so it cannot answer for the told one. Asked
    for that graph explicitly (not ``auto``): EstimatorError."""
    if not table.has(method, needs_model=True):
        return False
    recipe = (card.get("training") or {}).get("recipe") or {}
    trained = {k: str(v) for k, v in (recipe.get("model_set") or {}).items()}
    if model_set_of(scenario) == trained:
        return False
    if not auto:
        raise EstimatorError(
            f"{method}: the step.onnx beside its card holds the f and h of the model it was trained with, not "
            f"the model told now (model set {model_set_of(scenario)}): serve it with backend torch"
        )
    return True


def _onnx_options(m: str, card: dict, device: str, context, context_copies, covariance, cov_scale) -> tuple:
    """((context, copies), covariance, cov_scale) parsed for the exported step beside the card, which
    serves on the cpu; an attention model without a ``context`` asked keeps the window it was
    exported with."""
    if str(device).lower() not in ("cpu", "auto"):
        raise EstimatorError(f"{m}: the exported step beside the card serves on the cpu, not {device!r}")
    try:
        ctx = requested_context(card, context, context_copies)
        covariance, cov_scale = (
            parse_bool(covariance, "covariance"),
            float(parse_value(cov_scale, 1.0, "cov_scale")),
        )
    except OptionError as exc:
        raise EstimatorError(str(exc)) from None
    if table.has(m, context="window"):
        ctx = (0 if context is None else ctx[0], 0)  # None: the window it was exported with
    return ctx, covariance, cov_scale
