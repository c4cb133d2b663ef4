"""A full disk or a read-only directory under a verb's output: one line, exit status 2, and nothing
under the name asked for (no empty or partial file) nor a temporary file left beside it.

The disk is made full or read-only by the operating system's own errors (ENOSPC, EROFS) raised from
the calls that write, so the tests need no special file system (a tmpfs of 64 KiB and a read-only
tmpfs give the same lines: docs/bad-input.md)."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import pytest

from neural_estimator.cli.app import main

ROOT = Path(__file__).resolve().parents[1]
BAG = str(ROOT / "bags" / "lorenz96.mcap")


def _raise(code: int):
    def fail(*_a, **_k):
        raise OSError(code, os.strerror(code))

    return fail


def _one_line_error(capsys, rc: int, *words: str) -> str:
    err = capsys.readouterr().err.strip()
    assert rc == 2, err
    assert "Traceback" not in err and len(err.splitlines()) == 1, err
    assert err.startswith("neural-estimator: error: "), err
    for w in words:
        assert w in err, err
    return err


def _only(directory: Path, *names: str) -> None:
    assert sorted(p.name for p in directory.iterdir()) == sorted(names)


def test_simulate_onto_a_full_disk_leaves_no_file(tmp_path, monkeypatch, capsys):
    import zipfile

    monkeypatch.setattr(zipfile.ZipFile, "writestr", _raise(errno.ENOSPC))
    rc = main(["simulate", "--scenario", "lorenz96", "--trajectories", "2", "--out", str(tmp_path / "d.npz")])
    _one_line_error(capsys, rc, "d.npz", "No space left on device")
    _only(tmp_path)


def test_simulate_into_a_read_only_directory(tmp_path, monkeypatch, capsys):
    import neural_estimator.data.io as io_module

    monkeypatch.setattr(io_module, "open", _raise(errno.EROFS), raising=False)
    rc = main(["simulate", "--scenario", "lorenz96", "--trajectories", "2", "--out", str(tmp_path / "d.npz")])
    _one_line_error(capsys, rc, "d.npz", "Read-only file system")
    _only(tmp_path)


def test_replay_onto_a_full_disk_leaves_no_partial_bag(tmp_path, monkeypatch, capsys):
    from neural_estimator.bags.writer import BagWriter

    real = BagWriter.write
    written = []

    def write_then_fill(self, *a, **k):  # the disk fills after some messages reached it
        if len(written) > 50:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        written.append(1)
        return real(self, *a, **k)

    monkeypatch.setattr(BagWriter, "write", write_then_fill)
    out = tmp_path / "r.mcap"
    rc = main(["replay", BAG, "--methods", "ekf", "--out", str(out)])
    _one_line_error(capsys, rc, str(out))
    _only(tmp_path)


def test_recover_into_a_read_only_directory(tmp_path, monkeypatch, capsys):
    import neural_estimator.bags.writer as writer_module

    # a read-only file system refuses both the new file and the removal of a leftover
    monkeypatch.setattr(writer_module, "open", _raise(errno.EROFS), raising=False)
    monkeypatch.setattr(Path, "unlink", _raise(errno.EROFS))
    rc = main(["recover", BAG, "--out", str(tmp_path / "x.mcap")])
    err = _one_line_error(capsys, rc, "x.mcap", "Read-only file system")
    assert ".partial" not in err  # the name asked for, not the temporary one
    _only(tmp_path)


def test_metrics_table_onto_a_full_disk(tmp_path, monkeypatch, capsys):
    import neural_estimator.core.atomic as atomic

    scored = tmp_path / "scored.mcap"
    assert main(["replay", BAG, "--methods", "ekf", "--out", str(scored)]) == 0
    capsys.readouterr()
    monkeypatch.setattr(atomic.os, "fsync", _raise(errno.ENOSPC))  # where a full disk reports itself
    rc = main(["metrics", str(scored), "--out", str(tmp_path / "table.csv")])
    _one_line_error(capsys, rc, "table.csv", "No space left on device")
    _only(tmp_path, "scored.mcap")


@pytest.mark.parametrize("code", [errno.ENOSPC, errno.EROFS, errno.EACCES])
def test_replaced_atomically_keeps_the_old_file(tmp_path, code):
    from neural_estimator.core.atomic import WriteError, replaced_atomically

    target = tmp_path / "t.csv"
    target.write_text("old")
    with pytest.raises(WriteError, match=rf"t\.csv: cannot write \({os.strerror(code)}\); nothing was written"):
        with replaced_atomically(target) as tmp:
            tmp.write_text("half")
            raise OSError(code, os.strerror(code))
    assert target.read_text() == "old"
    _only(tmp_path, "t.csv")
