"""Your own robot: spec -> dataset from bags written by rosbags -> train / evaluate / metrics, no scenario."""

from __future__ import annotations

import math
import time
import sys
from pathlib import Path

import numpy as np
import pytest

from neural_estimator.cli import main
from neural_estimator.data import load_trajectories
from neural_estimator.robot import DataScenario, SpecError, build_dataset, load_spec
from neural_estimator.robot.dataset import sample, segments
from neural_estimator.robot.spec import euler

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "examples"))
import robot_bag  # noqa: E402
from ros_tester import fresh_domain  # noqa: E402

SPEC = ROOT / "examples" / "robot_spec.yaml"


@pytest.fixture(scope="module")
def bag(tmp_path_factory) -> Path:
    """Three 25-second runs of the example robot, written by rosbags (rosbag2 directory, MCAP storage)."""
    return robot_bag.write_bag(tmp_path_factory.mktemp("robot") / "bag", runs=3, seconds=25.0, seed=1)


def train_tiny(data: Path, out: Path, *extra: str) -> None:
    """A GRU trained for one epoch of 16 windows on a recorded dataset (the verbs' plumbing, not accuracy)."""
    args = ["train", "--data", str(data), "--model", "gru", "--out", str(out), "--epochs", "1"]
    assert main(args + ["--windows-per-epoch", "16", "--window", "20", "--warmup", "2", "--quiet", *extra]) == 0


def spec_dict(**changes):
    import yaml

    raw = yaml.safe_load(SPEC.read_text())
    raw.update(changes)
    return {k: v for k, v in raw.items() if v is not None}  # None: leave the key out


# ---- the spec ---------------------------------------------------------------------------------------
def test_example_spec_parses_with_angles_names_and_units():
    s = load_spec(SPEC)
    assert [f.expr for f in s.vectors["state"]] == ["pose.position.x", "pose.position.y", "yaw(pose.orientation)"]
    assert s.angles("state") == (2,) and s.angles("observation") == ()
    assert s.names["state"] == ("x", "y", "yaw") and s.units["observation"][0] == "rad/s"
    assert s.topics == ("/imu", "/wheel_odom", "/gps/fix", "/mocap/pose", "/odometry/filtered")
    assert s.estimates == ("robot_filter",) and s.dt == pytest.approx(0.1)
    assert len(s.digest()) == 64 and s.digest() != load_spec(spec_dict(rate=20.0)).digest()


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"rates": 10}, "unknown key"),
        ({"rate": -1}, "rate must be a positive number"),
        ({"state": None}, "missing 'state'"),
        ({"state": {"/mocap/pose": ["pose.position..x"]}}, "is not a field path"),
        ({"state": {"/mocap/pose": ["heading(pose.orientation)"]}}, "unknown conversion 'heading'"),
        ({"state": {"mocap pose": ["pose.position.x"]}}, "is not a topic name"),
        ({"names": {"state": ["x"]}}, "names.state must list 3 strings"),
        ({"estimates": {"ekf": {"/odometry/filtered": ["pose.pose.position.x"]}}}, "one per state component"),
        ({"estimates": {"my ekf": {"/odometry/filtered": ["pose.pose.position.x"]}}}, "estimates must map names"),
        ({"stamp": "receive"}, "stamp must be one of"),
    ],
)
def test_bad_specs_are_refused_in_one_line(changes, message):
    with pytest.raises(SpecError, match=message) as err:
        load_spec(spec_dict(**changes))
    assert "\n" not in str(err.value)


def test_euler_angles_of_quaternions():
    for yaw in (-3.0, -0.5, 0.0, 1.2, math.pi):
        assert euler(0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))[2] == pytest.approx(
            math.atan2(math.sin(yaw), math.cos(yaw))
        )
    roll, pitch, yaw = euler(math.sin(0.15), 0.0, 0.0, math.cos(0.15))  # 0.3 rad about x
    assert (roll, pitch, yaw) == pytest.approx((0.3, 0.0, 0.0))
    assert all(math.isnan(v) for v in euler(0.0, 0.0, 0.0, 0.0))  # zero quaternion: dropped as non-finite


