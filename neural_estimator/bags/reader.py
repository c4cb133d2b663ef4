"""Read an MCAP bag, also one whose recording was cut short or damaged.

>>> with BagReader("run.mcap") as bag:
...     for conn, t_ns, raw in bag.messages(["/observation"]):
...         ...

Like rosbags' ``AnyReader``: a context manager, messages yielded as ``(connection, time_ns, raw)``
in log-time order (ties in file order), integer nanoseconds, :meth:`BagReader.decoded` for message
objects.

The reader does not trust the summary at the end of the file: it walks the records from the start,
so a file whose writer was killed (no summary, no footer, a half-written last chunk) or whose
middle was damaged is read as far as it can be. Every chunk that is complete and whose checksum
matches is recovered; a damaged chunk is skipped and reading resumes after it when its length is
intact. What was lost is described in :attr:`BagReader.damage` (bytes, chunks, and the time span
the lost chunks covered) and announced as a :class:`~neural_estimator.bags.errors.BagWarning`;
with ``strict=True`` any damage is a :class:`~neural_estimator.bags.errors.BagError` instead.
"""

from __future__ import annotations

import dataclasses
import heapq
import os
import struct
import warnings
import zlib
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any, BinaryIO

from neural_estimator.bags.errors import BagError, BagWarning
from neural_estimator.stream.messages import TYPESTORE

try:
    import zstandard
except ImportError:  # pragma: no cover - zstandard comes with mcap
    zstandard = None
try:
    import lz4.frame as lz4_frame
except ImportError:  # pragma: no cover
    lz4_frame = None

MAGIC = b"\x89MCAP0\r\n"
_OP_HEADER, _OP_FOOTER, _OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06
_OP_METADATA, _OP_DATA_END = 0x0C, 0x0F
_MAX_OPCODE = 0x0F
MAX_CHUNK_ENV = "NEURAL_ESTIMATOR_MAX_CHUNK_MB"
DEFAULT_MAX_CHUNK_MB = 64  # rosbag2 writes 768 KiB chunks, this package 256 KiB, the mcap CLI 4 MiB


# The longest schema text read (a .msg definition with its dependencies, as rosbag2 stores it; the
# largest of this package's bags is under 2 KB, and a Jazzy message with every dependency stays
# under 100 KB). A longer schema is not read (its type's messages decode through the Jazzy type store
# where it knows the type) and is reported in one warning: a 50 MB schema had cost 438 MB of memory.
MAX_SCHEMA_BYTES = 1 << 20
_SCHEMA_HEAD_BYTES = 1 << 16  # id, name and encoding of an oversized schema record: read, then stop


def max_chunk_bytes() -> int:
    """The largest uncompressed chunk a bag may declare (bytes): ``$NEURAL_ESTIMATOR_MAX_CHUNK_MB``
    MiB (default 64), checked before decompressing (zstd and lz4)."""
    try:
        return int(float(os.environ.get(MAX_CHUNK_ENV, DEFAULT_MAX_CHUNK_MB)) * 2**20)
    except ValueError:
        raise BagError(f"{MAX_CHUNK_ENV} must be a number of MiB, got {os.environ[MAX_CHUNK_ENV]!r}") from None


def _read_at_most(reader, n: int) -> bytes:
    """Up to ``n`` bytes of a stream reader (several reads: one may return less)."""
    parts, got = [], 0
    while got < n:
        piece = reader.read(n - got)
        if not piece:
            break
        parts.append(piece)
        got += len(piece)
    return b"".join(parts)


_U16, _U32, _U64 = struct.Struct("<H"), struct.Struct("<I"), struct.Struct("<Q")
_MSG_HEAD = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_CHUNK_HEAD = struct.Struct("<QQQI")  # start, end, uncompressed size, uncompressed crc


@dataclasses.dataclass
class Connection:
    """One topic of the bag (an MCAP channel with its schema)."""

    id: int
    topic: str
    msgtype: str
    msgdef: str  # ros2msg text of the schema
    message_encoding: str  # "cdr"
    offered_qos_profiles: str  # rosbag2's YAML
    type_hash: str  # RIHS01_... where recorded
    msgcount: int = 0  # messages recovered


