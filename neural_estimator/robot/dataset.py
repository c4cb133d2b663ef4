"""Recorded bags -> the project's dataset format, through a :mod:`~neural_estimator.robot.spec`.

For each bag (a ``.mcap`` file or a rosbag2 directory, written by any tool: messages are decoded
with rosbags' type store, custom types registered from the bag's own schemas):

1. every topic the spec reads is collected as (stamp, field values) per message, the stamp being
   ``header.stamp`` where the message has a header (``stamp: header``, the default) or the log
   time;
2. ticks: a fixed rate from the latest first message to the earliest last message over the
   topics, or one tick per message of the ``trigger`` topic;
3. at each tick every topic contributes its latest message with a stamp at or before the tick;
   the tick is *stale* when some input topic (observation, control, estimates) has none, or only
   one older than ``max_age``, and *non-finite* when an input value is NaN or inf (e.g. a zero
   quaternion); both are dropped and counted;
4. the ground truth (the state) is sampled the same way, but a tick where it is stale or
   non-finite (a robot outside the motion-capture volume) is kept *unlabelled*: the inputs run
   on through the gap, so a model's state carries across it, and the dataset's ``labelled``
   mask (N, T) says which steps hold ground truth (x holds the last labelled state of the
   trajectory at the others, a placeholder that training and scoring never read);
5. the valid ticks form segments (runs between dropped ticks); each segment is cut into
   trajectories of ``length`` steps, the remainder dropped and counted, and a trajectory with no
   labelled step dropped and counted; except where the spec reads no state (a ``model:`` and no
   ``state:``: a recording without ground truth), whose trajectories are all kept, no step
   labelled, x holding the model's prior mean m0 (a placeholder never read).

The truth is not an input because cutting at its gaps would drop them and the pieces shorter than
a trajectory, and live the estimator never sees it. The ticks still span the time every topic, the
truth included, has messages: a recording's head or tail without truth is not used.

The result is a :class:`~neural_estimator.data.simulate.Trajectories` whose meta records the spec,
its digest, the names, units and angles of the three vectors, the rate, every source bag's SHA-256
and what was dropped.
"""

from __future__ import annotations

import dataclasses
import hashlib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from neural_estimator.bags import BagError, open_bag
from neural_estimator.data.simulate import Trajectories
from neural_estimator.robot.data_scenario import DATA_SCENARIO
from neural_estimator.robot.spec import MAX_TICKS, ESTIMATE_PREFIX, Field, Spec, SpecError, topic_values


@dataclasses.dataclass
class BagSummary:
    """What one bag contributed and what was dropped from it."""

    bag: str
    sha256: str
    messages: dict[str, int]
    ticks: int = 0
    stale: int = 0
    nonfinite: int = 0
    segments: int = 0
    trajectories: int = 0
    remainder: int = 0  # valid ticks at the end of segments, fewer than a trajectory's length
    labelled: int = 0  # steps of the kept trajectories with ground truth
    unlabelled: int = 0  # steps of the kept trajectories without
    unlabelled_trajectories: int = 0  # trajectories dropped for having no labelled step

    def line(self) -> str:
        partial = (
            f"; {self.unlabelled} of {self.labelled + self.unlabelled} steps unlabelled (no ground truth)"
            if self.unlabelled or self.unlabelled_trajectories
            else ""
        )
        unlab = f", {self.unlabelled_trajectories} unlabelled trajectories" if self.unlabelled_trajectories else ""
        return (
            f"{self.bag}: {self.ticks} ticks -> {self.trajectories} trajectories from {self.segments} segments; "
            f"dropped {self.stale} stale, {self.nonfinite} non-finite, {self.remainder} remainder ticks{unlab}"
            f"{partial}"
        )