# ---- alignment ----------------------------------------------------------------------------------------
def test_latest_value_alignment_with_staleness_and_nonfinite_ticks():
    s = load_spec({"rate": 10, "max_age": 0.15, "observation": {"/a": ["v"]}, "state": {"/b": ["v"]}})
    ms = 1_000_000
    streams = {
        "/a": (np.array([0, 100, 200, 300, 400, 500]) * ms, np.array([[0.0], [1], [2], [3], [np.nan], [5]])),
        "/b": (np.array([0, 50, 100, 150, 500]) * ms, np.array([[10.0], [11], [12], [13], [15]])),
    }
    ticks = np.arange(6) * 100 * ms
    vectors, stale, nonfinite, labelled = sample(streams, s, ticks)
    np.testing.assert_array_equal(vectors["observation"][:, 0][:4], [0, 1, 2, 3])
    np.testing.assert_array_equal(vectors["state"][:, 0][:3], [10, 12, 13])  # latest at or before each tick
    # the truth /b's last message before t = 400 ms is 250 ms old: unlabelled, not dropped (partial
    # ground truth; at 300 ms it is 150 ms old, within max_age); the input /a is NaN at 400 ms: dropped
    np.testing.assert_array_equal(labelled, [True, True, True, True, False, True])
    np.testing.assert_array_equal(stale, [False] * 6)
    np.testing.assert_array_equal(nonfinite, [False, False, False, False, True, False])
    assert segments(~stale & ~nonfinite) == [(0, 4), (5, 6)]
    # an input going silent is stale: /a ending at 300 ms leaves t = 500 ms with a message 200 ms old
    late = {"/a": (streams["/a"][0][:4], streams["/a"][1][:4]), "/b": streams["/b"]}
    _, stale, _, _ = sample(late, s, ticks)
    np.testing.assert_array_equal(stale, [False] * 5 + [True])


# ---- bags -> dataset ------------------------------------------------------------------------------------
@pytest.mark.slow
def test_dataset_from_a_rosbags_recording(bag):
    spec = load_spec(SPEC)
    data, estimates, summaries = build_dataset([bag], spec, length=50)
    (summary,) = summaries
    assert summary.segments == 3  # one per run: the 2-second gaps are stale ticks
    assert summary.stale >= 2 * 19 and summary.nonfinite == 0
    assert data.x.shape[1:] == (50, 3) and data.y.shape[1:] == (50, 5) and data.u.shape[1:] == (50, 0)
    # every tick accounted for: stale, non-finite, in a trajectory, or a segment's remainder
    assert summary.ticks == summary.stale + summary.nonfinite + 50 * data.n + summary.remainder
    assert data.n == summary.trajectories >= 3 * 4 and summary.remainder < 3 * 50
    assert data.meta["angle_states"] == [2] and data.meta["scenario"] == "data"
    assert data.meta["sources"][0]["sha256"] == summary.sha256 and len(summary.sha256) == 64
    assert set(estimates) == {"robot_filter"} and estimates["robot_filter"].shape == data.x.shape
    assert np.all(np.abs(data.x[..., 2]) <= math.pi)
    # the GPS observation is the true position plus noise of 0.5 m (up to the staleness of a fix)
    err = data.y[..., 3:5] - data.x[..., :2]
    assert 0.3 < err.std() < 0.8
    # the same recording through its .mcap file directly gives the same data
    again, _, _ = build_dataset(sorted(bag.glob("*.mcap")), spec, length=50)
    np.testing.assert_array_equal(again.x, data.x)


@pytest.mark.slow
def test_dataset_errors_name_the_topic_or_field(bag):
    with pytest.raises(SpecError, match=r"no topic /lidar in this bag \(it has: .*/imu"):
        build_dataset(
            [bag], load_spec(spec_dict(observation={"/lidar": ["ranges[0]"]}, names=None, units=None)), length=50
        )
    with pytest.raises(SpecError, match=r"no field 'angular_velocty' .*fields there: .*angular_velocity"):
        build_dataset(
            [bag], load_spec(spec_dict(observation={"/imu": ["angular_velocty.z"]}, names=None, units=None)), length=50
        )
    with pytest.raises(SpecError, match="longest run of valid ticks is"):
        build_dataset([bag], load_spec(SPEC), length=5000)


