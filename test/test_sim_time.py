"""The robot estimator on the player's /clock: a bag replayed at 4x scores as at 1x (the graph of
launch/robot_estimator.launch.py, started as `neural-estimator live` starts nodes)."""

from __future__ import annotations

import signal
import sys
from pathlib import Path

import numpy as np
import pytest

from neural_estimator.cli import main

ROOT = Path(__file__).resolve().parents[1]
SPEC = ROOT / "examples" / "robot_spec.yaml"
sys.path.insert(0, str(ROOT / "examples"))
import robot_bag  # noqa: E402
from ros_tester import fresh_domain  # noqa: E402

pytestmark = pytest.mark.ros  # every test here runs ROS 2 nodes


def _replay(bag: Path, model: Path, rate: float, out: Path, env) -> Path:
    from neural_estimator.nodes.graph import build, command
    from neural_estimator.nodes.launch import start_node

    rec = out / f"x{rate:g}.mcap"
    specs = build(
        "robot_estimator",
        {"checkpoint": str(model), "bag": str(bag), "rate": str(rate), "spec": str(SPEC), "output": str(rec)},
    )
    procs = {}
    try:
        for s in specs:
            procs[s.name] = start_node(command(sys.executable, s), out / f"{s.name}-x{rate:g}.log", env)
        code = procs["evaluator"].wait(timeout=180)
        logs = "".join((out / f"{n}-x{rate:g}.log").read_text() for n in procs)
        assert code == 0, logs
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for p in procs.values():
            try:
                p.wait(timeout=10)
            except Exception:
                p.kill()
    return rec


def test_a_bag_replayed_at_4x_scores_within_one_percent_of_1x(tmp_path):
    pytest.importorskip("rclpy")
    from neural_estimator.bags import BagReader
    from neural_estimator.nodes.launch import isolated_env
    from neural_estimator.robot.score import score_recording

    bag = robot_bag.write_bag(tmp_path / "bag", runs=2, seconds=12.0, seed=3)
    data = tmp_path / "data.npz"
    assert main(["dataset", str(bag), "--spec", str(SPEC), "--length", "40", "--out", str(data), "--quiet"]) == 0
    model = tmp_path / "gru"
    args = ["train", "--data", str(data), "--model", "gru", "--out", str(model), "--epochs", "1"]
    assert main(args + ["--windows-per-epoch", "16", "--window", "20", "--warmup", "2", "--quiet"]) == 0
    env = isolated_env(fresh_domain())
    scores, counts = {}, {}
    for rate in (1.0, 4.0):
        rec = _replay(bag, model, rate, tmp_path, env)
        reports, truth = score_recording(rec, SPEC, length=20, stamp="header")
        scores[rate] = reports["gru"].rmse
        with BagReader(rec) as reader:
            counts[rate] = reader.topics["/estimates/gru"].msgcount
        assert truth.n >= 4
    print(f"robot estimator on /clock: RMSE at 1x {scores[1.0]:.4f}, at 4x {scores[4.0]:.4f}; estimates {counts}")
    # 2 runs x 12 s at 10 Hz on the bag's clock, whatever the speed (a few ticks stale at each start)
    assert 200 <= counts[1.0] <= 240 and abs(counts[4.0] - counts[1.0]) <= 5, counts
    assert np.isfinite(scores[1.0]) and abs(scores[4.0] - scores[1.0]) <= 0.01 * scores[1.0], scores
