"""Every way a user can go wrong on the command line or at a node's start-up ends in one line that
names the problem (and the flag or parameter as the user wrote it), with exit status 2 (CLI) or 1
(node); no traceback, no usage block, no Python-warnings prefix."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from ros_tester import fresh_domain

pytestmark = pytest.mark.slow  # each test runs the command line in a new Python process

ROOT = Path(__file__).resolve().parents[1]
BAG = str(ROOT / "bags" / "lorenz96.mcap")
SPEC = str(ROOT / "examples" / "robot_spec.yaml")
CLI = [sys.executable, "-m", "neural_estimator.cli"]

# (arguments, text the one line must contain); {tmp} is a fresh directory, {bag} a sample bag
CLI_CASES = [
    (["evalute", "--scenario", "lorenz96"], "did you mean 'evaluate'?"),
    (
        ["evaluate", "--scenario", "lorenz96", "--methds", "ukf"],
        "unrecognized option --methds (did you mean '--methods'?)",
    ),
    (["evaluate", "--scenario", "lorenz96", "--methods", "ukff"], "unknown method 'ukff' (did you mean 'ukf'?)"),
    (
        ["evaluate", "--scenario", "lorenz69", "--methods", "ukf"],
        "unknown scenario 'lorenz69' (did you mean 'lorenz96'?)",
    ),
    (
        ["evaluate", "--scenario", "lorenz96", "--methods", "ukf", "--option", "ukf.alpah=1"],
        "unknown option(s) alpah (did you mean 'alpha'?)",
    ),
    (
        ["evaluate", "--scenario", "lorenz96", "--methods", "ukf", "--set", "forcng=8"],
        "no constant 'forcng' (did you mean 'forcing'?)",
    ),
    (
        ["evaluate", "--scenario", "lorenz96", "--methods", "ukf", "--horizon", "5", "--no-cache"],
        "--horizon 5 leaves no step to score after --warmup 10",
    ),
    (["evaluate", "--scenario", "lorenz96", "--methods", "ukf", "--horizon", "0"], "--horizon must be >= 1"),
    (["replay", "{bag}", "--methods", "ukf", "--out", "{bag}"], "file exists; pass --overwrite to replace it"),
    (["recover", "{bag}", "--out", "{bag}"], "it cannot overwrite its input"),
    (["metrics", "{tmp}/missing.npz"], "missing.npz: no such file"),
    (["metrics", "{tmp}/truncated.mcap"], "no /observation or /ground_truth topic"),
    (["replay", "{bag}", "--methods", "ukf", "--out", "{tmp}/o.mcap", "--threads", "-1"], "--threads must be >= 0"),
    (["train", "--scenario", "lorenz96", "--model", "ukf", "--out", "{tmp}/m"], "--model must be a trainable method"),
    (["dataset", "{tmp}/missing_bag", "--spec", SPEC, "--out", "{tmp}/d.npz"], "missing_bag"),
    (["simulate", "--scenario", "lorenz96", "--out", "{tmp}/x.npz", "--trajectories", "0"], "must be >= 1"),
    (["live", "--scenario", "lorenz96", "--methods", "ukff"], "unknown method 'ukff' (did you mean 'ukf'?)"),
    (["live", "--scenario", "lorenz96", "--methods", "ukf", "--rate-hz", "x"], "invalid float value: 'x'"),
    (
        ["live", "--scenario", "lorenz96", "--methods", "ukf", "--realtime-priority", "100"],
        "--realtime-priority must be from 0 (off) to 99, got 100",
    ),
    (["reproduce", "--scale", "smal"], "did you mean 'small'?"),
]


def _fill(args, tmp):
    return [a.format(tmp=tmp, bag=BAG) for a in args]


@pytest.fixture(scope="module")
def tmp(tmp_path_factory):
    d = tmp_path_factory.mktemp("bad")
    (d / "truncated.mcap").write_bytes(Path(BAG).read_bytes()[:30000])  # a recorder killed mid-chunk
    return d


@pytest.mark.parametrize("args, text", CLI_CASES, ids=[" ".join(a[:3]) for a, _ in CLI_CASES])
def test_cli_bad_invocation_is_one_line_and_status_2(args, text, tmp):
    res = subprocess.run(CLI + _fill(args, tmp), capture_output=True, text=True, timeout=300, cwd=tmp)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    errors = [ln for ln in lines if ": error: " in ln]
    assert res.returncode == 2, res.stderr
    assert len(errors) == 1 and text in errors[0], res.stderr
    # besides the error, at most the package's own one-line warnings (a truncated bag's damage report)
    assert all(ln.startswith("neural-estimator") for ln in lines), res.stderr
    assert "Traceback" not in res.stderr and "usage:" not in res.stderr and ".py:" not in res.stderr


def test_truncated_bag_warning_has_no_python_warnings_prefix(tmp):
    res = subprocess.run(CLI + ["metrics", str(tmp / "truncated.mcap")], capture_output=True, text=True, timeout=120)
    warning = [ln for ln in res.stderr.splitlines() if "damaged or unfinished bag" in ln]
    assert len(warning) == 1 and warning[0].startswith("neural-estimator: warning: "), res.stderr
    assert "BagWarning" not in res.stderr and "warnings.warn" not in res.stderr


# (node, parameters, text the one fatal line must contain)
NODE_CASES = [
    ("estimator", ["method:=ukff"], "unknown method 'ukff' (did you mean 'ukf'?)"),
    ("estimator", ["method:=ukf", "scenario:=lorenz96", "options:=[alpah=1]"], "did you mean 'alpha'?"),
    ("simulator", ["scenario:=lorenz69"], "unknown scenario 'lorenz69' (did you mean 'lorenz96'?)"),
    ("evaluator", ["spec:={tmp}/no_spec.yaml", "output:={tmp}/e.mcap"], "no_spec.yaml"),
    ("evaluator", ["spec:=" + SPEC, "spec_length:=1", "output:={tmp}/e.mcap"], "spec_length must be at least 2"),
    ("evaluator", ["output:={bag}"], "file exists; pass -p overwrite:=true to replace it"),
    ("evaluator", ["record_period:=0.0", "output:={tmp}/e.mcap"], "record_period must be in (0, 1] seconds"),
    ("player", ["bag:={tmp}/missing.mcap"], "missing.mcap"),
    ("robot_estimator", ["checkpoint:={tmp}/missing"], "missing"),
]


@pytest.mark.ros
@pytest.mark.parametrize("node, params, text", NODE_CASES, ids=[f"{n} {p[0]}" for n, p, _ in NODE_CASES])
def test_node_bad_start_up_is_one_line_and_status_1(node, params, text, tmp):
    pytest.importorskip("rclpy")

    from neural_estimator.nodes.launch import isolated_env

    cmd = [sys.executable, "-m", "neural_estimator.nodes.entry", node, "--ros-args"]
    for p in _fill(params, tmp):
        cmd += ["-p", p]
    env = isolated_env(fresh_domain())
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=120, env=env, cwd=tmp)
    out = [ln for ln in (res.stdout + res.stderr).splitlines() if ln.strip()]
    fatal = [ln for ln in out if "FATAL" in ln or "error" in ln.lower()]
    assert res.returncode == 1, res.stdout + res.stderr
    assert len(fatal) == 1 and text in fatal[0], res.stdout + res.stderr
    assert "Traceback" not in res.stderr


def test_recorded_data_length_errors_name_the_setting_the_user_has(tmp):
    """Too long a trajectory for a recording: the CLI names --length, the evaluator node spec_length."""
    sys.path.insert(0, str(ROOT / "examples"))
    import robot_bag

    from neural_estimator.robot import SpecError, build_dataset, load_spec

    bag = robot_bag.write_bag(tmp / "robot_bag", runs=1, seconds=3.0, seed=2)
    spec = load_spec(SPEC)
    with pytest.raises(SpecError, match=r"pass a smaller --length"):
        build_dataset([bag], spec, 10_000)
    with pytest.raises(SpecError, match=r"pass a smaller spec_length \(-p spec_length:=N\)"):
        build_dataset([bag], spec, 10_000, length_name="spec_length (-p spec_length:=N)")
    res = subprocess.run(
        CLI + ["dataset", str(bag), "--spec", SPEC, "--length", "10000", "--out", str(tmp / "d.npz")],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert res.returncode == 2 and "pass a smaller --length" in res.stderr, res.stderr


def test_progress_bars_only_on_terminals(tmp):
    """evaluate's progress bar draws on a terminal and stays out of pipes and logs."""
    import os
    import pty

    argv = CLI + ["evaluate", "--scenario", "lorenz96", "--methods", "ukf", "--trajectories", "2", "--sets", "1"]
    argv += ["--horizon", "200", "--no-cache"]
    piped = subprocess.run(argv, capture_output=True, text=True, timeout=300, cwd=tmp)
    assert piped.returncode == 0, piped.stderr
    assert "\r" not in piped.stderr and "traj-step" not in piped.stderr, piped.stderr
    import fcntl
    import struct
    import termios

    leader, follower = pty.openpty()
    fcntl.ioctl(follower, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 100, 0, 0))  # a 100-column terminal
    try:
        proc = subprocess.run(argv, stdout=subprocess.DEVNULL, stderr=follower, timeout=300, cwd=tmp)
        os.close(follower)
        chunks = []
        while True:
            try:
                data = os.read(leader, 65536)
            except OSError:
                break
            if not data:
                break
            chunks.append(data)
    finally:
        os.close(leader)
    assert proc.returncode == 0
    assert b"traj-step" in b"".join(chunks)