def bag_sha256(path: str | Path) -> str:
    """SHA-256 of a bag file, or of a rosbag2 directory's files (names and bytes, sorted)."""
    p = Path(path)
    h = hashlib.sha256()
    files = sorted(q for q in p.rglob("*") if q.is_file()) if p.is_dir() else [p]
    for q in files:
        if p.is_dir():
            h.update(str(q.relative_to(p)).encode() + b"\0")
        with q.open("rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()


def topic_fields(spec: Spec) -> dict[str, tuple[Field, ...]]:
    """Per topic, every field any vector reads from it (each once, in order)."""
    out: dict[str, list[Field]] = {}
    for name in spec.vectors:
        for f in spec.vectors[name]:
            if f not in out.setdefault(f.topic, []):
                out[f.topic].append(f)
    return {t: tuple(fs) for t, fs in out.items()}


def message_stamp(msg, t_log: int, spec: Spec) -> int:
    """A message's time [ns]: its ``header.stamp`` where it has one and the spec says ``stamp: header``,
    else ``t_log`` (its log time; live, its receipt time)."""
    header = getattr(msg, "header", None)
    if spec.stamp == "header" and header is not None and hasattr(header, "stamp"):
        return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)
    return int(t_log)


def read_streams(bag_path: str | Path, spec: Spec) -> tuple[dict[str, tuple[np.ndarray, np.ndarray]], dict[str, int]]:
    """Per topic of the spec (and its trigger): (stamps_ns (M,) sorted, values (M, k)); message counts.

    Raises SpecError for a topic the bag does not have (naming the bag's topics) or a field a
    message does not have; BagError for a bag that cannot be read.
    """
    fields = topic_fields(spec)
    wanted = list(fields) + ([spec.trigger] if spec.trigger and spec.trigger not in fields else [])
    rows: dict[str, list[tuple[int, np.ndarray]]] = {t: [] for t in wanted}
    with open_bag(bag_path) as bag:
        missing = [t for t in wanted if t not in bag.topics]
        if missing:
            have = ", ".join(sorted(bag.topics)) or "none"
            raise SpecError(f"{bag_path}: no topic {', '.join(missing)} in this bag (it has: {have})")
        for conn, t_log, msg in bag.decoded(wanted):
            stamp = message_stamp(msg, t_log, spec)
            values = topic_values(msg, fields.get(conn.topic, ()), conn.msgtype)
            rows[conn.topic].append((stamp, values))
    streams, counts = {}, {}
    for topic, got in rows.items():
        counts[topic] = len(got)
        if not got:
            raise SpecError(f"{bag_path}: topic {topic} has no messages")
        stamps = np.array([s for s, _ in got], dtype=np.int64)
        values = np.stack([v for _, v in got]) if fields.get(topic) else np.zeros((len(got), 0))
        order = np.argsort(stamps, kind="stable")
        streams[topic] = (stamps[order], values[order])
    return streams, counts


