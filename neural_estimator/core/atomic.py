"""Output files that appear whole or not at all.

Every file a verb writes (``simulate``'s dataset, ``metrics --out``'s table, ``replay``'s and
``recover``'s bags) is written under a temporary name beside its target and renamed over the
target only once complete: ``os.replace`` within one directory is atomic on POSIX, so a full disk,
a read-only directory or an interrupted run leaves either the old file or none, never an empty or
half-written one under the name asked for. The temporary file is removed on failure, and the failure
becomes one :class:`WriteError` line naming the target and the operating system's reason.
"""

from __future__ import annotations

import contextlib
import os
import threading
from collections.abc import Iterator
from pathlib import Path


class WriteError(OSError):
    """An output file could not be written; the message names the file and why (one line)."""


def temporary_name(path: Path) -> Path:
    """A name beside ``path``, private to this process and thread (parallel writers of the same file
    must not rename each other's), with the same suffix (writers that check it still accept it)."""
    return path.with_name(f".{path.stem}.{os.getpid()}.{threading.get_ident()}.partial{path.suffix}")


@contextlib.contextmanager
def replaced_atomically(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path to write; on success it is renamed over ``path``.

    On any exception the temporary file is removed; an ``OSError`` (ENOSPC, EROFS, EACCES, ...)
    is raised again as :class:`WriteError` ``"<path>: cannot write (<reason>); nothing was written"``,
    other exceptions unchanged.
    """
    path = Path(path)
    tmp = temporary_name(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        yield tmp
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(OSError):  # a read-only directory cannot hold it: nothing to remove
            tmp.unlink(missing_ok=True)
        if isinstance(exc, OSError) and not isinstance(exc, WriteError):
            raise WriteError(f"{path}: cannot write ({_reason(exc)}); nothing was written") from None
        raise


def write_text_atomically(path: str | Path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` through :func:`replaced_atomically`."""
    with replaced_atomically(path) as tmp:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())  # ENOSPC can surface only here (delayed allocation)
    return Path(path)


def _reason(exc: OSError) -> str:
    if exc.strerror:
        return exc.strerror
    return str(exc).splitlines()[0] if str(exc) else type(exc).__name__
