"""The node executables as commands: ``--help`` prints the parameters without starting the node, a
misspelt parameter is one warning with "did you mean", and a node stopped while it starts (Ctrl-C
or SIGTERM while a model loads) exits 0 without a traceback."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from ros_tester import fresh_domain

pytestmark = pytest.mark.ros
ROOT = Path(__file__).resolve().parents[1]
NODES = ("simulator", "estimator", "evaluator", "player", "robot_estimator", "lifecycle_estimator")


@pytest.mark.slow
@pytest.mark.parametrize("node", NODES)
def test_help_prints_every_parameter_and_starts_nothing(node):
    pytest.importorskip("rclpy")
    from neural_estimator.nodes.entry import NODES as MODULES
    from neural_estimator.nodes.entry import parameter_fields

    env = dict(os.environ, PYTHONPATH=str(ROOT))
    out = subprocess.run(
        [sys.executable, "-m", MODULES[node], "--help"], capture_output=True, text=True, timeout=120, env=env
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith(f"usage: ros2 run neural_estimator {node} --ros-args")
    for f in parameter_fields(node):
        assert f"\n  {f.name} (" in out.stdout, f.name
    assert "[INFO]" not in out.stdout + out.stderr  # no node came up


@pytest.mark.parametrize("node", NODES)
def test_the_shipped_params_files_hold_only_known_parameters(node):
    pytest.importorskip("rclpy")
    from neural_estimator.nodes.entry import unknown_parameters

    path = ROOT / "params" / f"{'estimator' if node == 'lifecycle_estimator' else node}.yaml"
    assert unknown_parameters(node, ["--ros-args", "--params-file", str(path)]) == []


def test_a_misspelt_parameter_is_one_warning_with_the_closest_name(tmp_path):
    pytest.importorskip("rclpy")
    from neural_estimator.nodes.entry import unknown_parameters

    args = ["--ros-args", "-r", "__node:=est", "-p", "methd:=ukf", "-p", "method:=ukf", "-p", "use_sim_time:=true"]
    assert unknown_parameters("estimator", args) == ["unknown parameter 'methd' (ignored); did you mean 'method'?"]
    params = tmp_path / "p.yaml"
    params.write_text("est:\n  ros__parameters:\n    rate_hzz: 3\nother:\n  ros__parameters:\n    zzz: 1\n")
    got = unknown_parameters("simulator", ["--ros-args", "-r", "__node:=est", "--params-file", str(params)])
    assert got == ["unknown parameter 'rate_hzz' (ignored); did you mean 'rate_hz'?"]  # not the other node's
    assert unknown_parameters("player", ["--ros-args", "-p", "qqqq:=1"]) == ["unknown parameter 'qqqq' (ignored)"]


def test_run_node_stops_cleanly_when_interrupted_during_start_up(monkeypatch):
    pytest.importorskip("rclpy")
    import rclpy
    from rclpy._rclpy_pybind11 import RCLError
    from rclpy.node import Node

    from neural_estimator.nodes.common import run_node

    monkeypatch.setenv("ROS_DOMAIN_ID", str(fresh_domain()))
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

    def interrupted():  # Ctrl-C while loading: KeyboardInterrupt out of the node's constructor
        raise KeyboardInterrupt

    assert run_node(interrupted, "x", []) == 0

    def terminated():  # SIGTERM while loading: rclpy shut the context down, the next publisher fails
        from std_msgs.msg import String

        node = Node("x")
        rclpy.shutdown()
        node.create_publisher(String, "y", 1)
        return node

    assert run_node(terminated, "x", []) == 0
    assert not rclpy.ok()

    def broken():  # a real error while the context is valid is not hidden
        raise RCLError("boom")

    with pytest.raises(RCLError, match="boom"):
        run_node(broken, "x", [])
    rclpy.try_shutdown()


@pytest.fixture(scope="module")
def recorded_gru(tmp_path_factory) -> Path:
    """A GRU trained (one short epoch) on a recorded-data set from the example robot bag: the checkpoint
    the robot estimator loads. Built once for both signals (the node only reads it)."""
    pytest.importorskip("rclpy")
    from neural_estimator.cli import main

    tmp_path = tmp_path_factory.mktemp("recorded_gru")
    sys.path.insert(0, str(ROOT / "examples"))
    import robot_bag

    bag = robot_bag.write_bag(tmp_path / "bag", runs=1, seconds=8.0, seed=4)
    data = tmp_path / "data.npz"
    spec = ROOT / "examples" / "robot_spec.yaml"
    assert main(["dataset", str(bag), "--spec", str(spec), "--length", "30", "--out", str(data), "--quiet"]) == 0
    model = tmp_path / "gru"
    args = ["train", "--data", str(data), "--model", "gru", "--out", str(model), "--epochs", "1", "--quiet"]
    assert main(args + ["--windows-per-epoch", "8", "--window", "10", "--warmup", "2", "--val-fraction", "0.5"]) == 0
    return model


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_the_robot_estimator_exits_0_on_a_signal_while_loading_and_while_running(sig, recorded_gru, tmp_path):
    """Signals at both times: during the model load (the node's log has not said it runs) and after."""
    pytest.importorskip("rclpy")
    from neural_estimator.nodes.launch import isolated_env, node_command

    model = recorded_gru
    env = isolated_env(fresh_domain())
    cmd = node_command(sys.executable, "neural_estimator.nodes.robot_estimator_node", "est", {"checkpoint": str(model)})
    for wait_for_start in (False, True):
        log = tmp_path / f"est-{wait_for_start}.log"
        with open(log, "w") as fh:
            proc = subprocess.Popen(cmd, env=env, stdout=fh, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 60
        # loading: once the node module is imported (rclpy is up), before the model is ready
        want = "recorded-data spec" if wait_for_start else None
        seen = False
        while not seen and time.monotonic() < deadline and proc.poll() is None:
            text = log.read_text()
            if want is None:
                seen = os.path.exists(f"/proc/{proc.pid}") and _loading_the_model(proc.pid)
            else:
                seen = want in text
            if not seen:
                time.sleep(0.02)
        # the moment looked for came (a node that never maps its backend would be signalled after the
        # deadline, once it runs, and the loading case would go untested)
        assert seen, f"{'running' if wait_for_start else 'loading'} not seen in 60 s; log: {log.read_text()}"
        proc.send_signal(sig)
        assert proc.wait(timeout=30) == 0, log.read_text()
        assert "Traceback" not in log.read_text() and "FATAL" not in log.read_text(), log.read_text()


def _loading_the_model(pid: int) -> bool:
    """Whether the process has mapped the library of its serving backend (it is loading the model):
    ONNX Runtime's (the default backend, without torch) or torch's."""
    try:
        maps = Path(f"/proc/{pid}/maps").read_text()
        return "onnxruntime" in maps or "libtorch" in maps
    except OSError:
        return False


def test_every_node_trims_its_heap_on_a_timer(monkeypatch):
    # run_node gives each node a steady-clock timer that calls malloc_trim (nodes/heap_trace.py):
    # without it a node's freed memory stayed resident and its RSS crept at 500 Hz
    pytest.importorskip("rclpy")
    from neural_estimator.nodes import common
    from neural_estimator.nodes.common import ExitStatusNode, request_shutdown, run_node
    from neural_estimator.nodes.heap_trace import DEFAULT_HEAP_TRIM_PERIOD, HEAP_TRIM_ENV

    pins = []  # and glibc's mmap and trim thresholds pinned (nodes/heap_trace.py pin_malloc_thresholds)
    monkeypatch.setattr(common, "pin_malloc_thresholds", lambda: pins.append(1) or True)

    monkeypatch.setenv("ROS_DOMAIN_ID", str(fresh_domain()))
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    seen = {}

    def node_with_a_look():
        node = ExitStatusNode("x")

        def look():  # from inside the spin: what run_node set up
            seen["trim"] = getattr(node, "heap_trim", None)
            seen["periods"] = sorted(t.timer_period_ns for t in node.timers)
            request_shutdown(node, 3)

        node.create_timer(0.05, look)
        return node

    monkeypatch.delenv(HEAP_TRIM_ENV, raising=False)
    assert run_node(node_with_a_look, "x", []) == 3
    assert seen["trim"] is not None and seen["trim"].period == DEFAULT_HEAP_TRIM_PERIOD
    assert seen["periods"] == [50_000_000, int(DEFAULT_HEAP_TRIM_PERIOD * 1e9)] and pins == [1]

    monkeypatch.setenv(HEAP_TRIM_ENV, "0")  # off: no timer
    assert run_node(node_with_a_look, "x", []) == 3
    assert seen["trim"] is None and seen["periods"] == [50_000_000] and pins == [1]  # nor a second pin

    built = []
    monkeypatch.setenv(HEAP_TRIM_ENV, "soon")  # one fatal line, exit status 1, no node built
    assert run_node(lambda: built.append(1), "x", []) == 1 and built == []
