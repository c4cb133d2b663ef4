"""Rewrite a damaged or unfinished bag into a valid, closed MCAP file (``neural-estimator recover``).

A recorder killed with SIGKILL (or a full disk) leaves an ``.mcap`` without its summary and
footer, perhaps with a half-written last chunk. :class:`~neural_estimator.bags.reader.BagReader`
reads such a file as far as it can; tools that trust the summary (mcap's ``make_reader``,
``mcap_ros2``, rosbags' ``AnyReader``) refuse it. :func:`recover_bag` copies every recovered
message, channel and schema, in log-time order, into a new file written by
:class:`~neural_estimator.bags.writer.BagWriter`: the same role as ``ros2 bag reindex`` for rosbag2.
"""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

from neural_estimator.bags.errors import BagError, BagWarning
from neural_estimator.bags.directory import open_bag
from neural_estimator.bags.reader import BagDamage
from neural_estimator.core.atomic import replaced_atomically, temporary_name
from neural_estimator.bags.writer import BagWriter, QosError, parse_qos_yaml


@dataclasses.dataclass(frozen=True)
class RecoverResult:
    """What :func:`recover_bag` wrote and what the input had lost."""

    path: Path
    messages: int
    topics: int
    damage: BagDamage | None  # None: the input was intact (the copy is then just a rewrite)
    lost: dict[str, int] = dataclasses.field(default_factory=dict)  # stream -> messages lost against the run

    def lost_note(self) -> str:
        """'' or one clause: the messages each stream lost against the run's announcement."""
        if not self.lost:
            return ""
        return "messages lost against the announced run: " + ", ".join(f"{t} {n}" for t, n in self.lost.items())


def recover_bag(src: str | Path, out: str | Path, *, overwrite: bool = False) -> RecoverResult:
    """Copy what ``src`` (a ``.mcap`` file or rosbag2 directory) holds into the valid file ``out``.

    The copy is written beside ``out`` under a temporary name and renamed when complete, so a full
    disk or a read-only directory never leaves a partial or empty ``out``. Messages lost are
    counted, not only chunks: where the bag's ``/scenario`` announces the run (trajectories x
    horizon), each vector stream's messages short of that number are its lost messages (those in
    damaged chunks and those the recorder still buffered when it died).

    Raises:
        BagError: ``src`` unreadable (not MCAP, empty), ``out`` equal to ``src`` or existing
            without ``overwrite``, or ``out`` cannot be written (the error names why).
    """
    src, out = Path(src), Path(out)
    if out.exists() and src.exists() and out.resolve() == src.resolve():
        raise BagError(f"{out}: recover writes a new file; it cannot overwrite its input")
    if out.exists() and not overwrite:
        raise BagError(f"{out}: file exists (pass overwrite=True to replace it)")
    refused: list[str] = []  # topics whose recorded QoS was out of bounds (announced after the copy)
    try:
        with replaced_atomically(out) as tmp, warnings.catch_warnings():
            warnings.simplefilter("ignore", BagWarning)  # reported through RecoverResult.damage
            with open_bag(src) as bag, BagWriter(tmp, overwrite=True) as writer:
                for conn in bag.connections:
                    writer.add_topic(
                        conn.topic,
                        conn.msgtype,
                        qos=_checked_qos(conn.topic, conn.offered_qos_profiles, refused),
                        msgdef=conn.msgdef or None,
                        type_hash=(conn.type_hash or "") if conn.msgdef else None,
                    )
                n = 0
                counts: dict[str, int] = {}
                run = None
                for conn, t, raw in bag.messages():
                    writer.write(conn.topic, t, raw)
                    n += 1
                    run = _count(conn.topic, raw, counts, run)
                damage, topics = bag.damage, len(bag.connections)
    except BagError as exc:  # errors name the file asked for, not the temporary one
        raise BagError(str(exc).replace(str(temporary_name(out)), str(out))) from None
    for line in refused:
        warnings.warn(line, BagWarning, stacklevel=2)
    return RecoverResult(out, n, topics, damage, _lost(counts, run))


def _checked_qos(topic: str, text: str, refused: list[str]) -> list:
    """The topic's recorded profiles, or none (defaults) with a line in ``refused`` saying why."""
    try:
        return parse_qos_yaml(text)
    except QosError as exc:
        refused.append(f"topic {topic}: recorded QoS ignored, defaults used: {exc}")
        return []


def _count(topic: str, raw: bytes, counts: dict[str, int], run: dict | None) -> dict | None:
    """Count a vector stream's message; return the run a /scenario message announces (else ``run``)."""
    from neural_estimator.stream import messages as MSG
    from neural_estimator.bags.errors import MessageError

    leaf = topic.rsplit("/", 1)[-1]
    try:
        if leaf == MSG.SCENARIO:
            desc = MSG.decode_scenario(raw)
            return desc.get("run") if isinstance(desc.get("run"), dict) else run
    except MessageError:
        return run
    if leaf in (MSG.OBSERVATION, MSG.GROUND_TRUTH, MSG.COVARIANCE_SUFFIX) or f"/{MSG.ESTIMATES}/" in topic:
        counts[topic] = counts.get(topic, 0) + 1
    return run


def _lost(counts: dict[str, int], run: dict | None) -> dict[str, int]:
    """Messages per vector stream short of the run's trajectories x horizon (duplicates aside)."""
    try:
        expected = int(run["trajectories"]) * int(run["horizon"])
    except (TypeError, KeyError, ValueError):
        return {}
    return {topic: expected - n for topic, n in sorted(counts.items()) if n < expected}
