"""The fuzz harness (scripts/fuzz.py) in the test suite: a short coverage-guided run of every target,
and every input a longer run ever crashed on (test/data/fuzz/<target>/) replayed as a regression."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("atheris")
ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "fuzz.py"
REGRESSIONS = ROOT / "test" / "data" / "fuzz"


def _harness():
    spec = importlib.util.spec_from_file_location("ne_fuzz_harness", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _regressions() -> list[tuple[str, Path]]:
    return [
        (d.name, f) for d in sorted(REGRESSIONS.iterdir()) if d.is_dir() for f in sorted(d.iterdir()) if f.is_file()
    ]


@pytest.mark.parametrize(("target", "path"), _regressions(), ids=lambda v: v if isinstance(v, str) else v.name)
def test_every_input_that_once_crashed_is_handled(target, path, tmp_path):
    _harness().Target(target, tmp_path).run(path.read_bytes())  # raises on a regression


def test_the_regression_corpus_is_not_empty():
    assert len(_regressions()) >= 2


@pytest.mark.slow
@pytest.mark.parametrize("target", ["mcap", "rosbag2", "cdr", "scenario"])
def test_a_short_fuzzing_run_finds_nothing(target, tmp_path):
    """A few hundred mutated inputs per target (a few seconds): the longer campaign is the script's.

    Memory: libFuzzer reads its RSS as getrusage's ru_maxrss, which on Linux a forked child starts at
    its parent's resident size and keeps across exec; spawned from this pytest process (torch and the
    earlier tests' data resident, over 1 GB late in a full run) the fuzzer would start "over" a fixed
    1,024 MB limit. So the limit is 1,024 MB above this process's peak, and a single allocation over
    1,024 MB fails on its own (-malloc_limit_mb)."""
    import resource

    parent_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss // 1024  # kB on Linux
    proc = subprocess.run(
        [
            sys.executable,
            str(SCRIPT),
            target,
            "-runs=400",
            "-timeout=10",
            f"-rss_limit_mb={1024 + parent_mb}",
            "-malloc_limit_mb=1024",
            f"-artifact_prefix={tmp_path}/",
        ],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Done 400 runs" in proc.stderr or "DONE" in proc.stderr
