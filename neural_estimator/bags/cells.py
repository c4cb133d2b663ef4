"""The (trajectory, step) cells of one recorded vector stream, held in compact arrays.

A recorded run is read message by message; each valid message of a stream fills the cell its
in-band identity names. :class:`StreamCells` appends each message's identity, stamp and values to
flat typed buffers (24 bytes + 8 per value), instead of a Python dict of tuples and small arrays per
cell: reading peaks at 2.9x the run's arrays (tracemalloc, test_compact_cells.py) where the dict
peaked at 13.3x. :meth:`StreamCells.finish` resolves repeated cells as the dict did: the last
message of a cell is kept, the cells ordered by (trajectory, step), and the order in which each
cell first arrived is kept for messages that name "the first" one.
"""

from __future__ import annotations

from array import array

import numpy as np


class StreamCells:
    """The cells of one stream of values ``width`` wide (see the module docstring)."""

    def __init__(self, width: int) -> None:
        self.width = int(width)
        self._ids = array("q")  # trajectory, step, stamp of every message, in arrival order
        self._values = array("d")
        self.messages = 0  # valid messages appended (repeats included)
        self.duplicates = 0  # of them, those that repeated a cell already filled (set by finish)
        self.n = self.k = self.stamps = self.first = np.zeros(0, dtype=np.int64)
        self.values = np.zeros((0, self.width))

    def add(self, trajectory: int, step: int, stamp_ns: int, values: np.ndarray) -> None:
        self._ids.extend((trajectory, step, stamp_ns))
        self._values.frombytes(np.ascontiguousarray(values, dtype=np.float64).tobytes())
        self.messages += 1

    def finish(self) -> "StreamCells":
        """Resolve the cells: ``n``, ``k``, ``stamps``, ``values`` (U, width) of the U distinct
        cells sorted by (trajectory, step), each from its last message; ``first``: the arrival index
        of each cell's first message. The buffers are released."""
        ids = np.frombuffer(self._ids, dtype=np.int64).reshape(-1, 3).copy()
        values = np.frombuffer(self._values, dtype=np.float64).reshape(-1, self.width).copy()
        self._ids, self._values = array("q"), array("d")
        order = np.lexsort((np.arange(len(ids)), ids[:, 1], ids[:, 0]))  # by (n, k), then arrival
        n, k = ids[order, 0], ids[order, 1]
        new = np.ones(len(order), dtype=bool)
        new[1:] = (n[1:] != n[:-1]) | (k[1:] != k[:-1])
        starts = np.flatnonzero(new)
        ends = np.append(starts[1:], len(order)) - 1  # the last message of each cell
        last = order[ends]
        self.n, self.k, self.stamps = ids[last, 0], ids[last, 1], ids[last, 2]
        self.values = values[last]
        self.first = order[starts]
        self.duplicates = self.messages - len(starts)
        return self

    def drop(self, keep: np.ndarray) -> int:
        """Keep only the cells where ``keep`` is true; the number dropped."""
        dropped = int((~keep).sum())
        if dropped:
            self.n, self.k, self.stamps = self.n[keep], self.k[keep], self.stamps[keep]
            self.values, self.first = self.values[keep], self.first[keep]
        return dropped