def test_reproduce_without_ray_names_the_extra_to_install(tmp):
    fake = tmp / "no_ray"
    (fake / "ray").mkdir(parents=True, exist_ok=True)
    (fake / "ray" / "__init__.py").write_text("raise ImportError('no ray here')\n")
    import os

    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(fake), os.environ.get("PYTHONPATH", "")]))
    res = subprocess.run(
        CLI + ["reproduce", "--scale", "smoke", "--out", str(tmp / "rp")], capture_output=True, text=True, env=env
    )
    assert res.returncode == 2 and res.stderr.count("\n") == 1, res.stderr
    assert "pip install 'neural_estimator[reproduce]'" in res.stderr


@pytest.mark.ros
def test_node_with_a_bad_realtime_priority_is_one_line_and_status_1(tmp):
    pytest.importorskip("rclpy")

    from neural_estimator.nodes.launch import isolated_env

    env = isolated_env(fresh_domain())
    env["NEURAL_ESTIMATOR_REALTIME_PRIORITY"] = "high"
    cmd = [sys.executable, "-m", "neural_estimator.nodes.entry", "estimator", "--ros-args", "-p", "method:=ukf"]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=120, env=env, cwd=tmp)
    fatal = [ln for ln in (res.stdout + res.stderr).splitlines() if "FATAL" in ln]
    assert res.returncode == 1, res.stdout + res.stderr
    assert len(fatal) == 1 and "NEURAL_ESTIMATOR_REALTIME_PRIORITY must be an integer from 1 to 99" in fatal[0]
    assert "Traceback" not in res.stderr
