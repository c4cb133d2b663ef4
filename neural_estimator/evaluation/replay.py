"""Bag replay: a bag's observations through estimators at full speed, without DDS, into a new bag.

Each observation goes through :class:`~neural_estimator.stream.online.OnlineEstimator`, the estimator
node's own per-message code, so a replay gives the estimates a live node would have published.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any


from neural_estimator.core.atomic import replaced_atomically, temporary_name
from neural_estimator.stream import messages as MSG
from neural_estimator.bags.errors import BagError, MessageError
from neural_estimator.bags.directory import open_bag
from neural_estimator.bags.writer import LATCHED_QOS, STREAM_QOS, BagWriter, topic_qos
from neural_estimator.methods import table
from neural_estimator.methods.interface import EstimatorError
from neural_estimator.methods.registry import make_estimator, per_message_options

from neural_estimator.stream.online import (
    DEFAULT_MAX_GAP,
    DEFAULT_MAX_GAP_SECONDS,
    OnlineEstimator,
    StepResult,
    set_torch_threads,
)


@dataclasses.dataclass
class ReplayResult:
    """What :func:`replay` wrote."""

    path: Path
    observations: int
    estimates: dict[str, int]  # estimate messages per method
    seconds: dict[str, float]  # time spent in OnlineEstimator.process per method
    rejected: dict[str, int]  # observation messages each method could not use
    skipped: dict[str, int] = dataclasses.field(default_factory=dict)  # duplicate or stale observations

    def per_step_us(self, method: str) -> float:
        return 1e6 * self.seconds[method] / max(1, self.estimates[method])


def replay(
    bag_in: str | Path,
    methods: Sequence[str],
    bag_out: str | Path,
    checkpoints: Mapping[str, str | Path] | None = None,
    *,
    device: str = "cpu",
    seed: int = 0,
    namespace: str = "/",
    options: Mapping[str, Mapping[str, Any]] | None = None,
    publish_covariance: bool = True,
    overwrite: bool = False,
    model_set: Mapping[str, Any] | None = None,
    description: Mapping[str, Any] | None = None,
    order: str = "recorded",
    threads: int = 1,
    force: bool = False,
    max_gap: int = DEFAULT_MAX_GAP,
    max_gap_seconds: float = DEFAULT_MAX_GAP_SECONDS,
) -> ReplayResult:
    """Run a bag's observations through estimators offline and write a bag with their estimates.

    Observations are processed in the order they were recorded (``order="recorded"``: the order
    a live estimator node received them, so a stray or late message is skipped exactly as the
    node skips it) or, with ``order="identity"``, grouped by trajectory with steps in order (for
    bags whose recording order was scrambled), each by :meth:`OnlineEstimator.process`: the
    estimator node's code path, so the estimates equal those a live node computes from the same
    messages. The output holds every message of ``bag_in`` (estimate streams of the replayed
    methods replaced) plus ``estimates/<method>`` (and ``/covariance``) with the log time of the
    observation each one answers.

    Args:
        bag_in: a recorded or sample bag (``.mcap`` file or rosbag2 directory) with an
            ``observation`` stream, and a ``scenario`` stream unless ``description`` is given.
        methods: method names (see :func:`neural_estimator.methods.table.names`).
        bag_out: output ``.mcap``.
        checkpoints: {method: checkpoint} for neural methods (default: the shipped models).
        device, seed: passed to :func:`~neural_estimator.methods.registry.make_estimator`.
        namespace: namespace of the streams.
        options: {method: {option: value}} filter hyperparameters.
        publish_covariance: also write covariance streams where methods have them.
        overwrite: replace an existing ``bag_out``.
        model_set: {constant: value} (and ``Q``/``R`` scales) of the model the model-based methods
            are built with (:func:`~neural_estimator.scenarios.model.model_scenario`); the bag's
            data and the data-trained networks are untouched. None: the true model.
        description: the scenario description (``scenario.describe()``) to use instead of the
            bag's ``scenario`` message (needed for bags without one).
        order: "recorded" (default, as live) or "identity".
        threads: torch intra-op threads for neural methods (one suits per-message B = 1 steps;
            0 = torch's default).
        max_gap, max_gap_seconds: the bound on predict-only bridging (see :class:`OnlineEstimator`).
    """
    from neural_estimator.scenarios import scenario_from_description

    bag_in, bag_out = Path(bag_in), Path(bag_out)
    if order not in ("recorded", "identity"):
        raise BagError(f"order must be 'recorded' or 'identity', got {order!r}")
    if bag_in.resolve() == bag_out.resolve():
        raise BagError(f"{bag_out}: replay cannot overwrite its input bag")
    obs_topic = MSG.resolve_topic(MSG.OBSERVATION, namespace)
    scen_topic = MSG.resolve_topic(MSG.SCENARIO, namespace)
    desc, kept_topics, passthrough = _read_input(bag_in, methods, namespace, obs_topic, scen_topic, description, force)
    scenario = scenario_from_description(desc)
    from neural_estimator.scenarios.model import model_scenario

    model = model_scenario(scenario, model_set)  # a bad name or value: the scenario's one-line error, before any work
    observations = _ordered_observations(passthrough, obs_topic, order)

    out_msgs: list[tuple[str, int, bytes]] = list(passthrough)
    if not any(c.topic == scen_topic for c in kept_topics):  # the output names its scenario even when the input did not
        t0 = min((t for _, t, _ in passthrough), default=0)
        out_msgs.insert(0, (scen_topic, t0, MSG.encode_scenario(desc)))
    counts, seconds, rejected, skipped = {}, {}, {}, {}
    for method in methods:
        ckpt = (checkpoints or {}).get(method)
        options_of = per_message_options(method, dict((options or {}).get(method, {})))  # the live node's backend
        told = model if table.has(method, needs_model=True) else scenario
        est = _estimator(method, told, ckpt, device, seed, options_of, description is None)
        if sys.modules.get("torch") is not None:  # not imported where step.onnx serves the model
            set_torch_threads([method], threads)
        online = OnlineEstimator(
            est,
            method,
            publish_covariance=publish_covariance,
            max_gap=max_gap,
            max_gap_seconds=max_gap_seconds,
            horizon=(desc.get("run") or {}).get("horizon"),
        )
        counts[method], rejected[method], skipped[method] = 0, 0, 0
        seconds[method] = _run_method(
            online, method, namespace, observations, order, out_msgs, counts, rejected, skipped
        )

    _write_atomically(bag_out, kept_topics, out_msgs, scen_topic, methods, options, overwrite)
    return ReplayResult(bag_out, len(observations), counts, seconds, rejected, skipped)


def _read_input(bag_in: Path, methods, namespace: str, obs_topic: str, scen_topic: str, description, force: bool):
    """The input bag read once: the scenario description to run on, the connections kept in the output
    (all but the replayed methods' estimate and covariance streams) and their messages in bag order."""
    replaced = {MSG.resolve_topic(MSG.estimate_topic(m), namespace) for m in methods}
    replaced |= {MSG.resolve_topic(MSG.covariance_topic(m), namespace) for m in methods}
    with open_bag(bag_in) as bag:
        bag.connection(obs_topic, MSG.JOINT_STATE)
        desc = _description(bag, bag_in, scen_topic, description, force)
        kept_topics = [c for c in bag.connections if c.topic not in replaced]
        passthrough = [(conn.topic, t, raw) for conn, t, raw in bag.messages([c.topic for c in kept_topics])]
    if desc is None:
        raise BagError(f"{bag_in}: no message on {scen_topic}: name the scenario (--scenario NAME [--set ...])")
    return desc, kept_topics, passthrough


def _ordered_observations(passthrough: list, obs_topic: str, order: str) -> list:
    """The observations in recorded order (as a live node receives them), or by in-band identity."""
    observations = []
    for i, (topic, t, raw) in enumerate(passthrough):
        if topic != obs_topic:
            continue
        key: tuple[int, int, int] = (0, 0, i)
        if order == "identity":
            try:
                vec = MSG.decode_vector(raw)
                key = (vec.trajectory, vec.step, i)
            except MessageError:
                key = (-1, -1, i)  # unparsable ones keep bag order
        observations.append((key, t, raw))
    observations.sort(key=lambda o: o[0])
    return observations


def _run_method(
    online: OnlineEstimator, method: str, namespace: str, observations: list, order: str, out_msgs: list, *tallies
) -> float:
    """One method over every observation, its estimates appended to ``out_msgs``; ``tallies`` are the
    (counts, rejected, skipped) dicts it adds to. Returns the seconds spent in the estimator."""
    counts, rejected, skipped = tallies
    est_topic = MSG.resolve_topic(MSG.estimate_topic(method), namespace)
    cov_topic = MSG.resolve_topic(MSG.covariance_topic(method), namespace)
    spent = 0.0
    for _, t, raw in observations:
        t0 = time.perf_counter()
        now = t * 1e-9 if order == "recorded" else 0.0  # the receive time: held jumps time out as live
        try:
            results = online.poll(now) + online.feed(raw, now)
        except MessageError:
            rejected[method] += 1
            continue
        finally:
            spent += time.perf_counter() - t0
        for res in results:
            counts[method] += _collect(res, t, est_topic, cov_topic, out_msgs, skipped, method)
    t_end = observations[-1][1] if observations else 0
    for res in online.flush():
        counts[method] += _collect(res, t_end, est_topic, cov_topic, out_msgs, skipped, method)
    return spent


def _write_atomically(bag_out: Path, kept_topics: list, out_msgs: list, scen_topic: str, methods, options, overwrite):
    """The output bag written complete or not at all: a full disk leaves no partial bag under the name
    asked for."""
    qos = {c.topic: topic_qos(c.topic, c.offered_qos_profiles) for c in kept_topics}
    types = {c.topic: c for c in kept_topics}
    out_msgs.sort(key=lambda m: m[1])  # stable: per time, input order then methods in order
    if Path(bag_out).exists() and not overwrite:
        raise BagError(f"{bag_out}: file exists (pass overwrite=True to replace it)")
    try:
        with replaced_atomically(bag_out) as tmp:
            _write_output(tmp, types, qos, out_msgs, scen_topic, methods, options)
    except BagError as exc:
        raise BagError(str(exc).replace(str(temporary_name(Path(bag_out))), str(bag_out))) from None


def _write_output(path: Path, types: dict, qos: dict, out_msgs: list, scen_topic: str, methods, options) -> None:
    """The output bag: how the filters started, the kept input topics with their recorded QoS, then
    every message in time order."""
    with BagWriter(path, overwrite=True) as out:
        _record_starts(out, methods, options)
        for topic, conn in types.items():
            out.add_topic(
                topic, conn.msgtype, qos=qos[topic], msgdef=conn.msgdef or None, type_hash=conn.type_hash or None
            )
        for topic, t, raw in out_msgs:
            if not out.has_topic(topic):
                out.add_topic(
                    topic,
                    MSG.STRING if topic == scen_topic else MSG.JOINT_STATE,
                    qos=[LATCHED_QOS if topic == scen_topic else STREAM_QOS],
                )
            out.write(topic, t, raw)


def _collect(res: StepResult, t: int, est_topic: str, cov_topic: str, out_msgs: list, skipped: dict, method: str):
    """Append an estimated result's messages at log time ``t``; count the skipped ones. 1 if estimated."""
    if res.estimate is None:
        skipped[method] += res.status != "held"  # a held message is counted once, when dropped
        return 0
    out_msgs.append((est_topic, t, res.estimate))
    if res.covariance is not None:
        out_msgs.append((cov_topic, t, res.covariance))
    return 1


def _estimator(method, scenario, ckpt, device, seed, options, constants_from_bag: bool):
    """make_estimator; a checkpoint refused for other constants than the bag's own data is pointed
    at another bag or another model (not at a --preset, which would run it on other data)."""
    try:
        return make_estimator(method, scenario, checkpoint=ckpt, device=device, seed=seed, **dict(options))
    except EstimatorError as exc:
        if constants_from_bag and "other constants" in str(exc):
            head = str(exc).split(". Use the checkpoint's constants")[0].replace("(requested)", "(this bag)")
            raise EstimatorError(
                f"{head}. The requested constants are this bag's data: replay a bag recorded with the "
                "checkpoint's constants (bags/ holds one per preset), or train a model on this bag's"
            ) from None
        raise


def _record_starts(out: BagWriter, methods, options) -> None:
    """How the filters started (their ``init`` option), as the evaluator records it: `metrics` on the
    output bag then marks them as the run did."""
    starts = {m: str(o["init"]) for m, o in (options or {}).items() if m in methods and o.get("init")}
    if starts:
        from neural_estimator.evaluation.bag_report import STARTS_METADATA

        out.metadata[STARTS_METADATA] = starts


def _description(bag, bag_in: Path, scen_topic: str, description: Mapping[str, Any] | None, force: bool):
    """The scenario description to run on: ``description`` (checked against the bag's own
    announcement unless ``force``), else the bag's first ``scenario`` message (None if it has none)."""
    recorded = None
    if scen_topic in bag.topics:
        bag.connection(scen_topic, MSG.STRING)
        for _, _, raw in bag.messages([scen_topic]):
            recorded = MSG.decode_scenario(raw)
            break  # the first announcement defines the run
    if description is None:
        if recorded is None and scen_topic not in bag.topics:
            raise BagError(f"{bag_in}: no {scen_topic} topic: name the scenario (--scenario NAME [--set ...])")
        return recorded
    if recorded is not None and not force:
        _check_same_constants(bag_in, recorded, description)
    return dict(description)


def _check_same_constants(bag: str | Path, recorded: Mapping[str, Any], requested: Mapping[str, Any]) -> None:
    """A bag announces the constants its data were made with: a description naming others would run
    estimators (a model of another preset, a filter with other noise) on data they do not describe.
    Raises BagError naming both, unless the caller forces it."""
    from neural_estimator.scenarios.base import EVALUATION_CONSTANTS

    if recorded.get("scenario") != requested.get("scenario"):
        raise BagError(
            f"{bag}: recorded on scenario {recorded.get('scenario')!r}, not {requested.get('scenario')!r} "
            "(--scenario): drop --scenario to use the bag's own, or pass --force"
        )
    ours, theirs = dict(requested.get("config") or {}), dict(recorded.get("config") or {})
    diffs = [
        f"{k}={theirs.get(k, '<absent>')!r} (bag) vs {ours.get(k, '<absent>')!r} (requested)"
        for k in sorted(set(ours) | set(theirs))
        if k not in EVALUATION_CONSTANTS and ours.get(k) != theirs.get(k)
    ]
    if diffs:
        raise BagError(
            f"{bag}: its data were made with other constants than --scenario/--preset/--set name: {'; '.join(diffs)}. "
            "Drop them to use the bag's own, or pass --force to run the estimators on these data anyway"
        )