def tick_times(streams: dict[str, tuple[np.ndarray, np.ndarray]], spec: Spec) -> np.ndarray:
    """The sample times [ns]: the trigger topic's stamps, or the multiples of the period (``dt``
    rounded to a nanosecond) over the common span. Multiples of the period, not offsets from the
    first message: the robot estimator node ticks on the same grid live
    (:mod:`~neural_estimator.robot.ticker`), whenever it starts."""
    if spec.trigger:
        return streams[spec.trigger][0]
    step = int(round(spec.dt * 1e9))
    start = max(int(s[0]) for s, _ in streams.values())
    start = -(-start // step) * step  # the first multiple of the period in the span
    stop = min(int(s[-1]) for s, _ in streams.values())
    if stop < start:
        return np.zeros(0, dtype=np.int64)
    n = (stop - start) // step + 1
    if n > MAX_TICKS:
        raise SpecError(
            f"{(stop - start) / 1e9:.1f} s at {spec.rate:g} Hz is {n} samples, "
            f"over the bound of {MAX_TICKS} (MAX_TICKS)"
        )
    return start + np.arange(n, dtype=np.int64) * step


def sample(
    streams: dict[str, tuple[np.ndarray, np.ndarray]], spec: Spec, ticks: np.ndarray
) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray, np.ndarray]:
    """The vectors at every tick; the stale and non-finite masks (K,) of the inputs (every vector
    but the state); and the labelled mask (K,): the state fresh and finite.

    Each topic contributes its latest message stamped at or before the tick, if no older than
    ``max_age``.
    """
    fields = topic_fields(spec)
    K = ticks.size
    fresh: dict[str, np.ndarray] = {}
    at: dict[str, np.ndarray] = {}
    max_age = int(round(spec.max_age * 1e9))
    for topic in fields:
        stamps, values = streams[topic]
        idx = np.searchsorted(stamps, ticks, side="right") - 1
        ok = idx >= 0
        ok[ok] &= (ticks[ok] - stamps[idx[ok]]) <= max_age
        fresh[topic] = ok
        at[topic] = values[np.clip(idx, 0, None)]
    vectors, usable = {}, {}
    for name in spec.vectors:
        cols = [at[f.topic][:, fields[f.topic].index(f)] for f in spec.vectors[name]]
        vectors[name] = np.stack(cols, axis=1) if cols else np.zeros((K, 0))
        topics = {f.topic for f in spec.vectors[name]}
        is_fresh = np.all([fresh[t] for t in topics], axis=0) if topics else np.ones(K, bool)
        usable[name] = (is_fresh, np.isfinite(vectors[name]).all(axis=1))
    inputs = [name for name in spec.vectors if name != "state"]
    stale = ~np.all([usable[n][0] for n in inputs], axis=0) if inputs else np.zeros(K, bool)
    finite = np.all([usable[n][1] for n in inputs], axis=0) if inputs else np.ones(K, bool)
    nonfinite = ~stale & ~finite
    # no state read (a spec with a model and no ground truth): no step is labelled
    labelled = usable["state"][0] & usable["state"][1] if spec.has_state else np.zeros(K, bool)
    return vectors, stale, nonfinite, labelled


def fill_unlabelled(x: np.ndarray, labelled: np.ndarray) -> np.ndarray:
    """x (T, dx) with every unlabelled step holding the last labelled state before it (the first
    labelled one before the first label): a finite placeholder, never read by training or scoring."""
    if labelled.all():
        return x
    idx = np.where(labelled, np.arange(labelled.size), -1)
    idx = np.maximum.accumulate(idx)
    idx[idx < 0] = int(np.argmax(labelled))
    return x[idx]