@pytest.mark.slow
def test_data_scenario_has_no_model_and_refuses_classical_filters(bag):
    from neural_estimator.methods.registry import EstimatorError, make_estimator

    data, _, _ = build_dataset([bag], load_spec(SPEC), length=50)
    s = DataScenario(data.meta)
    assert (s.dx, s.dy, s.du, s.angle_states, s.dt) == (3, 5, 0, (2,), pytest.approx(0.1))
    with pytest.raises((EstimatorError, ValueError), match="no .*a classical filter needs the system's equations"):
        make_estimator("ekf", s)


# ---- the verbs ------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_dataset_train_evaluate_metrics_from_a_recording(bag, tmp_path, capsys):
    spec = tmp_path / "spec.yaml"
    import yaml

    spec.write_text(yaml.safe_dump(spec_dict()))
    data = tmp_path / "data.npz"
    assert main(["dataset", str(bag), "--spec", str(spec), "--length", "50", "--out", str(data)]) == 0
    assert (tmp_path / "data.robot_filter.npz").is_file()
    out = tmp_path / "gru"
    train_tiny(data, out)
    import json

    card = json.loads((out / "card.json").read_text())
    assert card["scenario"]["scenario"] == "data" and card["data"]["source"] == "recorded"
    assert card["metrics"]["set"]["role"] == "val (recorded)"
    capsys.readouterr()
    assert (
        main(
            [
                "evaluate",
                "--data",
                str(data),
                "--checkpoint",
                f"gru={out}",
                "--estimate",
                f"robot_filter={tmp_path / 'data.robot_filter.npz'}",
                "--quiet",
            ]
        )
        == 0
    )
    table = capsys.readouterr().out
    assert "gru " in table and "robot_filter " in table
    assert main(["metrics", str(data), str(tmp_path / "data.robot_filter.npz")]) == 0
    # the robot-data model learns a covariance too: a head fitted on recorded trajectories
    # (here the same file twice: the plumbing, not a held-out calibration)
    import importlib.util

    spec_ = importlib.util.spec_from_file_location("fit_heads", ROOT / "scripts" / "fit_covariance_heads.py")
    fit_heads = importlib.util.module_from_spec(spec_)
    spec_.loader.exec_module(fit_heads)
    fit = ["--checkpoint", str(out), "--data", str(data), "--calibration-data", str(data), "--steps", "20"]
    assert fit_heads.main(fit) == 0
    assert json.loads((out / "card.json").read_text())["covariance_head"]["fitted_on"]["head"]["recorded"] > 0
    # step.onnx was exported anew with the head: the nodes' default serves its covariance, equal to torch's
    from neural_estimator.serving.load import load_neural_estimator

    recorded, _ = load_trajectories(data)
    served = load_neural_estimator("gru", DataScenario(recorded.meta), out, backend="auto")
    ref = load_neural_estimator("gru", DataScenario(recorded.meta), out)
    assert type(served).__name__ == "OnnxEstimator" and served.has_covariance
    served.reset(1)
    ref.reset(1)
    y0, u0 = recorded.y[0, :1], np.zeros((1, recorded.u.shape[-1]))
    np.testing.assert_allclose(served.step(y0, u0), ref.step(y0, u0), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(served.covariance, ref.covariance, rtol=1e-4, atol=1e-5 * np.abs(ref.covariance).max())
    capsys.readouterr()
    assert main(["evaluate", "--data", str(data), "--checkpoint", f"gru={out}", "--quiet"]) == 0
    assert "Verdict" in capsys.readouterr().out  # the model now reports a covariance
    # a checkpoint of another spec (another rate) is refused; a classical filter too; --scenario with --data too
    other = tmp_path / "other.npz"
    spec.write_text(yaml.safe_dump(spec_dict(rate=5.0)))
    assert main(["dataset", str(bag), "--spec", str(spec), "--length", "20", "--out", str(other), "--quiet"]) == 0
    capsys.readouterr()
    assert main(["evaluate", "--data", str(other), "--checkpoint", f"gru={out}", "--quiet"]) == 2
    assert "spec_sha256" in capsys.readouterr().err
    assert main(["evaluate", "--data", str(data), "--methods", "ekf", "--quiet"]) == 2
    assert "classical filter" in capsys.readouterr().err
    assert (
        main(["train", "--data", str(data), "--scenario", "lorenz96", "--model", "gru", "--out", str(tmp_path / "x")])
        == 2
    )
    assert "drop --scenario" in capsys.readouterr().err


def test_simulated_dataset_is_not_taken_as_recorded(tmp_path, capsys):
    sim = tmp_path / "sim.npz"
    assert (
        main(["simulate", "--scenario", "bearings", "--trajectories", "2", "--horizon", "30", "--out", str(sim)]) == 0
    )
    capsys.readouterr()
    assert main(["evaluate", "--data", str(sim), "--checkpoint", "gru=x", "--quiet"]) == 2
    assert "not a recorded dataset" in capsys.readouterr().err
    data, _ = load_trajectories(sim)
    assert data.meta["scenario"] == "bearings"


# ---- served live ------------------------------------------------------------------------------------------
@pytest.mark.ros
@pytest.mark.slow
def test_served_live_the_model_scores_what_evaluate_scored_on_the_recordings_clock(tmp_path, capsys):
    """The documented chain, default parameters: player (the robot's own bag, standard messages) ->
    estimator (a `train --data` model: the robot estimator) -> evaluator (records /mocap/pose and the
    estimates, scores them through the spec). Its RMSE is within 5 % of `evaluate` on the
    recording's dataset (it was 2.6-3.7x worse when the node ticked on its steady clock and never
    restarted the model), and every estimate is stamped with its tick on the recording's clock, so
    a pose tool pairs it with the ground truth message of the same stamp."""
    pytest.importorskip("rclpy")
    import json

    from neural_estimator.bags import BagReader
    from neural_estimator.stream import messages as MSG
    from neural_estimator.nodes.launch import ESTIMATOR, EVALUATOR, isolated_env, node_command, start_node

    bag = robot_bag.write_bag(tmp_path / "bag", runs=2, seconds=42.0, seed=3)
    data = tmp_path / "data.npz"
    assert main(["dataset", str(bag), "--spec", str(SPEC), "--length", "200", "--out", str(data), "--quiet"]) == 0
    model = tmp_path / "gru"
    train_tiny(data, model, "--val-fraction", "0.25")
    capsys.readouterr()
    assert main(["evaluate", "--data", str(data), "--checkpoint", f"gru={model}", "--json", "--quiet"]) == 0
    offline = json.loads(capsys.readouterr().out)["methods"]["gru"]["summary"]["rmse"]["median"]
    env = isolated_env(fresh_domain())
    rec = tmp_path / "live.mcap"
    procs = []
    try:
        for module, name, params in (
            (EVALUATOR, "rec", dict(output=str(rec), idle_timeout=3.0, topics=["/mocap/pose"], spec=str(SPEC))),
            (ESTIMATOR, "est", dict(checkpoint=str(model))),
            (
                "neural_estimator.nodes.player_node",
                "player",
                dict(bag=str(bag), rate=4.0, wait_for_subscribers=1, wait_topic="/imu"),  # 4x: the test's time
            ),
        ):
            procs.append(start_node(node_command(sys.executable, module, name, params), tmp_path / f"{name}.log", env))
        assert procs[0].wait(timeout=180) == 0, "".join(
            (tmp_path / f"{n}.log").read_text() for n in ("rec", "est", "player")
        )
    finally:
        import signal

        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for p in procs:
            try:
                p.wait(timeout=5)
            except Exception:
                p.kill()
    log = (tmp_path / "est.log").read_text()
    assert "subscribed to '/gps/fix' (geometry_msgs/msg/PointStamped)" in log, log
    assert "trajectories x 200 steps" in (tmp_path / "rec.log").read_text()
    from neural_estimator.robot.score import score_recording

    reports, truth = score_recording(rec, SPEC, length=200)
    live = reports["gru"].rmse
    print(f"gru: evaluate RMSE {offline:.4f}, live {live:.4f} ({truth.n} trajectories)")
    assert truth.n == 4 and abs(live - offline) <= 0.05 * offline, (offline, live)
    written = json.loads(rec.with_suffix(".metrics.json").read_text())  # the evaluator's own scoring
    assert written["trajectories"] == 4 and written["methods"]["gru"]["rmse"] == pytest.approx(live)
    # the estimates' stamps are the recording's ticks; each has a ground-truth message of the same stamp
    with BagReader(rec) as reader:
        first = None
        types = {"/estimates/gru": "sensor_msgs/msg/JointState", "/mocap/pose": "geometry_msgs/msg/PoseStamped"}
        stamps = {topic: [] for topic in types}
        for conn, _, raw in reader.messages(list(stamps)):
            msg = MSG.TYPESTORE.deserialize_cdr(raw, types[conn.topic])
            stamps[conn.topic].append(msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec)
            if first is None and conn.topic == "/estimates/gru":
                first = msg
    assert list(first.name) == ["x", "y", "yaw"]
    est = np.array(stamps["/estimates/gru"])
    assert len(est) >= 4 * 200 and np.all(est % 100_000_000 == 0) and est.min() >= 1_700_000_000 * 10**9
    truth = np.sort(stamps["/mocap/pose"])
    nearest = np.minimum(
        np.abs(est - truth[np.clip(np.searchsorted(truth, est), 0, truth.size - 1)]),
        np.abs(est - truth[np.clip(np.searchsorted(truth, est) - 1, 0, truth.size - 1)]),
    )
    assert nearest.max() <= 10_000_000  # evo's association (max_diff 0.01 s by default) pairs every estimate
    assert main(["metrics", str(rec), "--spec", str(SPEC)]) == 0


@pytest.mark.parametrize(
    "checkpoint, text",
    [
        ("", "parameter checkpoint is required"),
        ("/nonexistent/model", "does not exist"),
        (str(ROOT / "neural_estimator" / "serving" / "zoo" / "lorenz96-gru"), "not on recorded data with a spec"),
    ],
)
@pytest.mark.ros
def test_robot_estimator_refuses_to_start(checkpoint, text, tmp_path):
    pytest.importorskip("rclpy")
    import subprocess

    from neural_estimator.nodes.launch import isolated_env, node_command

    env = isolated_env(fresh_domain())
    cmd = node_command(sys.executable, "neural_estimator.nodes.robot_estimator_node", "est", {"checkpoint": checkpoint})
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1 and text in proc.stderr + proc.stdout, proc.stderr + proc.stdout


@pytest.mark.ros
def test_the_estimator_node_serves_a_recorded_data_checkpoint_without_a_scenario(tmp_path):
    """`ros2 run neural_estimator estimator -p checkpoint:=DIR` with a `train --data` model starts the
    robot estimator on the spec's topics (no scenario parameter, no scenario topic needed)."""
    pytest.importorskip("rclpy")
    import signal

    from neural_estimator.nodes.launch import ESTIMATOR, isolated_env, node_command, start_node

    bag = robot_bag.write_bag(tmp_path / "bag", runs=1, seconds=8.0, seed=4)
    data = tmp_path / "data.npz"
    assert main(["dataset", str(bag), "--spec", str(SPEC), "--length", "30", "--out", str(data), "--quiet"]) == 0
    model = tmp_path / "gru"
    train_tiny(data, model, "--val-fraction", "0.5")
    env = isolated_env(fresh_domain())
    log = tmp_path / "est.log"
    proc = start_node(node_command(sys.executable, ESTIMATOR, "est", {"checkpoint": str(model)}), log, env)
    try:
        deadline = time.monotonic() + 60
        while "recorded-data spec" not in log.read_text() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.2)
        assert "recorded-data spec" in log.read_text(), log.read_text()
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=10)
    wrong = node_command(sys.executable, ESTIMATOR, "est", {"checkpoint": str(model), "method": "mamba"})
    import subprocess

    out = subprocess.run(wrong, env=env, capture_output=True, text=True, timeout=60)
    assert out.returncode == 1 and "holds a gru model" in out.stderr + out.stdout


