"""Per-trajectory rows of values kept on disk, and an exact median of them in bounded memory.

A run's medians (MedAE, the NEES medians) need every scored cell, and which cells count is only
known once the outlier rule has seen every trajectory. :class:`RowSpill` appends one row of
``width`` float64 values per trajectory to an anonymous temporary file with plain sequential writes
(not a memory map: mapped pages count in the resident set) and reads it back chunk by chunk,
restricted to the rows a mask keeps. :func:`exact_median` selects the median from those chunks by
radix refinement: a non-negative float64 orders as its 64-bit pattern, so four passes, each a
histogram of the next 16 bits among the values that share the bits already fixed, find the k-th
smallest value exactly. Memory: one chunk (:data:`CHUNK_VALUES` values) and a 65,536-bin histogram,
whatever the run's length.
"""

from __future__ import annotations

import math
import tempfile
from collections.abc import Iterator

import numpy as np

CHUNK_VALUES = 1 << 20  # values read back per chunk: 8 MiB, the bound on the temporaries
_DIGIT_BITS = 16
_DIGITS = 1 << _DIGIT_BITS


class RowSpill:
    """Rows of ``width`` float64 values, one per trajectory in the order added, on disk."""

    def __init__(self, width: int, directory: str | None = None) -> None:
        self.width = int(width)
        self.rows = 0
        self._file = tempfile.TemporaryFile(dir=directory)  # unlinked at once: nothing is left behind

    def append(self, rows: np.ndarray) -> None:
        rows = np.ascontiguousarray(rows, dtype=np.float64).reshape(-1, self.width)
        self._file.write(rows.tobytes())
        self.rows += rows.shape[0]

    def chunks(self, keep: np.ndarray | None = None) -> Iterator[np.ndarray]:
        """(rows, width) blocks of the rows where ``keep`` (rows,) is true (all rows when None)."""
        self._file.flush()
        self._file.seek(0)
        per = max(1, CHUNK_VALUES // max(1, self.width))
        for start in range(0, self.rows, per):
            count = min(per, self.rows - start)
            raw = self._file.read(count * self.width * 8)
            block = np.frombuffer(raw, dtype=np.float64).reshape(count, self.width)
            yield block if keep is None else block[keep[start : start + count]]

    def sum_rows(self, keep: np.ndarray) -> np.ndarray:
        """(width,) the sum of the kept rows."""
        total = np.zeros(self.width)
        for block in self.chunks(keep):
            total += block.sum(axis=0)
        return total

    def close(self) -> None:
        self._file.close()


def exact_median(spill: RowSpill, keep: np.ndarray | None = None, nan_as_inf: bool = False) -> float:
    """The median of the non-negative values in the kept rows of ``spill``, equal to ``np.median``
    of them: the middle value, or the mean of the two middle ones for an even count; NaN when a
    value is NaN (``nan_as_inf``: NaN counts as inf) or there is none.

    Raises:
        ValueError: a negative value (the bit order below holds for non-negative floats only).
    """
    count, has_nan = 0, False
    for block in _values(spill, keep, nan_as_inf):
        count += block.size
        has_nan = has_nan or bool(np.isnan(block).any())
        if (block < 0).any():
            raise ValueError("exact_median takes non-negative values only")
    if count == 0 or has_nan:
        return math.nan
    upper = _kth(spill, keep, nan_as_inf, count // 2)
    if count % 2:
        return upper
    lower = _kth(spill, keep, nan_as_inf, count // 2 - 1)
    return float((np.float64(lower) + np.float64(upper)) / 2.0)


def _values(spill: RowSpill, keep: np.ndarray | None, nan_as_inf: bool) -> Iterator[np.ndarray]:
    for block in spill.chunks(keep):
        flat = block.ravel() + 0.0  # -0.0 + 0.0 = +0.0: one bit pattern for zero
        yield np.where(np.isnan(flat), np.inf, flat) if nan_as_inf else flat


def _kth(spill: RowSpill, keep: np.ndarray | None, nan_as_inf: bool, k: int) -> float:
    """The k-th smallest (0-based) value, its 64 bits fixed 16 at a time, most significant first:
    each pass counts the candidates (values whose leading bits equal those fixed so far) by their
    next 16 bits, and the cumulative counts name the digit that holds the k-th one."""
    prefix = 0
    for shift in range(64 - _DIGIT_BITS, -1, -_DIGIT_BITS):
        hist = np.zeros(_DIGITS, dtype=np.int64)
        for flat in _values(spill, keep, nan_as_inf):
            bits = flat.view(np.uint64)
            if shift < 64 - _DIGIT_BITS:
                bits = bits[(bits >> np.uint64(shift + _DIGIT_BITS)) == np.uint64(prefix)]
            digits = ((bits >> np.uint64(shift)) & np.uint64(_DIGITS - 1)).astype(np.intp)
            hist += np.bincount(digits, minlength=_DIGITS)
        cum = np.cumsum(hist)
        digit = int(np.searchsorted(cum, k, side="right"))
        k -= int(cum[digit - 1]) if digit else 0
        prefix = (prefix << _DIGIT_BITS) | digit
    return float(np.array([prefix], dtype=np.uint64).view(np.float64)[0])
