"""Estimation per observation message: the one code path of the live estimator node and of replay.

:class:`OnlineEstimator` turns one observation message (CDR bytes, layout of
:mod:`neural_estimator.bags.messages`) into the estimate message (and covariance message) of that
step. The estimator node calls it from its subscription callback; :func:`replay` calls it for every
observation of a bag at full speed, without DDS. Same bytes in, same calls, same estimates out.

Stream rules (one estimator, B = 1):

- a message of another trajectory, or a step 0 with a stamp other than the current stream's step 0
  (a new run that restarts its trajectory indices at 0), starts a new stream: the estimator is
  reset to its prior;
- a step at or before the last one processed in the current trajectory is out of order or a
  duplicate: it is skipped (the caller logs it), the estimator state is untouched;
- a step later than the next one means observations were lost: the missing steps are run as
  predict-only steps (observation NaN, the last received control held), so that the estimate of
  step k is still an estimate of x_k; at most ``max_gap`` steps are filled, a longer gap restarts
  the stream at this message;
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
from neural_estimator.bags.reader import BagReader
from neural_estimator.bags.writer import STREAM_QOS, BagWriter, parse_qos_yaml
from neural_estimator.estimators import Estimator, EstimatorError, make_estimator

DEFAULT_MAX_GAP = 10_000


@dataclasses.dataclass(frozen=True)
class StepResult:
    """Outcome of one observation message."""

    status: str  # "estimated", "duplicate" or "stale" (out of order)
    trajectory: int
    step: int
    stamp_ns: int
    estimate: bytes | None = None  # estimate message (when estimated)
    covariance: bytes | None = None  # covariance message (when estimated and published)
    x_hat: np.ndarray | None = None  # (dx,)
    reset: bool = False  # this message started a new stream
    filled: int = 0  # missing steps run as predict-only before this one
    restarted: bool = False  # the gap was longer than max_gap: the stream restarted here
    nonfinite: bool = False  # y_k had NaN/inf: predict only
    diverged: bool = False  # the estimator's stream is diverged (estimates NaN until reset)


class OnlineEstimator:
    """One estimator (B = 1) fed with observation messages (see the module docstring).

    Args:
        estimator: any of the ten methods, built for the scenario of the stream.
        method: the method name written in the estimates' frame_id.
        publish_covariance: build covariance messages where the method has a covariance.
        max_gap: the most missing steps filled with predict-only steps.
    """

    def __init__(self, estimator: Estimator, method: str, *, publish_covariance: bool = True,
                 max_gap: int = DEFAULT_MAX_GAP) -> None:
        self.estimator = estimator
        self.scenario = estimator.scenario
        self.method = method
        self.publish_covariance = bool(publish_covariance and estimator.has_covariance)
        self.max_gap = int(max_gap)
        self._obs_labels = M.observation_labels(self.scenario)
        self._obs_codec = M.VectorCodec(self.scenario.name, self._obs_labels)
        self._est_codec = M.VectorCodec(method, M.state_labels(self.scenario))
        self._cov_codec = M.VectorCodec(method, M.covariance_labels(self.scenario.dx))
        self._dy = self.scenario.dy
        self.trajectory: int | None = None
        self.step = -1
        self._u_hold = np.zeros((1, self.scenario.du))
        self._first_stamp: int | None = None  # stamp of step 0 of the current stream

    def reset(self) -> None:
        """Forget the current stream; the next message starts from the prior."""
        self.trajectory = None
        self.step = -1

    def _start(self, trajectory: int) -> None:
        self.estimator.reset(1)
        self.trajectory = trajectory
        self.step = -1
        self._u_hold = np.zeros((1, self.scenario.du))

    def process(self, raw: bytes | memoryview) -> StepResult:
        """Consume one observation message; raises MessageError for a message that cannot be used."""
        vec = self._obs_codec.decode(raw)
        values = M.check_labels(vec, self._obs_labels, "observation")
        y, u_prev = values[None, : self._dy], values[None, self._dy :]
        if not np.all(np.isfinite(u_prev)):
            raise MessageError(f"observation {vec.trajectory}/{vec.step}: control u_prev contains NaN or inf")
        # step 0 again with another stamp: a new run that reuses the trajectory index
        reset = vec.trajectory != self.trajectory or (vec.step == 0 and vec.stamp_ns != self._first_stamp)
        if not reset and vec.step <= self.step:
            status = "duplicate" if vec.step == self.step else "stale"
            return StepResult(status, vec.trajectory, vec.step, vec.stamp_ns)
        if reset:
            self._start(vec.trajectory)
            self._first_stamp = vec.stamp_ns if vec.step == 0 else None
        gap = vec.step - self.step - 1
        restarted = False
        if gap > self.max_gap:
            self._start(vec.trajectory)  # too long to bridge: estimate from the prior from here on
            self.step = vec.step - 1
            gap, restarted = 0, True
        if gap:
            nan_y = np.full((1, self._dy), np.nan)
            for _ in range(gap):
                self.estimator.step(nan_y, self._u_hold)
        try:
            x_hat = self.estimator.step(y, u_prev)[0]
        except EstimatorError as exc:  # the checks above should make this unreachable
            raise MessageError(f"observation {vec.trajectory}/{vec.step}: {exc}") from None
        self.step = vec.step
        self._u_hold = u_prev
        est = self._est_codec.encode(vec.stamp_ns, vec.trajectory, vec.step, x_hat)
        cov = None
        if self.publish_covariance and self.estimator.covariance is not None:
            cov = self._cov_codec.encode(vec.stamp_ns, vec.trajectory, vec.step, self.estimator.covariance[0])
        diverged = bool(self.estimator.diverged[0]) if len(self.estimator.diverged) else False
        return StepResult(
            "estimated", vec.trajectory, vec.step, vec.stamp_ns, est, cov, x_hat,
            reset=reset, filled=gap, restarted=restarted,
            nonfinite=not bool(np.all(np.isfinite(y))), diverged=diverged,
        )


@dataclasses.dataclass
class ReplayResult:
    """What :func:`replay` wrote."""

    path: Path
    observations: int
    estimates: dict[str, int]  # estimate messages per method
    seconds: dict[str, float]  # time spent in OnlineEstimator.process per method
    rejected: dict[str, int]  # observation messages each method could not use

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
) -> ReplayResult:
    """Run a bag's observations through estimators offline and write a bag with their estimates.

    Observations are processed grouped by trajectory, steps in order (sorted by their in-band
    identity, whatever order they were recorded in), each by :meth:`OnlineEstimator.process`: the
    estimator node's code path, so the estimates equal those a live node computes from the same
    messages. The output holds every message of ``bag_in`` (estimate streams of the replayed
    methods replaced) plus ``estimates/<method>`` (and ``/covariance``) with the log time of the
    observation each one answers.

    Args:
        bag_in: a recorded or sample bag with ``scenario`` and ``observation`` streams.
        methods: method names (see :data:`neural_estimator.estimators.METHODS`).
        bag_out: output ``.mcap``.
        checkpoints: {method: checkpoint} for neural methods (default: the shipped models).
        device, seed: passed to :func:`~neural_estimator.estimators.make_estimator`.
        namespace: namespace of the streams.
        options: {method: {option: value}} filter hyperparameters.
        publish_covariance: also write covariance streams where methods have them.
        overwrite: replace an existing ``bag_out``.
    """
    from neural_estimator.scenarios import scenario_from_description

    bag_in, bag_out = Path(bag_in), Path(bag_out)
    if bag_in.resolve() == bag_out.resolve():
        raise BagError(f"{bag_out}: replay cannot overwrite its input bag")
    obs_topic = M.resolve_topic(M.OBSERVATION, namespace)
    scen_topic = M.resolve_topic(M.SCENARIO, namespace)
    replaced = {M.resolve_topic(M.estimate_topic(m), namespace) for m in methods}
    replaced |= {M.resolve_topic(M.covariance_topic(m), namespace) for m in methods}
    with BagReader(bag_in) as bag:
        bag.connection(obs_topic, M.JOINT_STATE)
        bag.connection(scen_topic, M.STRING)
        desc = None
        for _, _, raw in bag.messages([scen_topic]):
            desc = M.decode_scenario(raw)
        kept_topics = [c for c in bag.connections if c.topic not in replaced]
        passthrough = [(conn.topic, t, raw) for conn, t, raw in bag.messages([c.topic for c in kept_topics])]
    if desc is None:
        raise BagError(f"{bag_in}: no message on {scen_topic}")
    scenario = scenario_from_description(desc)

    # The observations in stream order, by their in-band identity; unparsable ones keep bag order.
    observations = []
    for i, (topic, t, raw) in enumerate(passthrough):
        if topic != obs_topic:
            continue
        try:
            vec = M.decode_vector(raw)
            key = (vec.trajectory, vec.step, i)
        except MessageError:
            key = (-1, -1, i)
        observations.append((key, t, raw))
    observations.sort(key=lambda o: o[0])

    out_msgs: list[tuple[str, int, bytes]] = list(passthrough)
    counts, seconds, rejected = {}, {}, {}
    for method in methods:
        ckpt = (checkpoints or {}).get(method)
        est = make_estimator(method, scenario, checkpoint=ckpt, device=device, seed=seed, **dict((options or {}).get(method, {})))
        online = OnlineEstimator(est, method, publish_covariance=publish_covariance)
        est_topic = M.resolve_topic(M.estimate_topic(method), namespace)
        cov_topic = M.resolve_topic(M.covariance_topic(method), namespace)
        counts[method], rejected[method], spent = 0, 0, 0.0
        for _, t, raw in observations:
            t0 = time.perf_counter()
            try:
                res = online.process(raw)
            except MessageError:
                rejected[method] += 1
                continue
            finally:
                spent += time.perf_counter() - t0
            if res.estimate is not None:
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
            out.add_topic(topic, conn.msgtype, qos=qos[topic], msgdef=conn.msgdef or None,
                          type_hash=conn.type_hash or None)
        for topic, t, raw in out_msgs:
            if not out.has_topic(topic):
                out.add_topic(topic, M.JOINT_STATE, qos=[STREAM_QOS])
            out.write(topic, t, raw)
    return ReplayResult(bag_out, len(observations), counts, seconds, rejected)
