"""The setup the estimator node and the lifecycle estimator share (one path, so that the two serve a
method alike): the parameters checked, the method's options read from them, the estimator built,
warmed up and wrapped for per-message updates, the standard outputs made, and one result published.

The estimator node runs it at start-up (or when the scenario is announced), the lifecycle node in its
configure and activate transitions; both turn a :class:`~neural_estimator.nodes.common.StartupError`
into their own failure (exit status 1, or a failed transition). The robot estimator makes its
standard outputs here too.
"""

from __future__ import annotations

import sys
from pathlib import Path

from neural_estimator.stream.online import OnlineEstimator, warm_up
from neural_estimator.methods import table
from neural_estimator.methods.registry import EstimatorError, check_method, make_estimator, per_message_options
from neural_estimator.nodes.common import StartupError, settle_heap
from neural_estimator.nodes.estimator_params import OBSERVATION_QOS, EstimatorParams, online_estimator
from neural_estimator.nodes.outputs import OutputError, Outputs


def checked_method(p: EstimatorParams) -> str:
    """The method the parameters name, after the checks made before anything is built: a known method,
    an existing checkpoint, a known observation QoS, a usable history bound. Raises StartupError."""
    try:
        method = check_method(p.method)
    except EstimatorError as exc:
        raise StartupError(str(exc)) from None
    if p.checkpoint and not Path(p.checkpoint).exists():
        raise StartupError(f"checkpoint {p.checkpoint!r} does not exist")
    if p.observation_qos not in OBSERVATION_QOS:
        raise StartupError(
            f"parameter observation_qos must be one of {', '.join(OBSERVATION_QOS)}, got {p.observation_qos!r}"
        )
    if p.history_mb <= 0 or p.history_depth < 1:
        raise StartupError("history_depth must be >= 1 and history_mb > 0")
    from neural_estimator.scenarios import ScenarioError
    from neural_estimator.scenarios.model import parse_model_set

    try:  # its form now; its names and values against the scenario when it is built (told_scenario)
        parse_model_set(p.model_set)
    except ScenarioError as exc:
        raise StartupError(f"parameter model_set: {exc}") from None
    return method


def model_note(method: str, p: EstimatorParams) -> str:
    """'' or '; model told on purpose: forcing=8.5 (model_set)' for the start-up log of a model-based method."""
    if not p.model_set.strip() or not table.has(method, needs_model=True):
        return ""
    return f"; model told on purpose: {p.model_set.strip()} (model_set)"


def method_options(method: str, p: EstimatorParams) -> dict[str, str]:
    """The method's options: the ``options`` parameter (name=value items), a classical filter's start
    from ``init`` unless the options name one, and the per-message backend (ONNX Runtime where a
    ``step.onnx`` serves the model). Raises StartupError for an item that is not name=value."""
    try:
        options = dict(item.split("=", 1) for item in p.options)
    except ValueError:
        raise StartupError(f"options must be name=value, got {list(p.options)}") from None
    if p.init != "prior" and table.has(method, takes_init=True):
        options.setdefault("init", p.init)
    return per_message_options(method, options)


def told_scenario(method: str, scenario, p: EstimatorParams):
    """The scenario ``method`` is built with: for a model-based method the model scenario of the
    ``model_set`` parameter (:func:`~neural_estimator.scenarios.model.model_scenario`), else
    ``scenario``. Raises StartupError (one line) for a bad item, an unknown constant or a bad value."""
    from neural_estimator.scenarios import ScenarioError
    from neural_estimator.scenarios.model import model_scenario, parse_model_set

    try:
        told = parse_model_set(p.model_set)  # checked for every method: a typo is never silently ignored
        model = model_scenario(scenario, told)
    except ScenarioError as exc:
        raise StartupError(f"parameter model_set: {exc}") from None
    return model if table.has(method, needs_model=True) else scenario


def build_online(method: str, scenario, p: EstimatorParams, horizon: int | None = None) -> tuple:
    """(the estimator, its :class:`OnlineEstimator`) of ``method`` on ``scenario`` (for a model-based
    method, with the ``model_set`` parameter's model: :func:`told_scenario`) as the parameters ask:
    built (torch's threads set where torch serves it), warmed up, and its objects moved out of the
    collector's reach. Raises StartupError."""
    options = method_options(method, p)
    told = told_scenario(method, scenario, p)
    try:
        est = make_estimator(method, told, checkpoint=p.checkpoint or None, device=p.device, seed=p.seed, **options)
    except EstimatorError as exc:
        raise StartupError(str(exc)) from None
    torch = sys.modules.get("torch")  # absent when the model is served without torch (step.onnx)
    if p.threads > 0 and table.has(method, uses_torch=True) and torch is not None:
        torch.set_num_threads(p.threads)
    warm_up(est, scenario)
    online: OnlineEstimator = online_estimator(est, method, p, horizon)
    settle_heap()  # the model's objects, built now, out of the collector's reach
    return est, online


def standard_outputs(node, po, p: EstimatorParams, out_topic: str, qos, scenario, **kwargs) -> Outputs:
    """The standard outputs (:class:`~neural_estimator.nodes.outputs.Outputs`) beside ``out_topic``.
    Raises StartupError."""
    try:
        return Outputs(
            node,
            po,
            out_topic,
            qos,
            p.frame_id,
            p.child_frame_id,
            scenario.state_names,
            getattr(scenario, "pose_states", {}),
            p.publish_odometry,
            **kwargs,
        )
    except OutputError as exc:
        raise StartupError(str(exc)) from None


def publish_result(res, pub_est, pub_cov, outputs: Outputs) -> None:
    """One estimated result out: the estimate, its covariance where there is a publisher for it, and
    the standard outputs."""
    pub_est.publish(res.estimate)
    if res.covariance is not None and pub_cov is not None:
        pub_cov.publish(res.covariance)
    outputs.publish(res.stamp_ns, res.x_hat, res.P)
