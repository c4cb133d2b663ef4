"""scripts/train_instances.sh: the queue of trained instances the findings need, walked by each worker
from its own starting point (run here with a stand-in Python that records each call, trains nothing)."""

import os
import stat
import subprocess
from pathlib import Path

from neural_estimator.methods import table

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "train_instances.sh"


def _stand_in(tmp_path: Path) -> tuple[Path, Path]:
    """An executable that appends its arguments (and its worker's parent pid) to a log, one call a line."""
    log = tmp_path / "calls.txt"
    python = tmp_path / "python"
    python.write_text(f'#!/bin/sh\necho "$PPID $*" >> "{log}"\n')
    python.chmod(python.stat().st_mode | stat.S_IXUSR)
    return python, log


def _run(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    python, _ = _stand_in(tmp_path)
    env = {k: v for k, v in os.environ.items() if k != "WORKERS"} | {"PYTHON": str(python)}
    return subprocess.run(
        ["bash", str(SCRIPT), *args], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=60
    )


def _calls(log: Path) -> list[tuple[str, str, str, str]]:
    """(worker, instance, scenario, method) of each recorded call."""
    out = []
    for line in log.read_text().splitlines():
        worker, *argv = line.split()
        opt = dict(zip(argv[1::2], argv[2::2]))  # argv[0] is scripts/train_zoo.py
        assert "--quiet" in argv and opt["--threads"] == "1", line
        out.append((worker, opt["--instance"], opt["--scenarios"], opt["--methods"]))
    return out


def test_each_worker_walks_the_whole_queue_from_its_own_start(tmp_path):
    done = _run(tmp_path, "2")
    assert done.returncode == 0, done.stderr
    calls = _calls(tmp_path / "calls.txt")
    workers = sorted({w for w, *_ in calls})
    assert len(workers) == 2
    nlink = {("nlink", m) for m in table.paper_methods(family="neural")}
    wanted = {(i, s, m) for i in ("1", "2") for s, m in nlink | {("lorenz96", m) for m in ("gru", "mamba", "mamba2")}}
    assert len(wanted) == 18
    firsts = []
    for w in workers:
        mine = [c[1:] for c in calls if c[0] == w]
        assert sorted(mine) == sorted(wanted)  # every entry once, whatever another worker holds
        firsts.append(mine[0])
    assert firsts[0] != firsts[1]  # they start on different trainings


def test_a_bad_worker_count_is_one_line_and_trains_nothing(tmp_path):
    for bad in ("0", "two", "-1"):
        done = _run(tmp_path, bad)
        assert done.returncode == 2
        assert done.stderr.count("\n") == 1 and "number of workers" in done.stderr and bad in done.stderr
    assert not (tmp_path / "calls.txt").exists()