@dataclasses.dataclass(frozen=True)
class BagDamage:
    """What a damaged or unfinished bag lost."""

    path: str
    file_size: int
    lost_bytes: int  # bytes that could not be used (damaged chunks and the unreadable tail)
    chunks_recovered: int
    messages_recovered: int
    chunks_lost: int  # damaged or incomplete chunks (their messages are lost)
    lost_span_ns: tuple[int, int] | None  # log-time span covered by the lost chunks, where known
    problems: tuple[str, ...]

    def __str__(self) -> str:
        span = ""
        if self.lost_span_ns is not None:
            a, b = self.lost_span_ns
            span = f"; lost chunks covered log times {a} .. {b} ns ({(b - a) / 1e9:.3f} s)"
        return (
            f"{self.path}: damaged or unfinished bag ({'; '.join(self.problems)}). Recovered "
            f"{self.messages_recovered} messages in {self.chunks_recovered} complete chunks; lost "
            f"{self.chunks_lost} chunk(s), {self.lost_bytes} of {self.file_size} bytes{span}."
        )


@dataclasses.dataclass
class _Chunk:
    offset: int  # file offset of the chunk data (compressed records)
    length: int
    start: int
    end: int
    usize: int
    crc: int
    compression: str
    record_at: int = 0  # file offset of the chunk record
    counts: dict[int, int] = dataclasses.field(default_factory=dict)  # messages per channel


class BagSummary:
    """What every bag reader shares (an MCAP file, a rosbag2 directory, a sqlite3 bag): a context
    manager over its ``open`` and ``close``, and the summary of its ``connections``."""

    connections: list[Connection]

    def __enter__(self) -> Any:
        return self.open()

    def __exit__(self, *exc: Any) -> None:
        self.close()

    @property
    def topics(self) -> dict[str, Connection]:
        """{topic: connection}."""
        return {c.topic: c for c in self.connections}

    @property
    def message_count(self) -> int:
        return sum(c.msgcount for c in self.connections)


class PartedBag(BagSummary):
    """A bag made of parts, each a bag of its own (a rosbag2 directory's files, a sqlite3 bag's
    databases): closing it closes every part."""

    parts: list[Any]

    def close(self) -> None:
        for part in self.parts:
            part.close()
        self.parts = []