# ---- bounds on what a spec can make this package allocate ----------------------------------------------------
def test_yaml_aliases_in_a_spec_are_refused_before_expansion(tmp_path):
    """Nested aliases amplified a 51 KB spec to 1.74 GB; now any alias is one line, read in linear time."""
    lines = ["a0: &a0 [x, x, x, x, x, x, x, x, x, x]"]
    lines += [f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 10)}]" for i in range(1, 9)]
    bomb = tmp_path / "bomb.yaml"
    bomb.write_text(SPEC.read_text() + "\n" + "\n".join(lines) + "\n")
    with pytest.raises(SpecError, match=r"YAML aliases \(\*name\) are not allowed in a spec"):
        load_spec(bomb)


@pytest.mark.slow
def test_a_rate_of_a_megahertz_is_refused(bag):
    """``rate: 1e6`` took 5.2 GB, then a MemoryError traceback."""
    with pytest.raises(SpecError, match="rate 1e\\+06 Hz is over the bound of 10000 Hz"):
        load_spec(spec_dict(rate=1e6))
    spec = load_spec(spec_dict(rate=9000.0))  # under the rate bound; the samples are bounded as well
    import neural_estimator.robot.dataset as D

    bound = D.MAX_TICKS
    try:
        D.MAX_TICKS = 1000
        with pytest.raises(SpecError, match="over the bound of 1000 \\(MAX_TICKS\\)"):
            build_dataset([bag], spec, length=50)
    finally:
        D.MAX_TICKS = bound