def segments(valid: np.ndarray) -> list[tuple[int, int]]:
    """[start, stop) index ranges of the runs of True in ``valid``."""
    edges = np.diff(np.concatenate([[0], valid.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist()))


def build_dataset(
    bags: Sequence[str | Path], spec: Spec, length: int, progress=None, length_name: str = "--length"
) -> tuple[Trajectories, dict[str, np.ndarray], list[BagSummary]]:
    """Trajectories of ``length`` steps from every bag (see the module docstring), and the spec's
    recorded estimates {name: x_hat (N, T, dx)} at the same ticks. ``length_name`` names the
    setting in the error (``--length`` on the command line, ``spec_length`` on the evaluator node).

    Raises:
        SpecError: a topic or field the spec names is missing, or no trajectory of ``length`` steps
            could be cut (the message says how long the longest segment was).
    """
    if int(length) < 2:
        raise SpecError(f"trajectory length must be at least 2 steps, got {length}")
    length = int(length)
    xs, ys, us, labels, summaries, longest = [], [], [], [], [], 0
    est: dict[str, list[np.ndarray]] = {name: [] for name in spec.estimates}
    for bag in bags:
        try:
            streams, counts = read_streams(bag, spec)
        except BagError as exc:
            raise SpecError(str(exc)) from None
        summary = BagSummary(str(bag), bag_sha256(bag), counts)
        ticks = tick_times(streams, spec)
        vectors, stale, nonfinite, labelled = sample(streams, spec, ticks)
        summary.ticks, summary.stale, summary.nonfinite = ticks.size, int(stale.sum()), int(nonfinite.sum())
        segs = segments(~stale & ~nonfinite)
        summary.segments = len(segs)
        for lo, hi in segs:
            longest = max(longest, hi - lo)
            n = (hi - lo) // length
            summary.remainder += (hi - lo) - n * length
            for k in range(n):
                sl = slice(lo + k * length, lo + (k + 1) * length)
                if spec.has_state and not labelled[sl].any():  # no ground truth at all: nothing to train on or score
                    summary.unlabelled_trajectories += 1
                    continue
                summary.trajectories += 1
                summary.labelled += int(labelled[sl].sum())
                summary.unlabelled += int((~labelled[sl]).sum())
                labels.append(labelled[sl])
                xs.append(
                    fill_unlabelled(vectors["state"][sl], labelled[sl])
                    if spec.has_state
                    else np.tile(spec.model.prior()[0], (length, 1))
                )
                ys.append(vectors["observation"][sl])
                us.append(vectors["control"][sl])
                for name in est:
                    est[name].append(vectors[ESTIMATE_PREFIX + name][sl])
        summaries.append(summary)
        if progress:
            progress(summary.line())
    if not xs:
        unlab = sum(s.unlabelled_trajectories for s in summaries)
        raise SpecError(
            f"no trajectory of {length} steps: the longest run of valid ticks is {longest} "
            f"(at {spec.rate:g} Hz); pass a smaller {length_name}, or raise max_age in the spec"
            if not unlab
            else f"no trajectory of {length} steps with ground truth: all {unlab} have no labelled step "
            f"(the state's topics are silent or non-finite there)"
        )
    meta = dataset_meta(spec, length, summaries)
    estimates = {name: np.stack(v) for name, v in est.items()}
    mask = np.stack(labels)
    data = Trajectories(np.stack(xs), np.stack(ys), np.stack(us), meta, None if mask.all() else mask)
    return data, estimates, summaries


def dataset_meta(spec: Spec, length: int, summaries: Sequence[BagSummary]) -> dict[str, Any]:
    """The dataset's meta: everything a data scenario and a checkpoint card need, and the sources."""
    return {
        "scenario": DATA_SCENARIO,
        "spec": spec.source,
        "spec_sha256": spec.digest(),
        "rate": spec.rate,
        "dt": spec.dt,
        "horizon": int(length),
        "state_names": list(spec.names["state"]),
        "state_units": list(spec.units["state"]),
        "obs_names": list(spec.names["observation"]),
        "obs_units": list(spec.units["observation"]),
        "control_names": list(spec.names["control"]),
        "control_units": list(spec.units["control"]),
        "angle_states": list(spec.angles("state")),
        "angle_obs": list(spec.angles("observation")),
        "sources": [
            {"bag": Path(s.bag).name, "sha256": s.sha256, "messages": s.messages, "trajectories": s.trajectories}
            for s in summaries
        ],
        "dropped": {
            "stale_ticks": sum(s.stale for s in summaries),
            "nonfinite_ticks": sum(s.nonfinite for s in summaries),
            "remainder_ticks": sum(s.remainder for s in summaries),
            "unlabelled_trajectories": sum(s.unlabelled_trajectories for s in summaries),
        },
        # steps with ground truth (the "labelled" array, saved when some step has none)
        "labelled_steps": sum(s.labelled for s in summaries),
        "unlabelled_steps": sum(s.unlabelled for s in summaries),
        # a spec's model (the scenario DataScenario delegates the equations to); no state read: no label
        **({"model": spec.source["model"]} if spec.model is not None else {}),
        **({} if spec.has_state else {"ground_truth": False}),
    }
