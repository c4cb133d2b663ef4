"""A rosbag2 bag directory (``metadata.yaml`` + one or more ``.mcap`` files) read as one bag; and
:func:`open_bag`, the one entry for a file or a directory of either storage (``.db3``, sqlite3:
:mod:`neural_estimator.bags.sqlite`).

``ros2 bag record`` writes a directory, not a file: ``metadata.yaml`` lists the storage files
(``relative_file_paths``) that split recording produced. :class:`BagDirectory` opens each file
with :class:`~neural_estimator.bags.reader.BagReader` (so a damaged or unfinished file is
recovered as far as it can be) and merges them: one :class:`Connection` per topic, messages in
log-time order across files (ties: file order, then order in the file). It offers the reader's
interface, so every verb, the player and the metrics take either a file or a directory; use
:func:`open_bag`, which picks the right one.
"""

from __future__ import annotations

import dataclasses
import heapq
import warnings
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from neural_estimator.bags.errors import BagError, BagWarning
from neural_estimator.bags.reader import PartedBag, BagDamage, BagReader, Connection
from neural_estimator.bags.sqlite import SQLITE_SUFFIX, SqliteBag

METADATA_FILE = "metadata.yaml"


def bag_files(path: str | Path) -> list[Path]:
    """The storage files of a rosbag2 directory (``.mcap``, or ``.db3`` for sqlite3 storage), in
    recording order (``metadata.yaml``'s ``relative_file_paths`` where it lists them, else the
    directory's files of that storage sorted by name)."""
    return bag_storage(path)[1]


def bag_storage(path: str | Path) -> tuple[str, list[Path]]:
    """``("mcap" | "sqlite3", files)`` of a rosbag2 directory (see :func:`bag_files`): the storage
    ``metadata.yaml`` names, else the one whose files the directory holds."""
    root = Path(path)
    meta = root / METADATA_FILE
    listed: list[str] = []
    storage = ""
    if meta.is_file():
        import yaml

        try:
            info = yaml.load(meta.read_text(errors="replace"), Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))
        except (yaml.YAMLError, RecursionError, ValueError) as exc:
            raise BagError(
                f"{meta}: unreadable rosbag2 metadata ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})"
            ) from None
        info = info.get("rosbag2_bagfile_information") if isinstance(info, dict) else None
        if info is not None and not isinstance(info, dict):
            raise BagError(f"{meta}: 'rosbag2_bagfile_information' is not a mapping")
        info = info or {}
        listed = info.get("relative_file_paths") or []
        # a file list names files inside the directory: anything else is refused, never followed
        if not isinstance(listed, list) or not all(isinstance(f, str) and _plain_file_name(f) for f in listed):
            raise BagError(f"{meta}: relative_file_paths must list file names inside the bag directory")
        storage = info.get("storage_identifier") or ""
        if storage not in STORAGES:
            raise BagError(
                f"{root}: storage {str(storage)[:40]!r} is not supported (only {' and '.join(STORAGES)}; convert "
                f"with `rosbags-convert` or `ros2 bag convert`)"
            )
    if not storage:  # no metadata (or no storage named): the files say
        storage = "sqlite3" if not any(root.glob("*.mcap")) and any(root.glob("*.db3")) else "mcap"
    suffix = STORAGES[storage]
    bound = max_bag_files()
    if len(listed) > bound:
        raise BagError(
            f"{meta}: lists {len(listed)} files, over the bound of {bound} files open at once ({_BOUND_WHY})"
        )
    files = [root / f for f in listed] if listed else sorted(root.glob("*" + suffix))
    if len(files) > bound:
        raise BagError(
            f"{root}: holds {len(files)} {suffix} files, over the bound of {bound} files open at once ({_BOUND_WHY})"
        )
    if not files:
        raise BagError(f"{root}: a directory without .mcap or .db3 files (not a rosbag2 bag)")
    missing = [str(f) for f in files if not _is_file(f)]
    if missing:
        raise BagError(f"{root}: {METADATA_FILE} lists missing file(s): {', '.join(missing)}")
    return storage, files


STORAGES = {"mcap": ".mcap", "sqlite3": ".db3"}  # rosbag2 storage identifier -> its files' suffix


MAX_BAG_FILES = 512
_BOUND_WHY = "512, or the open-file limit (ulimit -n) less 64"


def max_bag_files() -> int:
    """The most files of one rosbag2 directory read at once: 512, or fewer where the process's
    open-file limit is lower (less 64 kept for everything else)."""
    try:
        import resource

        soft = resource.getrlimit(resource.RLIMIT_NOFILE)[0]
    except (ImportError, OSError, ValueError):
        return MAX_BAG_FILES
    return MAX_BAG_FILES if soft == resource.RLIM_INFINITY else max(1, min(MAX_BAG_FILES, soft - 64))


