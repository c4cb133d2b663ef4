"""Write one MCAP file in the layout rosbag2 (Jazzy) writes, without rclpy.

What makes the file a rosbag2 bag that ``ros2 bag info/play``, Foxglove, PlotJuggler and rosbags
read (MCAP ``ros2`` profile):

- header profile ``ros2``; one schema per message type, encoding ``ros2msg``, holding the full
  ``.msg`` text with its dependencies (``====`` separated, as rosbag2 stores it);
- one channel per topic, message encoding ``cdr``, channel metadata ``offered_qos_profiles``
  (rosbag2's YAML, metadata version 9 with string policies) and ``topic_type_hash`` (RIHS01);
- zstd-compressed chunks with message indexes, then the summary (schemas, channels, statistics,
  chunk indexes) and a ``rosbag2`` metadata record with ``serialized_metadata`` (the bag metadata
  as rosbag2 writes it: without it rosbag2 would read the QoS strings as version 8 integers).

A file is only complete after :meth:`BagWriter.close` (the context manager calls it, also when the
body raises); until then the data of finished chunks are on disk and
:class:`~neural_estimator.bags.reader.BagReader` recovers them.
"""

from __future__ import annotations

import dataclasses
import os
import tempfile
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import yaml
from mcap.data_stream import RecordBuilder
from mcap.writer import CompressionType, Writer

from neural_estimator import __version__
from neural_estimator.core.safe_yaml import YamlError, load_yaml
from neural_estimator.bags.errors import BagError, BagWarning
from neural_estimator.stream.messages import TYPESTORE

_INFINITE_SEC, _INFINITE_NSEC = 9223372036, 854775807  # RMW_DURATION_INFINITE as rosbag2 prints it
DEFAULT_CHUNK_SIZE = 256 * 1024  # bytes of uncompressed records per chunk (the unit recovered after a crash)


class _ChunkIndexSpill:
    """The MCAP writer's chunk indexes, each serialised as it is made into an unlinked temporary
    file beside the bag, and read back into the summary at close (the file's bytes are unchanged).

    mcap's ``Writer`` keeps one ``ChunkIndex`` object per chunk until it writes the summary: about
    1 KB each with 8 channels, so a recording's memory grew with its length (the evaluator at
    500 Hz with three estimators: 5 chunks a second, 0.005 MiB/s, about 430 MB a day). Spilled, a
    chunk costs about 170 bytes of disk and no memory. It stands in for the writer's list, which
    the writer only appends to and iterates once in ``finish``.
    """

    def __init__(self, directory: Path) -> None:
        self._file = tempfile.TemporaryFile(dir=directory, prefix=".chunk-indexes-")
        self.count = 0

    def append(self, index: Any) -> None:
        record = RecordBuilder()
        index.write(record)
        self._file.write(record.end())
        self.count += 1

    def __len__(self) -> int:
        return self.count

    def __iter__(self):
        """The serialised records in 1 MiB pieces, each an object whose ``write`` adds it to the summary."""
        self._file.flush()
        self._file.seek(0)
        while block := self._file.read(1 << 20):
            yield _Records(block)

    def close(self) -> None:
        self._file.close()


class _Records:
    __slots__ = ("data",)

    def __init__(self, data: bytes) -> None:
        self.data = data

    def write(self, stream: RecordBuilder) -> None:
        stream.write(self.data)


def _spill_chunk_indexes(writer: Writer, directory: Path) -> _ChunkIndexSpill | None:
    """Put a :class:`_ChunkIndexSpill` in place of ``writer``'s chunk-index list; None (the list
    kept) where this mcap version has no such list."""
    if getattr(writer, "_Writer__chunk_indices", None) != []:
        return None
    spill = _ChunkIndexSpill(directory)
    writer._Writer__chunk_indices = spill
    return spill