class BagReader(BagSummary):
    """Read messages of one ``.mcap`` file (see the module docstring).

    Args:
        path: the bag file.
        strict: raise :class:`BagError` on any damage instead of recovering what is readable.
    """

    def __init__(self, path: str | Path, *, strict: bool = False) -> None:
        self.path = Path(path)
        self.strict = strict
        self.connections: list[Connection] = []
        self.metadata: dict[str, dict[str, str]] = {}
        self.profile = ""
        self.damage: BagDamage | None = None
        self._f: BinaryIO | None = None
        self._schemas: dict[int, tuple[str, str, str]] = {}  # id -> (name, encoding, text)
        self._channels: dict[int, Connection] = {}
        self._chunks: list[_Chunk] = []
        self._loose: list[tuple[int, int, int, bytes]] = []  # messages outside chunks
        self._registered: set[str] = set()
        self._oversized: dict[str, int] = {}  # schema name -> bytes of a schema text not read

    # ---- lifecycle --------------------------------------------------------------------------------
    def open(self) -> "BagReader":
        if self._f is not None:
            return self
        if not self.path.is_file():
            raise BagError(f"{self.path}: no such bag file")
        self._f = open(self.path, "rb")
        try:
            self._scan()
        except BaseException:
            self.close()
            raise
        return self

    def close(self) -> None:
        if self._f is not None:
            self._f.close()
            self._f = None

    # ---- summary ----------------------------------------------------------------------------------
    @property
    def start_time(self) -> int:
        """Earliest log time (ns) of the recovered messages (0 for an empty bag)."""
        times = [c.start for c in self._chunks] + [m[1] for m in self._loose]
        return min(times) if times else 0

    @property
    def end_time(self) -> int:
        """Latest log time (ns) of the recovered messages (0 for an empty bag)."""
        times = [c.end for c in self._chunks] + [m[1] for m in self._loose]
        return max(times) if times else 0

    def connection(self, topic: str, msgtype: str | None = None) -> Connection:
        """The connection of ``topic``; with ``msgtype``, a clear error when it holds another type."""
        conn = self.topics.get(topic)
        if conn is None:
            raise BagError(f"{self.path}: no topic {topic!r} (topics: {', '.join(sorted(self.topics)) or 'none'})")
        if msgtype is not None and conn.msgtype != msgtype:
            raise BagError(f"{self.path}: topic {topic!r} holds {conn.msgtype}, expected {msgtype}")
        return conn

    # ---- messages ----------------------------------------------------------------------------------
    def messages(
        self,
        topics: Iterable[str] | None = None,
        start: int | None = None,
        stop: int | None = None,
    ) -> Iterator[tuple[Connection, int, bytes]]:
        """Yield ``(connection, log_time_ns, raw_cdr)`` in log-time order.

        Args:
            topics: only these topics (default all).
            start, stop: only log times in [start, stop).
        """
        self._require_open()
        want = None if topics is None else {self.topics[t].id for t in topics if t in self.topics}
        lo = -1 if start is None else int(start)
        hi = 2**64 if stop is None else int(stop)
        chunks = sorted((c for c in self._chunks if c.end >= lo and c.start < hi), key=lambda c: (c.start, c.offset))
        heap: list[tuple[int, int, int, bytes]] = []
        seq = 0
        for cid, t, raw in ((m[0], m[1], m[3]) for m in self._loose):
            if (want is None or cid in want) and lo <= t < hi:
                heap.append((t, seq, cid, raw))
                seq += 1
        heapq.heapify(heap)
        i = 0
        # Chunks are opened lazily: a chunk whose first message is later than every message
        # already queued cannot hold an earlier one.
        while heap or i < len(chunks):
            while i < len(chunks) and (not heap or chunks[i].start <= heap[0][0]):
                for cid, t, raw in self._chunk_messages(chunks[i]):
                    if (want is None or cid in want) and lo <= t < hi:
                        heapq.heappush(heap, (t, seq, cid, raw))
                        seq += 1
                i += 1
            if heap:
                t, _, cid, raw = heapq.heappop(heap)
                yield self._channels[cid], t, raw

    __iter__ = messages

    def decoded(self, topics: Iterable[str] | None = None) -> Iterator[tuple[Connection, int, Any]]:
        """Yield ``(connection, log_time_ns, message)`` with rosbags message objects."""
        for conn, t, raw in self.messages(topics):
            yield conn, t, self.deserialize(raw, conn)

    def deserialize(self, raw: bytes, conn: Connection) -> Any:
        """A rosbags message object from the CDR bytes of ``conn`` (types outside the Jazzy store
        are registered from the bag's schema)."""
        if conn.msgtype not in TYPESTORE.fielddefs and conn.msgtype not in self._registered:
            self._register(conn)
        try:
            return TYPESTORE.deserialize_cdr(raw, conn.msgtype)
        except Exception as exc:
            raise BagError(f"{self.path}: cannot decode a {conn.msgtype} message on {conn.topic}: {exc}") from None

    # ---- internals ---------------------------------------------------------------------------------
    def _require_open(self) -> None:
        if self._f is None:
            raise BagError(f"{self.path}: reader is not open (use it as a context manager)")

    def _register(self, conn: Connection) -> None:
        register_schema(conn, self.path)
        self._registered.add(conn.msgtype)

    def _read(self, offset: int, n: int) -> bytes:
        assert self._f is not None
        self._f.seek(offset)
        return self._f.read(n)

    def _scan(self) -> None:
        """Walk the data section record by record (see the module docstring)."""
        size = self.path.stat().st_size
        if size == 0:
            raise BagError(f"{self.path}: empty file (0 bytes), not an MCAP bag")
        if self._read(0, 8) != MAGIC:
            raise BagError(f"{self.path}: not an MCAP file (bad magic bytes)")
        problems: list[str] = []
        lost_bytes = 0
        lost_chunks = 0
        lost_span: list[int] = []
        pos = 8
        finished = False
        while True:
            if pos + 9 > size:
                if finished:
                    problems.append(f"the summary is cut short at byte {size} (every data record was read)")
                elif pos < size:
                    problems.append(f"file ends at byte {size} inside a record header")
                else:
                    problems.append("file ends without its summary (the writer did not close it)")
                lost_bytes += size - pos
                break
            head = self._read(pos, 9)
            op, length = head[0], _U64.unpack_from(head, 1)[0]
            body_at, end = pos + 9, pos + 9 + length
            if op == 0 or op > _MAX_OPCODE and op < 0x80:
                problems.append(f"unreadable record at byte {pos} (opcode {op:#04x}): data after it ignored")
                lost_bytes += size - pos
                break
            if end > size:
                if finished:
                    problems.append(f"the summary is cut short at byte {size} (every data record was read)")
                    lost_bytes += size - pos
                    break
                what = "chunk" if op == _OP_CHUNK else f"record (opcode {op:#04x})"
                problems.append(f"file ends at byte {size} inside a {what} of {length} bytes starting at byte {pos}")
                if op == _OP_CHUNK and size - body_at >= 16:
                    s, e = struct.unpack_from("<QQ", self._read(body_at, 16))
                    lost_span += [s, e]
                lost_chunks += op == _OP_CHUNK
                lost_bytes += size - pos
                break
            if op == _OP_FOOTER:
                finished = True
                if self._read(end, 8) != MAGIC:
                    problems.append("the closing magic after the footer is missing")
                break
            if op == _OP_DATA_END:
                finished = True  # the summary section follows; everything was read
                pos = end
                continue
            if op == _OP_CHUNK:
                ok, reason, span = self._scan_chunk(body_at, length, pos)
                if not ok:
                    problems.append(f"chunk at byte {pos}: {reason}")
                    lost_bytes += 9 + length
                    lost_chunks += 1
                    if span is not None:
                        lost_span += list(span)
            elif finished:
                if op in (_OP_SCHEMA, _OP_CHANNEL):  # the summary repeats them: a fallback when a
                    n_read = min(length, MAX_SCHEMA_BYTES + _SCHEMA_HEAD_BYTES) if op == _OP_SCHEMA else length
                    try:  # damaged chunk held the first definition
                        self._record(op, self._read(body_at, n_read), loose=False)
                    except (struct.error, UnicodeDecodeError, IndexError):
                        pass
            elif op == _OP_HEADER:
                body = self._read(body_at, length)
                if len(body) < 4:  # a header too short for its profile string: the profile is unknown
                    problems.append(f"malformed header record at byte {pos} ({len(body)} bytes)")
                else:
                    n = _U32.unpack_from(body, 0)[0]
                    self.profile = body[4 : 4 + n].decode(errors="replace")
            elif op in (_OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE, _OP_METADATA):
                # of a schema record, no more than its head and a schema text within the bound is read
                n_read = min(length, MAX_SCHEMA_BYTES + _SCHEMA_HEAD_BYTES) if op == _OP_SCHEMA else length
                try:
                    self._record(op, self._read(body_at, n_read), loose=True)
                except (struct.error, UnicodeDecodeError, IndexError) as exc:
                    problems.append(f"malformed record at byte {pos} (opcode {op:#04x}): {exc}")
                    lost_bytes += 9 + length
            pos = end
        self._settle(size, problems, lost_bytes, lost_chunks, lost_span)

    def _settle(self, size: int, problems: list[str], lost_bytes: int, lost_chunks: int, lost_span: list[int]) -> None:
        """After the scan: drop the chunks whose channels were never defined, count each channel's
        messages, and report the damage (a warning, or BagError when strict)."""
        for chunk in list(self._chunks):
            unknown = sorted(set(chunk.counts) - set(self._channels))
            if unknown:
                problems.append(f"chunk at byte {chunk.record_at}: messages on undefined channel(s) {unknown}")
                self._chunks.remove(chunk)
                lost_chunks += 1
                lost_bytes += chunk.length
                lost_span += [chunk.start, chunk.end]
                continue
            for cid, k in chunk.counts.items():
                self._channels[cid].msgcount += k
        self.connections = sorted(self._channels.values(), key=lambda c: c.id)
        for name, n in self._oversized.items():
            warnings.warn(
                f"{self.path}: the schema of {name[:80]!r} holds {n:,} bytes, over the bound of "
                f"{MAX_SCHEMA_BYTES:,}: not read (its messages decode only where the Jazzy type store knows the type)",
                BagWarning,
                stacklevel=4,
            )
        if problems:
            self.damage = BagDamage(
                path=str(self.path),
                file_size=size,
                lost_bytes=lost_bytes,
                chunks_recovered=len(self._chunks),
                messages_recovered=self.message_count,
                chunks_lost=lost_chunks,
                lost_span_ns=(min(lost_span), max(lost_span)) if lost_span else None,
                problems=tuple(problems),
            )
            if self.strict:
                raise BagError(str(self.damage))
            warnings.warn(str(self.damage), BagWarning, stacklevel=4)  # the caller of _scan

    def _scan_chunk(self, at: int, length: int, record_at: int) -> tuple[bool, str, tuple[int, int] | None]:
        body = self._read(at, length)
        try:
            start, end, usize, crc = _CHUNK_HEAD.unpack_from(body, 0)
            n = _U32.unpack_from(body, 28)[0]
            compression = body[32 : 32 + n].decode()
            data_len = _U64.unpack_from(body, 32 + n)[0]
            data_at = 40 + n
        except (struct.error, UnicodeDecodeError) as exc:
            return False, f"malformed chunk header ({exc})", None
        if data_at + data_len > length:
            return False, "chunk data longer than its record", (start, end)
        chunk = _Chunk(at + data_at, data_len, start, end, usize, crc, compression, record_at)
        try:
            records = self._decompress(chunk, body[data_at : data_at + data_len])
            counts: dict[int, int] = {}
            for op, rec in _records(records):
                if op == _OP_MESSAGE:
                    cid = _U16.unpack_from(rec, 0)[0]
                    counts[cid] = counts.get(cid, 0) + 1
                elif op in (_OP_SCHEMA, _OP_CHANNEL):
                    self._record(op, rec, loose=False)
        except (BagError, struct.error, UnicodeDecodeError, IndexError) as exc:
            return False, str(exc), (start, end)
        chunk.counts = counts
        self._chunks.append(chunk)
        return True, "", None

    def _decompress(self, chunk: _Chunk, data: bytes) -> bytes:
        limit = max_chunk_bytes()
        if chunk.usize > limit and chunk.compression:
            raise BagError(
                f"a chunk declares {chunk.usize} bytes uncompressed, over the bound of {limit} bytes "
                f"({MAX_CHUNK_ENV}, MiB): not decompressed"
            )
        try:
            # never more than the declared size (+1 byte, to notice a chunk that holds more): a
            # crafted chunk cannot make the reader allocate what its header does not declare
            if chunk.compression == "zstd":
                if zstandard is None:
                    raise BagError("zstd chunk but the zstandard module is missing")
                raw = _read_at_most(zstandard.ZstdDecompressor().stream_reader(data), chunk.usize + 1)
            elif chunk.compression == "lz4":
                if lz4_frame is None:
                    raise BagError("lz4 chunk but the lz4 module is missing")
                raw = lz4_frame.LZ4FrameDecompressor().decompress(data, max_length=chunk.usize + 1)
            elif chunk.compression == "":
                raw = data
            else:
                raise BagError(f"unsupported chunk compression {chunk.compression!r}")
        except BagError:
            raise
        except Exception as exc:  # zstd/lz4 errors on damaged data
            raise BagError(f"cannot decompress ({exc})") from None
        if len(raw) != chunk.usize:
            raise BagError(f"decompressed to {len(raw)} bytes, expected {chunk.usize}")
        if chunk.crc and zlib.crc32(raw) != chunk.crc:
            raise BagError("checksum mismatch (the chunk's bytes were changed)")
        return raw

    def _chunk_messages(self, chunk: _Chunk) -> list[tuple[int, int, bytes]]:
        raw = self._decompress(chunk, self._read(chunk.offset, chunk.length))
        out = []
        for op, rec in _records(raw):
            if op == _OP_MESSAGE:
                cid, _, log_time, _ = _MSG_HEAD.unpack_from(rec, 0)
                out.append((cid, log_time, bytes(rec[_MSG_HEAD.size :])))
        out.sort(key=lambda m: m[1])  # stable: ties stay in file order
        return out

    def _record(self, op: int, rec: bytes | memoryview, loose: bool) -> None:
        if op == _OP_SCHEMA:
            sid = _U16.unpack_from(rec, 0)[0]
            name, p = _string(rec, 2)
            enc, p = _string(rec, p)
            n = _U32.unpack_from(rec, p)[0]
            if n > MAX_SCHEMA_BYTES:  # bounded memory: the text is neither copied nor decoded
                self._oversized[name] = n
                self._schemas.setdefault(sid, (name, enc, ""))
                return
            self._schemas[sid] = (name, enc, bytes(rec[p + 4 : p + 4 + n]).decode(errors="replace"))
        elif op == _OP_CHANNEL:
            cid, sid = struct.unpack_from("<HH", rec, 0)
            topic, p = _string(rec, 4)
            encoding, p = _string(rec, p)
            meta, _ = _string_map(rec, p)
            if cid in self._channels:
                return
            name, _, text = self._schemas.get(sid, ("", "", ""))
            self._channels[cid] = Connection(
                id=cid,
                topic=topic,
                msgtype=name,
                msgdef=text,
                message_encoding=encoding,
                offered_qos_profiles=meta.get("offered_qos_profiles", ""),
                type_hash=meta.get("topic_type_hash", ""),
            )
        elif op == _OP_MESSAGE and loose:
            cid, seq, log_time, _ = _MSG_HEAD.unpack_from(rec, 0)
            if cid in self._channels:
                self._channels[cid].msgcount += 1
                self._loose.append((cid, log_time, seq, bytes(rec[_MSG_HEAD.size :])))
        elif op == _OP_METADATA:
            name, p = _string(rec, 0)
            meta, _ = _string_map(rec, p)
            self.metadata[name] = meta


