"""The minimal `ros2 run` of pip environments: finds the package's executables, and hands over
to a real ros2 whenever one is on PATH."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

SHIM = Path(sys.executable).with_name("ros2")
pytestmark = pytest.mark.skipif(
    not SHIM.exists(), reason="package not installed in this environment (pip install -e .)"
)


def _run(args, env=None, **kw):
    return subprocess.run([str(SHIM), *args], capture_output=True, text=True, timeout=120, env=env, **kw)


def test_lists_the_package_executables():
    out = _run(["pkg", "executables", "neural_estimator"]).stdout.split("\n")
    for exe in ("simulator", "estimator", "evaluator", "player", "neural-estimator"):
        assert f"neural_estimator {exe}" in out


def test_runs_an_executable_with_its_arguments():
    res = _run(["run", "neural_estimator", "neural-estimator", "scenarios"])
    assert res.returncode == 0 and "lorenz96: x = [" in res.stdout


def test_unknown_executable_is_a_clear_error():
    res = _run(["run", "neural_estimator", "nope"])
    assert res.returncode == 1 and "no executable 'nope' in package 'neural_estimator'" in res.stderr
    assert _run(["topic", "list"]).returncode == 2


def test_hands_over_to_a_real_ros2(tmp_path):
    fake = tmp_path / "bin" / "ros2"
    fake.parent.mkdir()
    fake.write_text('#!/bin/sh\necho real ros2: "$@"\n')
    fake.chmod(0o755)
    env = dict(os.environ, PATH=f"{fake.parent}{os.pathsep}{os.environ.get('PATH', '')}")
    res = _run(["run", "neural_estimator", "estimator", "--ros-args", "-p", "method:=mamba"], env=env)
    assert res.stdout.strip() == "real ros2: run neural_estimator estimator --ros-args -p method:=mamba"
