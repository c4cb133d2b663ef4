"""Estimation per observation message: the one code path of the live estimator node and of replay.

:class:`OnlineEstimator` turns one observation message (CDR bytes, layout of
:mod:`neural_estimator.bags.messages`) into the estimate message (and covariance message) of that
step. The estimator node calls it from its subscription callback; :func:`replay` calls it for every
observation of a bag at full speed, without DDS. Same bytes in, same calls, same estimates out.

Stream rules (one estimator, B = 1), applied in arrival order (replay uses the bag's order, the
order a live node received the messages in, so both give the same estimates):

- the first message, a message of a later trajectory, or a step 0 stamped after the last processed
  message (a new run that restarts its trajectory indices) starts a new stream: the estimator is
  reset to its prior;
- a message of an earlier trajectory (a stray message arriving late), or a step at or before the
  last one processed in the current trajectory, is skipped (``stale`` or ``duplicate``, the
  caller counts and logs it); the estimator state is untouched. A stray message never resets;
- a step later than the next one means observations were lost: the missing steps are run as
  predict-only steps (observation NaN, the last received control held), so that the estimate of
  step k is still an estimate of x_k. The bridge is bounded: more than ``max_gap`` missing steps,
  or predict-only steps running longer than ``max_gap_seconds``, restart the stream from the prior
  at this message, so one message with a huge step jump costs at most about ``max_gap_seconds``;
- a non-finite value in y_k is used as "no observation" (filters predict only, neural models see
  their training mean, per the estimator contract) and reported; a non-finite control, wrong names
  or widths, an empty or unparsable message raise :class:`~neural_estimator.bags.errors.MessageError`
  and leave the estimator state untouched.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from neural_estimator.bags import messages as M
from neural_estimator.bags.errors import BagError, MessageError
from neural_estimator.bags.reader import open_bag
from neural_estimator.bags.writer import LATCHED_QOS, STREAM_QOS, BagWriter, parse_qos_yaml
from neural_estimator.estimators import NEURAL_METHODS, Estimator, EstimatorError, make_estimator

DEFAULT_MAX_GAP = 1_000
DEFAULT_MAX_GAP_SECONDS = 0.25


@dataclasses.dataclass(frozen=True)
class StepResult:
    """Outcome of one observation message."""

    status: str  # "estimated", "duplicate" or "stale" (out of order, or of an earlier trajectory)
    trajectory: int
    step: int
    stamp_ns: int
    estimate: bytes | None = None  # estimate message (when estimated)
    covariance: bytes | None = None  # covariance message (when estimated and published)
    x_hat: np.ndarray | None = None  # (dx,)
    reset: bool = False  # this message started a new stream
    filled: int = 0  # missing steps run as predict-only before this one
    restarted: bool = False  # the gap exceeded max_gap (or max_gap_seconds): the stream restarted here
    nonfinite: bool = False  # y_k had NaN/inf: predict only
    diverged: bool = False  # the estimator's stream is diverged (estimates NaN until reset)


class OnlineEstimator:
    """One estimator (B = 1) fed with observation messages (see the module docstring).

    Args:
        estimator: any of the ten methods, built for the scenario of the stream.
        method: the method name (the estimates' frame_id unless ``frame_id`` is given).
        publish_covariance: build covariance messages where the method has a covariance.
        max_gap: the most missing steps filled with predict-only steps.
        max_gap_seconds: the most seconds spent filling one gap (0 = no time bound).
        frame_id: header.frame_id of the estimate and covariance messages (default: the method).
    """

    def __init__(
        self,
        estimator: Estimator,
        method: str,
        *,
        publish_covariance: bool = True,
        max_gap: int = DEFAULT_MAX_GAP,
        max_gap_seconds: float = DEFAULT_MAX_GAP_SECONDS,
        frame_id: str | None = None,
    ) -> None:
        self.estimator = estimator
        self.scenario = estimator.scenario
        self.method = method
        self.publish_covariance = bool(publish_covariance and estimator.has_covariance)
        self.max_gap = int(max_gap)
        self.max_gap_seconds = float(max_gap_seconds)
        self._obs_labels = M.observation_labels(self.scenario)
        self._obs_codec = M.VectorCodec(self.scenario.name, self._obs_labels)
        frame = method if frame_id is None else frame_id
        self._est_codec = M.VectorCodec(frame, M.state_labels(self.scenario))
        self._cov_codec = M.VectorCodec(frame, M.covariance_labels(self.scenario.dx))
        self._dy = self.scenario.dy
        self.trajectory: int | None = None
        self.step = -1
        self._u_hold = np.zeros((1, self.scenario.du))
        self._last_stamp: int | None = None  # stamp of the last processed message

    def reset(self) -> None:
        """Forget the current stream; the next message starts from the prior."""
        self.trajectory = None
        self.step = -1
        self._last_stamp = None

    def _classify(self, trajectory: int, step: int, stamp_ns: int) -> str:
        """ "new" (start a stream here), "next" (continue), "duplicate" or "stale" (skip)."""
        if self.trajectory is None:
            return "new"
        newer = self._last_stamp is None or stamp_ns > self._last_stamp
        if step == 0 and newer and (trajectory != self.trajectory or self.step >= 0):
            return "new"  # a new trajectory, or a new run restarting the indices
        if trajectory > self.trajectory:
            return "new"
        if trajectory < self.trajectory:
            return "stale"  # a stray message of an earlier trajectory
        if step <= self.step:
            return "duplicate" if step == self.step else "stale"
        return "next"

    def _start(self, trajectory: int) -> None:
        self.estimator.reset(1)
        self.trajectory = trajectory
        self.step = -1
        self._u_hold = np.zeros((1, self.scenario.du))

    def _bridge(self, gap: int) -> tuple[int, bool]:
        """Run ``gap`` predict-only steps; (steps run, False), or (0, True) when they would take
        longer than ``max_gap_seconds`` (checked as they run: the cost per step is method-dependent)."""
        nan_y = np.full((1, self._dy), np.nan)
        deadline = time.perf_counter() + self.max_gap_seconds if self.max_gap_seconds > 0 else None
        for i in range(gap):
            self.estimator.step(nan_y, self._u_hold)
            if deadline is not None and time.perf_counter() > deadline and i + 1 < gap:
                return 0, True
        return gap, False

    def process(self, raw: bytes | memoryview) -> StepResult:
        """Consume one observation message; raises MessageError for a message that cannot be used."""
        vec = self._obs_codec.decode(raw)
        values = M.check_labels(vec, self._obs_labels, "observation")
        y, u_prev = values[None, : self._dy], values[None, self._dy :]
        if not np.all(np.isfinite(u_prev)):
            raise MessageError(f"observation {vec.trajectory}/{vec.step}: control u_prev contains NaN or inf")
        kind = self._classify(vec.trajectory, vec.step, vec.stamp_ns)
        if kind in ("duplicate", "stale"):
            return StepResult(kind, vec.trajectory, vec.step, vec.stamp_ns)
        reset = kind == "new"
        if reset:
            self._start(vec.trajectory)
        gap = vec.step - self.step - 1
        restarted = False
        if gap > self.max_gap:
            gap, restarted = 0, True
        elif gap:
            gap, restarted = self._bridge(gap)
        if restarted:  # too long to bridge: estimate from the prior from here on
            self._start(vec.trajectory)
        try:
            x_hat = self.estimator.step(y, u_prev)[0]
        except EstimatorError as exc:  # the checks above should make this unreachable
            raise MessageError(f"observation {vec.trajectory}/{vec.step}: {exc}") from None
        self.step = vec.step
        self._last_stamp = vec.stamp_ns
        self._u_hold = u_prev
        est = self._est_codec.encode(vec.stamp_ns, vec.trajectory, vec.step, x_hat)
        cov = None
        if self.publish_covariance and self.estimator.covariance is not None:
            cov = self._cov_codec.encode(vec.stamp_ns, vec.trajectory, vec.step, self.estimator.covariance[0])
        diverged = bool(self.estimator.diverged[0]) if len(self.estimator.diverged) else False
        return StepResult(
            "estimated",
            vec.trajectory,
            vec.step,
            vec.stamp_ns,
            est,
            cov,
            x_hat,
            reset=reset,
            filled=gap,
            restarted=restarted,
            nonfinite=not bool(np.all(np.isfinite(y))),
            diverged=diverged,
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
    description: Mapping[str, Any] | None = None,
    order: str = "recorded",
    threads: int = 1,
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
        methods: method names (see :data:`neural_estimator.estimators.METHODS`).
        bag_out: output ``.mcap``.
        checkpoints: {method: checkpoint} for neural methods (default: the shipped models).
        device, seed: passed to :func:`~neural_estimator.estimators.make_estimator`.
        namespace: namespace of the streams.
        options: {method: {option: value}} filter hyperparameters.
        publish_covariance: also write covariance streams where methods have them.
        overwrite: replace an existing ``bag_out``.
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
    obs_topic = M.resolve_topic(M.OBSERVATION, namespace)
    scen_topic = M.resolve_topic(M.SCENARIO, namespace)
    replaced = {M.resolve_topic(M.estimate_topic(m), namespace) for m in methods}
    replaced |= {M.resolve_topic(M.covariance_topic(m), namespace) for m in methods}
    with open_bag(bag_in) as bag:
        bag.connection(obs_topic, M.JOINT_STATE)
        desc = dict(description) if description is not None else None
        if desc is None:
            if scen_topic not in bag.topics:
                raise BagError(f"{bag_in}: no {scen_topic} topic: name the scenario (--scenario NAME [--set ...])")
            bag.connection(scen_topic, M.STRING)
            for _, _, raw in bag.messages([scen_topic]):
                desc = M.decode_scenario(raw)
        kept_topics = [c for c in bag.connections if c.topic not in replaced]
        passthrough = [(conn.topic, t, raw) for conn, t, raw in bag.messages([c.topic for c in kept_topics])]
    if desc is None:
        raise BagError(f"{bag_in}: no message on {scen_topic}: name the scenario (--scenario NAME [--set ...])")
    scenario = scenario_from_description(desc)
    set_torch_threads(methods, threads)

    # The observations in recorded order (as a live node receives them), or by in-band identity.
    observations = []
    for i, (topic, t, raw) in enumerate(passthrough):
        if topic != obs_topic:
            continue
        key: tuple[int, int, int] = (0, 0, i)
        if order == "identity":
            try:
                vec = M.decode_vector(raw)
                key = (vec.trajectory, vec.step, i)
            except MessageError:
                key = (-1, -1, i)  # unparsable ones keep bag order
        observations.append((key, t, raw))
    observations.sort(key=lambda o: o[0])

    out_msgs: list[tuple[str, int, bytes]] = list(passthrough)
    added_scenario = not any(c.topic == scen_topic for c in kept_topics)
    if added_scenario:  # the output names its scenario even when the input did not
        t0 = min((t for _, t, _ in passthrough), default=0)
        out_msgs.insert(0, (scen_topic, t0, M.encode_scenario(desc)))
    counts, seconds, rejected, skipped = {}, {}, {}, {}
    for method in methods:
        ckpt = (checkpoints or {}).get(method)
        est = make_estimator(
            method, scenario, checkpoint=ckpt, device=device, seed=seed, **dict((options or {}).get(method, {}))
        )
        online = OnlineEstimator(
            est, method, publish_covariance=publish_covariance, max_gap=max_gap, max_gap_seconds=max_gap_seconds
        )
        est_topic = M.resolve_topic(M.estimate_topic(method), namespace)
        cov_topic = M.resolve_topic(M.covariance_topic(method), namespace)
        counts[method], rejected[method], skipped[method], spent = 0, 0, 0, 0.0
        for _, t, raw in observations:
            t0 = time.perf_counter()
            try:
                res = online.process(raw)
            except MessageError:
                rejected[method] += 1
                continue
            finally:
                spent += time.perf_counter() - t0
            if res.estimate is None:
                skipped[method] += 1
            else:
                out_msgs.append((est_topic, t, res.estimate))
                counts[method] += 1
            if res.covariance is not None:
                out_msgs.append((cov_topic, t, res.covariance))
        seconds[method] = spent

    qos = {c.topic: parse_qos_yaml(c.offered_qos_profiles) for c in kept_topics}
    types = {c.topic: c for c in kept_topics}
    out_msgs.sort(key=lambda m: m[1])  # stable: per time, input order then methods in order
    with BagWriter(bag_out, overwrite=overwrite) as out:
        for topic, conn in types.items():
            out.add_topic(
                topic, conn.msgtype, qos=qos[topic], msgdef=conn.msgdef or None, type_hash=conn.type_hash or None
            )
        for topic, t, raw in out_msgs:
            if not out.has_topic(topic):
                out.add_topic(
                    topic,
                    M.STRING if topic == scen_topic else M.JOINT_STATE,
                    qos=[LATCHED_QOS if topic == scen_topic else STREAM_QOS],
                )
            out.write(topic, t, raw)
    return ReplayResult(bag_out, len(observations), counts, seconds, rejected, skipped)


def set_torch_threads(methods: Sequence[str], threads: int) -> None:
    """torch intra-op threads for per-message neural steps (B = 1): one thread is 10-25x faster
    than torch's default of one per core on these small matrices; 0 keeps torch's default.
    Only touches torch when a neural method is among ``methods``."""
    if threads < 0:
        raise EstimatorError(f"threads must be >= 0 (0 = torch's default), got {threads}")
    if threads and any(m in NEURAL_METHODS for m in methods):
        import torch

        torch.set_num_threads(int(threads))
