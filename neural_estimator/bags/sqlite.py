"""rosbag2's sqlite3 storage (``.db3``), read through rosbags, behind the MCAP reader's interface.

Many teams' archives were recorded before rosbag2 switched its default to MCAP: a directory whose
``metadata.yaml`` says ``storage_identifier: sqlite3`` (one or more ``.db3`` files), or a lone
``.db3`` file. :class:`SqliteBag` opens each file with rosbags' sqlite3 storage reader (read-only,
immutable) and offers what :class:`~neural_estimator.bags.reader.BagReader` offers: one
:class:`~neural_estimator.bags.reader.Connection` per topic, ``messages`` merged across files in
log-time order, ``decoded`` with the same type store (types outside Jazzy registered from the
schemas the bag stores). Every verb, the player and the metrics reach it through
:func:`~neural_estimator.bags.directory.open_bag`. A database that cannot be read, or a file
that is not one, is a one-line BagError naming the file; the same bound on files open at once
as for MCAP directories applies.
"""

from __future__ import annotations

import dataclasses
import heapq
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from neural_estimator.bags.errors import BagError
from neural_estimator.stream.messages import TYPESTORE
from neural_estimator.bags.reader import PartedBag, Connection, register_schema

SQLITE_SUFFIX = ".db3"


class SqliteBag(PartedBag):
    """One ``.db3`` file, or the ``.db3`` files of a rosbag2 directory in recording order, as one bag."""

    def __init__(self, path: str | Path, files: list[Path]) -> None:
        self.path = Path(path)
        self.files = files
        self.parts: list[Any] = []  # rosbags Sqlite3Reader per file
        self.connections: list[Connection] = []
        self.metadata: dict[str, dict[str, str]] = {}
        self.profile = ""
        self.damage = None  # sqlite has no partial recovery: a database reads whole or not at all
        self._map: list[dict[int, Connection]] = []  # per part: its connection id -> merged connection
        self._registered: set[str] = set()

    def open(self) -> "SqliteBag":
        if self.parts:
            return self
        from rosbags.rosbag2.errors import ReaderError
        from rosbags.rosbag2.storage_sqlite3 import Sqlite3Reader

        by_topic: dict[str, Connection] = {}
        try:
            for f in self.files:
                part = Sqlite3Reader(f)
                try:
                    part.open()
                except (ReaderError, OSError) as exc:
                    raise BagError(f"{f}: not a readable rosbag2 sqlite3 database ({_first_line(exc)})") from None
                self.parts.append(part)
                mapping = {}
                for c in part.connections:
                    merged = by_topic.get(c.topic)
                    if merged is None:
                        merged = by_topic[c.topic] = _connection(c, len(by_topic) + 1)
                    elif merged.msgtype != c.msgtype:
                        raise BagError(
                            f"{self.path}: topic {c.topic!r} holds {merged.msgtype} in one file and "
                            f"{c.msgtype} in {f.name}"
                        )
                    merged.msgcount += int(c.msgcount)
                    mapping[c.id] = merged
                self._map.append(mapping)
        except BaseException:
            self.close()
            raise
        self.connections = list(by_topic.values())
        return self

    @property
    def start_time(self) -> int:
        times = [p.metadata.start_time for p in self.parts if p.metadata.message_count]
        return min(times) if times else 0

    @property
    def end_time(self) -> int:
        return max([p.metadata.end_time for p in self.parts if p.metadata.message_count] or [0])

    def connection(self, topic: str, msgtype: str | None = None) -> Connection:
        conn = self.topics.get(topic)
        if conn is None:
            raise BagError(f"{self.path}: no topic {topic!r} (topics: {', '.join(sorted(self.topics)) or 'none'})")
        if msgtype is not None and conn.msgtype != msgtype:
            raise BagError(f"{self.path}: topic {topic!r} holds {conn.msgtype}, expected {msgtype}")
        return conn

    def messages(
        self, topics: Iterable[str] | None = None, start: int | None = None, stop: int | None = None
    ) -> Iterator[tuple[Connection, int, bytes]]:
        """``(connection, log_time_ns, raw)`` of every file, merged in log-time order (ties: file order)."""
        if not self.parts:
            raise BagError(f"{self.path}: reader is not open (use it as a context manager)")
        wanted = None if topics is None else set(topics)

        def stream(i: int, part):
            conns = [c for c in part.connections if wanted is None or c.topic in wanted]
            if not conns:  # rosbags reads an empty selection as "every topic"
                return
            for c, t, raw in part.messages(conns, start, stop):
                yield int(t), i, self._map[i][c.id], bytes(raw)

        merged = heapq.merge(*(stream(i, p) for i, p in enumerate(self.parts)), key=lambda m: (m[0], m[1]))
        for t, _, conn, raw in merged:
            yield conn, t, raw

    __iter__ = messages

    def decoded(self, topics: Iterable[str] | None = None) -> Iterator[tuple[Connection, int, Any]]:
        for conn, t, raw in self.messages(topics):
            yield conn, t, self.deserialize(raw, conn)

    def deserialize(self, raw: bytes, conn: Connection) -> Any:
        if conn.msgtype not in TYPESTORE.fielddefs and conn.msgtype not in self._registered:
            if not conn.msgdef:
                raise BagError(
                    f"{self.path}: {conn.topic} holds {conn.msgtype}, a type outside ROS 2 Jazzy's and the bag "
                    "stores no definition of it (a database older than rosbag2 schema 4)"
                )
            register_schema(conn, self.path)
            self._registered.add(conn.msgtype)
        try:
            return TYPESTORE.deserialize_cdr(raw, conn.msgtype)
        except Exception as exc:
            raise BagError(f"{self.path}: cannot decode a {conn.msgtype} message on {conn.topic}: {exc}") from None


def _connection(c: Any, cid: int) -> Connection:
    """This package's Connection for a rosbags connection (the definition where the database has one)."""
    msgdef = getattr(c, "msgdef", None)
    text = getattr(msgdef, "data", "") if getattr(getattr(msgdef, "format", None), "name", "") == "MSG" else ""
    ext = getattr(c, "ext", None)
    return dataclasses.replace(
        Connection(
            id=cid,
            topic=c.topic,
            msgtype=c.msgtype,
            msgdef=text or "",
            message_encoding=str(getattr(ext, "serialization_format", "cdr") or "cdr"),
            offered_qos_profiles=_qos_text(getattr(ext, "offered_qos_profiles", "")),
            type_hash=str(getattr(c, "digest", "") or ""),
        ),
        msgcount=0,
    )


def _qos_text(qos: Any) -> str:
    return qos if isinstance(qos, str) else ""


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__
