"""The minimal `ros2 run` of pip environments (`neural-estimator ros2 ...`): finds the package's
executables, runs the nodes with this interpreter, and hands over to a real ros2 whenever one is on
PATH."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow  # each test runs the shim in a new Python process

SHIM = [sys.executable, "-m", "neural_estimator.cli", "ros2"]


def _run(args, env=None, **kw):
    return subprocess.run([*SHIM, *args], capture_output=True, text=True, timeout=120, env=env, **kw)


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


def test_a_node_without_rclpy_names_the_extra_to_install(tmp_path):
    """An install without the ROS 2 wheels: one line naming the [ros] extra, exit status 1."""
    fake = tmp_path / "rclpy"
    fake.mkdir()
    (fake / "__init__.py").write_text("raise ImportError('no rclpy here')\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")]))
    res = _run(["run", "neural_estimator", "estimator", "--ros-args", "-p", "method:=ukf"], env=env)
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 1 and len(lines) == 1, res.stderr
    assert "pip install 'neural_estimator[ros]'" in lines[0]


def test_live_without_rclpy_names_the_extra_to_install(tmp_path):
    fake = tmp_path / "rclpy"
    fake.mkdir()
    (fake / "__init__.py").write_text("raise ImportError('no rclpy here')\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")]))
    cmd = [sys.executable, "-m", "neural_estimator.cli", "live", "--scenario", "lorenz96", "--methods", "ukf"]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=120, env=env)
    assert res.returncode == 1 and res.stderr.strip().count("\n") == 0, res.stderr
    assert "pip install 'neural_estimator[ros]'" in res.stderr


def test_a_wheel_puts_no_generic_command_into_bin(tmp_path):
    """pip's bin/ gets `neural-estimator` only; colcon (setup.py install) still gets the nodes."""
    import configparser
    import shutil

    root = Path(__file__).resolve().parents[1]
    src = tmp_path / "src"
    src.mkdir()
    for name in ("setup.py", "setup.cfg", "package.xml", "resource", "neural_estimator", "params"):
        (shutil.copytree if (root / name).is_dir() else shutil.copy)(
            root / name,
            src / name,
            **({"ignore": shutil.ignore_patterns("zoo", "__pycache__")} if name == "neural_estimator" else {}),
        )
    (tmp_path / "meta").mkdir()
    res = subprocess.run(
        [sys.executable, "setup.py", "-q", "dist_info", "--output-dir", str(tmp_path / "meta")],
        cwd=src,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert res.returncode == 0, res.stderr
    (meta,) = (tmp_path / "meta").glob("*.dist-info")
    eps = configparser.ConfigParser()
    eps.read(meta / "entry_points.txt")
    assert list(eps["console_scripts"]) == ["neural-estimator"]


@pytest.mark.parametrize("home", ["", "cli."])  # spelt apart so that a rewrite of module paths leaves both
def test_a_copy_of_the_shim_on_path_is_not_a_real_ros2(tmp_path, monkeypatch, home):
    """Older installs put a ``ros2`` script into bin/ that runs the shim (from its top-level home
    before it moved under cli/): that is not a real ros2 to hand over to; any other ros2 is."""
    from neural_estimator.cli import ros2_shim

    copy = tmp_path / "bin" / "ros2"
    copy.parent.mkdir()
    script = f"from neural_estimator.{home}ros2_shim import main\nsys.exit(main())\n"
    copy.write_text("#!/usr/bin/python3\nimport sys\n" + script)
    copy.chmod(0o755)
    monkeypatch.setenv("PATH", str(copy.parent))
    assert ros2_shim._real_ros2() is None
    copy.write_text('#!/bin/sh\necho real ros2: "$@"\n')
    assert ros2_shim._real_ros2() == str(copy)