@dataclasses.dataclass(frozen=True)
class Qos:
    """An offered QoS profile as rosbag2 records it (policy names lower-case, as in Jazzy).

    Durations are (sec, nsec); None is infinite (rmw's default).
    """

    reliability: str = "reliable"  # reliable | best_effort
    durability: str = "volatile"  # volatile | transient_local
    history: str = "keep_last"  # keep_last | keep_all
    depth: int = 10
    deadline: tuple[int, int] | None = None
    lifespan: tuple[int, int] | None = None
    liveliness: str = "automatic"  # automatic | manual_by_topic
    liveliness_lease_duration: tuple[int, int] | None = None
    avoid_ros_namespace_conventions: bool = False

    def to_dict(self) -> dict[str, Any]:
        """The mapping rosbag2 writes for one profile (metadata version 9)."""

        def dur(d: tuple[int, int] | None) -> dict[str, int]:
            sec, nsec = d if d is not None else (_INFINITE_SEC, _INFINITE_NSEC)
            return {"sec": int(sec), "nsec": int(nsec)}

        return {
            "history": self.history,
            "depth": int(self.depth),
            "reliability": self.reliability,
            "durability": self.durability,
            "deadline": dur(self.deadline),
            "lifespan": dur(self.lifespan),
            "liveliness": self.liveliness,
            "liveliness_lease_duration": dur(self.liveliness_lease_duration),
            "avoid_ros_namespace_conventions": bool(self.avoid_ros_namespace_conventions),
        }


# QoS of the streams of this package (see neural_estimator.stream.messages and the nodes).
STREAM_QOS = Qos(reliability="reliable", durability="transient_local", depth=1000)
LATCHED_QOS = Qos(reliability="reliable", durability="transient_local", depth=1)


def qos_yaml(profiles: Sequence[Qos]) -> str:
    """The ``offered_qos_profiles`` channel metadata string."""
    if not profiles:
        return ""
    return yaml.safe_dump([p.to_dict() for p in profiles], default_flow_style=False, sort_keys=False).strip()


QOS_TEXT_MAX = 64 * 1024  # bytes of one topic's offered_qos_profiles (rosbag2 writes ~400 per publisher)
QOS_PROFILES_MAX = 64  # publisher profiles per topic
QOS_DEPTH_MAX = 100_000  # ten times the deepest history this package offers (history_depth 10,000)
_POLICIES = {
    "history": ("keep_last", "keep_all", {1: "keep_last", 2: "keep_all"}),
    "reliability": ("reliable", "best_effort", {1: "reliable", 2: "best_effort"}),
    "durability": ("volatile", "transient_local", {1: "transient_local", 2: "volatile"}),
    "liveliness": ("automatic", "manual_by_topic", {1: "automatic", 3: "manual_by_topic"}),
}
_DEFAULTS = {"history": "keep_last", "reliability": "reliable", "durability": "volatile", "liveliness": "automatic"}
_MAX_SEC = _INFINITE_SEC
_MAX_NSEC = 2**32 - 1
# rmw's "infinite" (or default) duration as rosbag2 has recorded it: Jazzy's RMW_DURATION_INFINITE,
# Humble's and Iron's {2147483647, 4294967295}, and 0 (the default: infinite for these policies)
_INFINITE_DURATIONS = {(_INFINITE_SEC, _INFINITE_NSEC), (2**31 - 1, 2**32 - 1), (0, 0)}


class QosError(ValueError):
    """Recorded QoS metadata this package refuses to use; the message says which field and why."""


def parse_qos_yaml(text: str) -> list[Qos]:
    """Qos profiles back from rosbag2's ``offered_qos_profiles`` YAML (v9 names; v8 integers too).

    Every field is validated: the text at most :data:`QOS_TEXT_MAX` bytes (libyaml's C loader,
    nesting bounded), at most :data:`QOS_PROFILES_MAX` profiles, policies of their known names (or
    rosbag2 v8's integers), depth an integer in [0, :data:`QOS_DEPTH_MAX`], durations integers with
    0 <= nsec < 1e9. Empty text is no profile.

    Raises:
        QosError: the first field out of bounds, in one line.
    """
    if not text:
        return []
    try:
        items = load_yaml(text, "offered_qos_profiles", QOS_TEXT_MAX)
    except YamlError as exc:
        raise QosError(str(exc)) from None
    if items is None:
        return []
    if not isinstance(items, list):
        raise QosError(f"offered_qos_profiles is a {type(items).__name__}, not a list of profiles")
    if len(items) > QOS_PROFILES_MAX:
        raise QosError(f"offered_qos_profiles lists {len(items)} profiles, over the bound of {QOS_PROFILES_MAX}")
    return [_profile(i, item) for i, item in enumerate(items)]