def register_schema(conn: Connection, where: str | Path) -> None:
    """Register ``conn``'s message type, and the types its ros2msg schema embeds, in the type store
    (types outside the Jazzy store: a bag's own messages). BagError names the bag otherwise."""
    from rosbags.typesys import get_types_from_msg

    types: dict[str, Any] = {}
    name, text = conn.msgtype, conn.msgdef
    try:
        for part in text.split("=" * 80 + "\n"):
            if part.startswith("MSG: "):
                head, _, body = part.partition("\n")
                name, text = head[5:].strip(), body
            else:
                text = part
            types.update(get_types_from_msg(text, name))
        TYPESTORE.register(types)
    except Exception as exc:
        raise BagError(f"{where}: cannot use the schema of {conn.msgtype}: {exc}") from None


def _records(data: bytes) -> Iterator[tuple[int, memoryview]]:
    """(opcode, body) of the records packed in a chunk."""
    view = memoryview(data)
    pos, n = 0, len(data)
    while pos < n:
        if pos + 9 > n:
            raise BagError(f"truncated record inside the chunk at offset {pos}")
        op = view[pos]
        length = _U64.unpack_from(view, pos + 1)[0]
        if pos + 9 + length > n:
            raise BagError(f"record of {length} bytes overruns the chunk at offset {pos}")
        yield op, view[pos + 9 : pos + 9 + length]
        pos += 9 + length


def _string(buf: bytes | memoryview, pos: int) -> tuple[str, int]:
    n = _U32.unpack_from(buf, pos)[0]
    if pos + 4 + n > len(buf):
        raise IndexError("string runs past the record")
    return bytes(buf[pos + 4 : pos + 4 + n]).decode(), pos + 4 + n


def _string_map(buf: bytes | memoryview, pos: int) -> tuple[dict[str, str], int]:
    n = _U32.unpack_from(buf, pos)[0]
    end = pos + 4 + n
    out: dict[str, str] = {}
    p = pos + 4
    while p < end:
        k, p = _string(buf, p)
        v, p = _string(buf, p)
        out[k] = v
    return out, end