def _is_file(path: Path) -> bool:
    try:
        return path.is_file()
    except (OSError, ValueError):  # a name the file system cannot hold (too long, undecodable)
        return False


def _plain_file_name(name: str) -> bool:
    """A relative path of one component, not '.', '..' or hidden behind separators (rosbag2 lists bare names)."""
    return (
        bool(name)
        and len(name.encode("utf-8", "surrogatepass")) <= 255
        and "/" not in name
        and "\\" not in name
        and "\x00" not in name
        and name not in (".", "..")
    )


class BagDirectory(PartedBag):
    """The files of a rosbag2 directory as one bag (see the module docstring)."""

    def __init__(self, path: str | Path, *, strict: bool = False) -> None:
        self.path = Path(path)
        self.strict = strict
        self.parts: list[BagReader] = []
        self.connections: list[Connection] = []
        self.metadata: dict[str, dict[str, str]] = {}
        self.profile = ""
        self.damage: BagDamage | None = None
        self._map: list[dict[int, Connection]] = []  # per part: its channel id -> merged connection

    def open(self) -> "BagDirectory":
        if self.parts:
            return self
        files = bag_files(self.path)
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always", BagWarning)
                for f in files:
                    self.parts.append(BagReader(f, strict=self.strict).open())
        except BaseException:
            self.close()
            raise
        by_topic: dict[str, Connection] = {}
        for part in self.parts:
            mapping = {}
            for c in part.connections:
                merged = by_topic.get(c.topic)
                if merged is None:
                    merged = by_topic[c.topic] = dataclasses.replace(c, id=len(by_topic) + 1, msgcount=0)
                elif merged.msgtype != c.msgtype:
                    self.close()
                    raise BagError(
                        f"{self.path}: topic {c.topic!r} holds {merged.msgtype} in one file and "
                        f"{c.msgtype} in {part.path.name}"
                    )
                merged.msgcount += c.msgcount
                mapping[c.id] = merged
            self._map.append(mapping)
            self.metadata.update(part.metadata)
            self.profile = self.profile or part.profile
        self.connections = list(by_topic.values())
        damaged = [p.damage for p in self.parts if p.damage is not None]
        if damaged:
            self.damage = (
                damaged[0]
                if len(damaged) == 1
                else dataclasses.replace(
                    damaged[0],
                    path=str(self.path),
                    lost_bytes=sum(d.lost_bytes for d in damaged),
                    chunks_lost=sum(d.chunks_lost for d in damaged),
                    messages_recovered=self.message_count,
                    problems=tuple(f"{Path(d.path).name}: {p}" for d in damaged for p in d.problems),
                )
            )
        for w in caught:  # re-announce the files' damage as the directory's
            warnings.warn(str(w.message), BagWarning, stacklevel=2)
        return self

    @property
    def start_time(self) -> int:
        times = [p.start_time for p in self.parts if p.message_count]
        return min(times) if times else 0

    @property
    def end_time(self) -> int:
        return max([p.end_time for p in self.parts if p.message_count] or [0])

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
        """``(connection, log_time_ns, raw)`` of every file, merged in log-time order."""
        if not self.parts:
            raise BagError(f"{self.path}: reader is not open (use it as a context manager)")
        wanted = None if topics is None else list(topics)

        def stream(i: int, part: BagReader):
            for conn, t, raw in part.messages(wanted, start, stop):
                yield t, i, self._map[i][conn.id], raw

        merged = heapq.merge(*(stream(i, p) for i, p in enumerate(self.parts)), key=lambda m: (m[0], m[1]))
        for t, _, conn, raw in merged:
            yield conn, t, raw

    __iter__ = messages

    def decoded(self, topics: Iterable[str] | None = None) -> Iterator[tuple[Connection, int, Any]]:
        for conn, t, raw in self.messages(topics):
            yield conn, t, self.deserialize(raw, conn)

    def deserialize(self, raw: bytes, conn: Connection) -> Any:
        return self.parts[0].deserialize(raw, conn)


def open_bag(path: str | Path, *, strict: bool = False) -> BagReader | BagDirectory | SqliteBag:
    """A reader (not yet opened: use ``with``) for a ``.mcap`` file, a ``.db3`` file or a rosbag2
    directory of either storage (sqlite3 through :mod:`neural_estimator.bags.sqlite`)."""
    p = Path(path)
    if p.is_dir():
        storage, files = bag_storage(p)
        return SqliteBag(p, files) if storage == "sqlite3" else BagDirectory(p, strict=strict)
    if not p.exists():
        raise BagError(f"{p}: no such bag file or directory")
    if p.suffix == SQLITE_SUFFIX:
        return SqliteBag(p, [p])
    return BagReader(p, strict=strict)