def _profile(i: int, item: object) -> Qos:
    """One validated profile (see :func:`parse_qos_yaml`)."""
    where = f"offered_qos_profiles[{i}]"
    if not isinstance(item, dict):
        raise QosError(f"{where} is a {type(item).__name__}, not a mapping")

    def pol(key: str) -> str:
        v = item.get(key, _DEFAULTS[key])
        *names, v8 = _POLICIES[key]
        if isinstance(v, int) and not isinstance(v, bool) and v in v8:
            return v8[v]
        if isinstance(v, str) and v in names:
            return v
        if v in ("system_default", 0):  # rmw's "use the default"
            return _DEFAULTS[key]
        raise QosError(f"{where}.{key} = {_short(v)}: not one of {', '.join(names)}")

    def whole(v: object, key: str, hi: int) -> int:
        if not isinstance(v, int) or isinstance(v, bool) or not 0 <= v <= hi:
            raise QosError(f"{where}.{key} = {_short(v)}: not an integer in [0, {hi}]")
        return v

    def dur(key: str) -> tuple[int, int] | None:
        d = item.get(key)
        if d is None:
            return None
        if not isinstance(d, dict):
            raise QosError(f"{where}.{key} = {_short(d)}: not a mapping of sec and nsec")
        sec = whole(d.get("sec", 0), f"{key}.sec", _MAX_SEC)
        nsec = whole(d.get("nsec", 0), f"{key}.nsec", _MAX_NSEC)
        if (sec, nsec) in _INFINITE_DURATIONS:
            return None
        if nsec >= 1_000_000_000:
            raise QosError(f"{where}.{key}.nsec = {nsec}: not below 1e9")
        return (sec, nsec)

    avoid = item.get("avoid_ros_namespace_conventions", False)
    if not isinstance(avoid, bool):
        raise QosError(f"{where}.avoid_ros_namespace_conventions = {_short(avoid)}: not true or false")
    return Qos(
        reliability=pol("reliability"),
        durability=pol("durability"),
        history=pol("history"),
        depth=whole(item.get("depth", 10), "depth", QOS_DEPTH_MAX),
        deadline=dur("deadline"),
        lifespan=dur("lifespan"),
        liveliness=pol("liveliness"),
        liveliness_lease_duration=dur("liveliness_lease_duration"),
        avoid_ros_namespace_conventions=avoid,
    )


def topic_qos(topic: str, text: str) -> list[Qos]:
    """A topic's recorded profiles for a copy or a player; refused metadata is one :class:`BagWarning`
    line (the topic and the field) and the topic gets no recorded profile, so the caller's default
    applies and nothing out of bounds is copied or offered."""
    try:
        return parse_qos_yaml(text)
    except QosError as exc:
        warnings.warn(f"topic {topic}: recorded QoS ignored, defaults used: {exc}", BagWarning, stacklevel=2)
        return []


def _short(v: object) -> str:
    text = repr(v)
    return text if len(text) <= 40 else text[:37] + "..."


@dataclasses.dataclass
class _Topic:
    name: str
    msgtype: str
    channel_id: int
    qos: tuple[Qos, ...]
    type_hash: str
    count: int = 0