# ---- every rosbag2 storage ------------------------------------------------------------------------------------
@pytest.mark.slow
def test_a_sqlite3_copy_of_the_recording_gives_the_same_dataset(bag, tmp_path, capsys):
    """The same runs written with rosbag2's sqlite3 storage (a directory, and its lone .db3 file) give
    the dataset of the MCAP recording; `metrics` and the player's reader take it too."""
    from neural_estimator.bags import open_bag

    sqlite = robot_bag.write_bag(tmp_path / "sqlite", runs=3, seconds=25.0, seed=1, storage="sqlite3")
    (db3,) = sorted(sqlite.glob("*.db3"))
    spec = load_spec(SPEC)
    mcap, est_mcap, _ = build_dataset([bag], spec, length=50)
    for source in (sqlite, db3):
        data, est, _ = build_dataset([source], spec, length=50)
        np.testing.assert_array_equal(data.x, mcap.x)
        np.testing.assert_array_equal(data.y, mcap.y)
        np.testing.assert_array_equal(est["robot_filter"], est_mcap["robot_filter"])
    with open_bag(sqlite) as a, open_bag(bag) as b:
        assert {t: c.msgcount for t, c in a.topics.items()} == {t: c.msgcount for t, c in b.topics.items()}
        assert [t for _, t, _ in a.messages(["/gps/fix"])] == [t for _, t, _ in b.messages(["/gps/fix"])]
    out = tmp_path / "data.npz"
    assert main(["dataset", str(db3), "--spec", str(SPEC), "--length", "50", "--out", str(out), "--quiet"]) == 0
    # a file that is not a database: one line naming it
    bad = tmp_path / "broken.db3"
    bad.write_bytes(b"not sqlite at all" * 100)
    capsys.readouterr()
    assert main(["dataset", str(bad), "--spec", str(SPEC), "--length", "50", "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "broken.db3: not a readable rosbag2 sqlite3 database" in err and "Traceback" not in err
