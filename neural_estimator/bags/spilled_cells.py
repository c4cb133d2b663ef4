"""The cells of one recorded vector stream kept on disk, and read back a block of trajectories at a time.

:class:`SpilledCells` takes the messages of a stream as :class:`~neural_estimator.bags.cells.StreamCells`
does (``add``), but appends each one as a record (trajectory, step, stamp, arrival index, values) to
an anonymous temporary file with plain sequential writes, through a 1 MiB buffer. :meth:`SpilledCells.partition`
then reads the file chunk by chunk and appends each record to the file of its trajectory block
(``trajectory // block``); :meth:`SpilledCells.block` reads one block back and resolves it as
StreamCells.finish resolves the whole stream: the last message of a repeated cell is kept.
Resident memory: the buffer, one chunk and one block, whatever the recording's length.
"""

from __future__ import annotations

import os
import tempfile
from array import array
from collections.abc import Iterator
from pathlib import Path

import numpy as np

CHUNK_RECORDS_BYTES = 8 << 20  # bytes of records read back per chunk
_BUFFER_BYTES = 1 << 20
_HEAD = 4  # trajectory, step, stamp, arrival index (int64 each)


class ResolvedCells:
    """The distinct cells of one stream in one block, sorted by (trajectory, step): ``n``, ``k``,
    ``stamps`` (U,) and ``values`` (U, width), each from the cell's last message; ``duplicates``:
    the messages that repeated a cell."""

    def __init__(self, records: np.ndarray, width: int) -> None:
        ids = records[:, :_HEAD].view(np.int64)
        order = np.lexsort((ids[:, 3], ids[:, 1], ids[:, 0]))  # by (n, k), then arrival
        n, k = ids[order, 0], ids[order, 1]
        new = np.ones(len(order), dtype=bool)
        new[1:] = (n[1:] != n[:-1]) | (k[1:] != k[:-1])
        starts = np.flatnonzero(new)
        last = order[np.append(starts[1:], len(order))[: len(starts)] - 1]  # the last message of each cell
        self.n, self.k, self.stamps = ids[last, 0].copy(), ids[last, 1].copy(), ids[last, 2].copy()
        self.values = records[last, _HEAD:].reshape(-1, width).copy()
        self.duplicates = len(order) - len(starts)


class SpilledCells:
    """The messages of one stream ``width`` values wide, on disk (module docstring)."""

    def __init__(self, width: int, directory: str | Path) -> None:
        self.width = int(width)
        self.record = _HEAD + self.width  # 8-byte words per record
        self.messages = 0
        self._dir = Path(directory)
        fd, name = tempfile.mkstemp(dir=self._dir, suffix=".cells")
        os.close(fd)
        self._path = Path(name)
        self._buffer = bytearray()
        self._blocks: dict[int, Path] = {}
        self.block_size = 0

    def add(self, trajectory: int, step: int, stamp_ns: int, values: np.ndarray) -> None:
        self._buffer += array("q", (trajectory, step, stamp_ns, self.messages)).tobytes()
        self._buffer += np.ascontiguousarray(values, dtype=np.float64).tobytes()
        self.messages += 1
        if len(self._buffer) >= _BUFFER_BYTES:
            self._flush()

    def _flush(self) -> None:
        with open(self._path, "ab") as f:
            f.write(self._buffer)
        self._buffer = bytearray()

    def finish(self) -> "SpilledCells":
        self._flush()
        return self

    def chunks(self, path: Path | None = None) -> Iterator[np.ndarray]:
        """(records, record) float64 blocks of the file (ids as int64 bit patterns)."""
        per = max(1, CHUNK_RECORDS_BYTES // (8 * self.record))
        with open(path or self._path, "rb") as f:
            while True:
                raw = f.read(per * 8 * self.record)
                if not raw:
                    return
                yield np.frombuffer(raw, dtype=np.float64).reshape(-1, self.record)

    def survey(self, n_run: int, t_run: int) -> tuple[int, np.ndarray, int]:
        """(messages outside the announced run, the distinct trajectories received inside it,
        the largest step inside it, -1 when none). ``n_run``/``t_run`` 0: not announced."""
        outside, trajectories, top = 0, np.zeros(0, dtype=np.int64), -1
        for chunk in self.chunks():
            ids = chunk[:, :2].view(np.int64)
            inside = self._inside(ids, n_run, t_run)
            outside += int((~inside).sum())
            if inside.any():
                trajectories = np.union1d(trajectories, ids[inside, 0])
                top = max(top, int(ids[inside, 1].max()))
        return outside, trajectories, top

    @staticmethod
    def _inside(ids: np.ndarray, n_run: int, t_run: int) -> np.ndarray:
        if not (n_run and t_run):
            return np.ones(len(ids), dtype=bool)
        return (ids[:, 0] >= 0) & (ids[:, 0] < n_run) & (ids[:, 1] >= 0) & (ids[:, 1] < t_run)

    def partition(self, block: int, n_run: int, t_run: int) -> None:
        """Append every record inside the announced run to the file of its block (trajectory //
        ``block``); the stream's own file is then removed."""
        self.block_size = int(block)
        for chunk in self.chunks():
            ids = chunk[:, :2].view(np.int64)
            chunk = chunk[self._inside(ids, n_run, t_run)]
            if not len(chunk):
                continue
            which = chunk[:, 0].view(np.int64) // self.block_size
            order = np.argsort(which, kind="stable")  # keeps the arrival order within a block
            which, chunk = which[order], chunk[order]
            bounds = np.flatnonzero(np.diff(which)) + 1
            for part in np.split(np.arange(len(which)), bounds):
                b = int(which[part[0]])
                path = self._blocks.setdefault(b, self._path.with_name(f"{self._path.stem}.{b}"))
                with open(path, "ab") as f:
                    f.write(chunk[part].tobytes())
        self._path.unlink(missing_ok=True)

    def block(self, b: int) -> ResolvedCells:
        """The resolved cells of block ``b`` (empty when no message fell in it)."""
        path = self._blocks.get(b)
        records = (
            np.concatenate(list(self.chunks(path))) if path is not None else np.zeros((0, self.record), np.float64)
        )
        return ResolvedCells(records, self.width)