class BagWriter:
    """Write messages (raw CDR bytes or rosbags objects) into one ``.mcap`` file.

    >>> with BagWriter(tmp / "run.mcap") as bag:
    ...     bag.add_topic("/observation", "sensor_msgs/msg/JointState", qos=[STREAM_QOS])
    ...     bag.write("/observation", t_ns, raw)

    Args:
        path: output file; must end in ``.mcap``. An existing file is an error unless ``overwrite``.
        chunk_size: uncompressed bytes per chunk. A chunk is the unit a crashed recording loses.
        compression: ``"zstd"`` (as ``ros2 bag record --storage-preset-profile zstd_fast``) or
            ``"none"``.
        overwrite: replace an existing file.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        chunk_size: int = DEFAULT_CHUNK_SIZE,
        compression: str = "zstd",
        overwrite: bool = False,
    ) -> None:
        self.path = Path(path)
        if self.path.suffix != ".mcap":
            raise BagError(f"{self.path}: a bag file name must end in .mcap")
        if compression not in ("zstd", "none"):
            raise BagError(f"compression must be 'zstd' or 'none', got {compression!r}")
        self.chunk_size = int(chunk_size)
        self.compression = compression
        self.overwrite = overwrite
        self._topics: dict[str, _Topic] = {}
        self._schemas: dict[str, int] = {}
        self._writer: Writer | None = None
        self._stream: Any = None
        self._start_ns: int | None = None
        self._end_ns = 0
        self._closed = False
        self._spill: _ChunkIndexSpill | None = None  # the chunk indexes, on disk until close
        self.metadata: dict[str, dict[str, str]] = {}  # MCAP metadata records written at close: {name: {key: value}}

    # ---- lifecycle ----------------------------------------------------------------------------
    def open(self) -> "BagWriter":
        """Create the file and write the MCAP header."""
        if self._writer is not None:
            return self
        if self._closed:
            raise BagError(f"{self.path}: writer already closed")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            self._stream = open(self.path, "wb" if self.overwrite else "xb")
        except FileExistsError:
            raise BagError(f"{self.path}: file exists (pass overwrite=True to replace it)") from None
        except OSError as exc:
            raise BagError(f"{self.path}: cannot create: {exc.strerror}") from None
        self._writer = Writer(
            self._stream,
            chunk_size=self.chunk_size,
            compression=CompressionType.ZSTD if self.compression == "zstd" else CompressionType.NONE,
        )
        try:
            self._spill = _spill_chunk_indexes(self._writer, self.path.parent)
            self._writer.start(profile="ros2", library=f"neural_estimator {__version__} (mcap-python)")
        except OSError as exc:
            raise BagError(f"{self.path}: cannot write: {exc.strerror or exc}") from None
        return self

    def close(self) -> Path:
        """Finish the last chunk, write the summary and the rosbag2 metadata, close the file."""
        if self._closed:
            return self.path
        if self._writer is None:
            self.open()
        assert self._writer is not None
        try:
            self._writer.add_metadata("rosbag2", {"serialized_metadata": self._bag_metadata()})
            for name, record in self.metadata.items():
                self._writer.add_metadata(name, {str(k): str(v) for k, v in record.items()})
            self._writer.finish()
            self._stream.flush()
            os.fsync(self._stream.fileno())
        except OSError as exc:  # what reached the disk stays readable (BagReader, ``recover``)
            raise BagError(f"{self.path}: cannot finish the bag: {exc.strerror or exc}") from None
        finally:
            self._closed = True
            if self._spill is not None:
                self._spill.close()
            try:
                self._stream.close()
            except OSError:
                pass  # the buffered tail could not be written either: the error above says so
        return self.path

    def __enter__(self) -> "BagWriter":
        return self.open()

    def __exit__(self, *exc: Any) -> None:
        self.close()

    @property
    def closed(self) -> bool:
        return self._closed

    # ---- topics and messages ---------------------------------------------------------------------
    def add_topic(
        self,
        topic: str,
        msgtype: str,
        *,
        qos: Sequence[Qos] = (),
        msgdef: str | None = None,
        type_hash: str | None = None,
    ) -> None:
        """Declare ``topic`` (absolute name) with its type and offered QoS profiles.

        Types of the Jazzy type store need nothing else; any other type needs ``msgdef`` (its
        ros2msg text with dependencies) and ``type_hash`` (RIHS01). Declaring a topic again with
        the same type is a no-op; with another type it is an error.
        """
        w = self._require_open()
        if not topic.startswith("/"):
            raise BagError(f"topic {topic!r}: bags store absolute topic names (start with '/')")
        known = self._topics.get(topic)
        if known is not None:
            if known.msgtype != msgtype:
                raise BagError(f"topic {topic!r} already holds {known.msgtype}, cannot add it as {msgtype}")
            return
        if msgdef is None or type_hash is None:
            if msgtype not in TYPESTORE.fielddefs:
                raise BagError(f"type {msgtype!r} is not in the ROS 2 Jazzy type store: pass msgdef and type_hash")
            msgdef = TYPESTORE.generate_msgdef(msgtype, ros_version=2)[0] if msgdef is None else msgdef
            type_hash = TYPESTORE.hash_rihs01(msgtype) if type_hash is None else type_hash
        schema_id = self._schemas.get(msgtype)
        if schema_id is None:
            schema_id = w.register_schema(name=msgtype, encoding="ros2msg", data=msgdef.encode())
            self._schemas[msgtype] = schema_id
        channel_id = w.register_channel(
            topic=topic,
            message_encoding="cdr",
            schema_id=schema_id,
            metadata={"offered_qos_profiles": qos_yaml(qos), "topic_type_hash": type_hash},
        )
        self._topics[topic] = _Topic(topic, msgtype, channel_id, tuple(qos), type_hash)

    def write(
        self,
        topic: str,
        time_ns: int,
        raw: bytes | memoryview,
        *,
        publish_time_ns: int | None = None,
        sequence: int = 0,
    ) -> None:
        """Write serialized CDR bytes on a declared topic at log time ``time_ns`` (integer ns)."""
        w = self._require_open()
        t = self._topics.get(topic)
        if t is None:
            raise BagError(f"topic {topic!r} was not declared (add_topic first)")
        time_ns = int(time_ns)
        if time_ns < 0:
            raise BagError(f"log time must be >= 0 ns, got {time_ns}")
        try:
            w.add_message(
                channel_id=t.channel_id,
                log_time=time_ns,
                data=bytes(raw),
                publish_time=time_ns if publish_time_ns is None else int(publish_time_ns),
                sequence=sequence,
            )
        except OSError as exc:  # a full disk or a read-only file system: one line, not a traceback
            raise BagError(f"{self.path}: cannot write: {exc.strerror or exc}") from None
        t.count += 1
        self._start_ns = time_ns if self._start_ns is None else min(self._start_ns, time_ns)
        self._end_ns = max(self._end_ns, time_ns)

    def write_message(self, topic: str, time_ns: int, msg: Any, msgtype: str | None = None, **kw: Any) -> None:
        """Serialize a rosbags message object and write it (declaring the topic if needed)."""
        if msgtype is None:
            msgtype = getattr(msg, "__msgtype__", None)
            if msgtype is None:
                raise BagError(f"cannot tell the type of {type(msg).__name__}: pass msgtype")
        if topic not in self._topics:
            self.add_topic(topic, msgtype)
        self.write(topic, time_ns, TYPESTORE.serialize_cdr(msg, msgtype), **kw)

    def has_topic(self, topic: str) -> bool:
        return topic in self._topics

    # ---- internals -----------------------------------------------------------------------------------
    def _require_open(self) -> Writer:
        if self._closed:
            raise BagError(f"{self.path}: writer already closed")
        if self._writer is None:
            self.open()
        assert self._writer is not None
        return self._writer

    def _bag_metadata(self) -> str:
        """rosbag2's BagMetadata (version 9) as YAML, as ``serialized_metadata`` holds it."""
        start = self._start_ns or 0
        count = sum(t.count for t in self._topics.values())
        duration = max(0, self._end_ns - start) if count else 0
        meta = {
            "version": 9,
            "storage_identifier": "mcap",
            "duration": {"nanoseconds": duration},
            "starting_time": {"nanoseconds_since_epoch": start},
            "message_count": count,
            "topics_with_message_count": [
                {
                    "topic_metadata": {
                        "name": t.name,
                        "type": t.msgtype,
                        "serialization_format": "cdr",
                        "offered_qos_profiles": [q.to_dict() for q in t.qos],
                        "type_description_hash": t.type_hash,
                    },
                    "message_count": t.count,
                }
                for t in self._topics.values()
            ],
            "compression_format": "",
            "compression_mode": "",
            "relative_file_paths": [self.path.name],
            "files": [
                {
                    "path": self.path.name,
                    "starting_time": {"nanoseconds_since_epoch": start},
                    "duration": {"nanoseconds": duration},
                    "message_count": count,
                }
            ],
            "custom_data": {"writer": f"neural_estimator {__version__}"},
            "ros_distro": "jazzy",
        }
        return yaml.safe_dump(meta, default_flow_style=False, sort_keys=False)
