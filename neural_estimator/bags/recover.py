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
from neural_estimator.bags.reader import BagDamage, open_bag
from neural_estimator.bags.writer import BagWriter, parse_qos_yaml


@dataclasses.dataclass(frozen=True)
class RecoverResult:
    """What :func:`recover_bag` wrote and what the input had lost."""

    path: Path
    messages: int
    topics: int
    damage: BagDamage | None  # None: the input was intact (the copy is then just a rewrite)


def recover_bag(src: str | Path, out: str | Path, *, overwrite: bool = False) -> RecoverResult:
    """Copy what ``src`` (a ``.mcap`` file or rosbag2 directory) holds into the valid file ``out``.

    Raises:
        BagError: ``src`` unreadable (not MCAP, empty), ``out`` equal to ``src`` or existing
            without ``overwrite``.
    """
    src, out = Path(src), Path(out)
    if out.exists() and src.exists() and out.resolve() == src.resolve():
        raise BagError(f"{out}: recover writes a new file; it cannot overwrite its input")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", BagWarning)  # reported through RecoverResult.damage
        with open_bag(src) as bag, BagWriter(out, overwrite=overwrite) as writer:
            for conn in bag.connections:
                writer.add_topic(
                    conn.topic,
                    conn.msgtype,
                    qos=parse_qos_yaml(conn.offered_qos_profiles),
                    msgdef=conn.msgdef or None,
                    type_hash=(conn.type_hash or "") if conn.msgdef else None,
                )
            n = 0
            for conn, t, raw in bag.messages():
                writer.write(conn.topic, t, raw)
                n += 1
            damage, topics = bag.damage, len(bag.connections)
    return RecoverResult(out, n, topics, damage)
