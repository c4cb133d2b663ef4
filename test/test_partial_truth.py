"""Partial ground truth: a recording whose truth has gaps (a robot outside the motion-capture volume)
gives a dataset with a ``labelled`` mask; training and scoring use the labelled steps only."""

from __future__ import annotations

import hashlib
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from neural_estimator import metrics as M
from neural_estimator.cli import main
from neural_estimator.data import load_trajectories
from neural_estimator.data.io import DataError, save_npz, save_trajectories
from neural_estimator.data.simulate import Trajectories
from neural_estimator.robot import build_dataset, load_spec

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "examples"))
import robot_bag  # noqa: E402

SPEC = ROOT / "examples" / "robot_spec.yaml"
RUNS, SECONDS, GAP, LENGTH = 2, 30.0, 6.0, 50


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    """The same two 30-second runs with and without a 6-second truth gap (same seed: same inputs)."""
    root = tmp_path_factory.mktemp("partial")
    full = robot_bag.write_bag(root / "full", RUNS, SECONDS, seed=3)
    gaps = robot_bag.write_bag(root / "gaps", RUNS, SECONDS, seed=3, truth_gaps=GAP)
    return full, gaps


def truth_coverage(bag: Path, spec, exact: bool = False) -> np.ndarray:
    """Which steps of the dataset have a /mocap/pose message at most max_age old (``exact``: one
    stamped at the tick itself), from the writer's own timing (runs SECONDS + 2 s apart from t0,
    truth at 100 Hz except in each run's gap): (N, T). The ticks and the trajectories are the
    builder's (its tick rule, tested elsewhere)."""
    from neural_estimator.robot.dataset import read_streams, sample, segments, tick_times

    streams, _ = read_streams(bag, spec)
    ticks = tick_times(streams, spec)
    _, stale, nonfinite, _ = sample(streams, spec, ticks)
    t0, run_ns = 1_700_000_000 * 10**9, int((SECONDS + 2.0) * 1e9)
    lo, hi = (int(round(v * 1e9)) for v in robot_bag.truth_gap(SECONDS, GAP))
    last_ns = int(round((SECONDS - robot_bag.DT) * 1e9))  # the run's last truth message
    max_age = int(round(spec.max_age * 1e9))
    tau = (ticks - t0) % run_ns  # time since the run's start
    # the latest truth message at or before tau: every 10 ms, none in [lo, hi), none after the run
    latest = np.minimum((tau // 10_000_000) * 10_000_000, last_ns)
    latest = np.where((latest >= lo) & (latest < hi), lo - 10_000_000, latest)
    covered = tau - latest <= (0 if exact else max_age)
    rows = []
    for a, b in segments(~stale & ~nonfinite):
        rows += [covered[a + k * LENGTH : a + (k + 1) * LENGTH] for k in range((b - a) // LENGTH)]
    return np.stack(rows)


@pytest.mark.slow
def test_the_labelled_mask_is_the_truths_coverage_and_the_inputs_run_through_the_gap(bags, tmp_path):
    full_bag, gap_bag = bags
    spec = load_spec(SPEC)
    full, full_est, _ = build_dataset([full_bag], spec, LENGTH)
    part, part_est, summaries = build_dataset([gap_bag], spec, LENGTH)
    expected = truth_coverage(gap_bag, spec)
    assert full.labelled is None  # every step labelled: no mask, as before
    assert part.labelled is not None and part.labelled.shape == expected.shape
    np.testing.assert_array_equal(part.labelled, expected)
    assert (~expected).sum() == RUNS * 57  # 12.3 .. 17.9 s of each run: the last truth message over 0.25 s old
    assert expected.all(axis=1).sum() < expected.shape[0]  # (some trajectories do have a gap)
    # the gap does not cut the trajectories: the same ticks, the same inputs and recorded estimates
    np.testing.assert_array_equal(part.y, full.y)
    np.testing.assert_array_equal(part.u, full.u)
    np.testing.assert_array_equal(part_est["robot_filter"], full_est["robot_filter"])
    # truth where labelled: the truth at the tick, or (the first 0.25 s of the gap) the last message held
    # within max_age, as for every topic
    exact = truth_coverage(gap_bag, spec, exact=True)
    np.testing.assert_array_equal(part.x[exact], full.x[exact])
    assert (part.labelled & ~exact).sum() == RUNS * 3  # 12.0, 12.1, 12.2 s hold the message of 11.99 s
    assert np.isfinite(part.x).all()  # a finite placeholder elsewhere
    meta = part.meta
    assert (meta["labelled_steps"], meta["unlabelled_steps"]) == (int(expected.sum()), int((~expected).sum()))
    steps = expected.size
    assert f"{RUNS * 57} of {steps} steps unlabelled" in summaries[0].line()
    # the mask is saved with the dataset and read back; a fully labelled file has none
    path = save_trajectories(tmp_path / "part.npz", part)
    back, _ = load_trajectories(path)
    np.testing.assert_array_equal(back.labelled, expected)
    assert "labelled" not in np.load(save_trajectories(tmp_path / "full.npz", full)).files


def test_a_bad_labelled_mask_is_refused_in_one_line(tmp_path):
    x = np.zeros((2, 4, 1))
    for mask, words in (
        (np.ones((2, 3), bool), "'labelled' must be a (2, 4) bool array"),
        (np.ones((2, 4), np.int8), "'labelled' must be a (2, 4) bool array"),
        (np.array([[True] * 4, [False] * 4]), "marks no step of trajectory 1"),
    ):
        save_npz(tmp_path / "d.npz", {"x": x, "y": x, "u": x[..., :0], "labelled": mask}, {})
        with pytest.raises(DataError, match=words.replace("(", r"\(").replace(")", r"\)")):
            load_trajectories(tmp_path / "d.npz")


# ---- training -------------------------------------------------------------------------------------
def tiny_dataset(seed: int = 0, n: int = 8, T: int = 40) -> Trajectories:
    """A recorded-data set (DataScenario meta) with a truth gap in every trajectory."""
    rng = np.random.default_rng(seed)
    x = np.cumsum(rng.normal(size=(n, T, 2)), axis=1)
    y = x + 0.3 * rng.normal(size=x.shape)
    labelled = np.ones((n, T), bool)
    labelled[:, 15:25] = False
    meta = {
        "scenario": "data",
        "dt": 0.1,
        "horizon": T,
        "spec_sha256": "0" * 64,
        "state_names": ["a", "b"],
        "state_units": ["m", "m"],
        "obs_names": ["ya", "yb"],
        "obs_units": ["m", "m"],
    }
    return Trajectories(x, y, np.zeros((n, T, 0)), meta, labelled)


def train_on(data: Trajectories, tmp_path: Path, name: str) -> tuple[str, list]:
    """(SHA-256 of the trained weights, the run's loss history) of two epochs of a GRU on ``data``."""
    import json

    path = save_trajectories(tmp_path / f"{name}.npz", data)
    out = tmp_path / name
    args = ["train", "--data", str(path), "--model", "gru", "--out", str(out), "--epochs", "2"]
    args += ["--windows-per-epoch", "16", "--window", "20", "--warmup", "2", "--val-fraction", "0.25", "--quiet"]
    assert main(args) == 0
    history = json.loads((out / "card.json").read_text())["training"]["history"]
    losses = [(h["train_loss"], h["val_loss"]) for h in history]
    return hashlib.sha256((out / "model.safetensors").read_bytes()).hexdigest(), losses


@pytest.mark.slow
def test_training_reads_the_labelled_steps_only(tmp_path):
    data = tiny_dataset()
    weights, losses = train_on(data, tmp_path, "base")
    # any other truth inside the gaps: the same weights and losses, bit for bit
    moved = Trajectories(data.x.copy(), data.y, data.u, data.meta, data.labelled)
    moved.x[~data.labelled] = 1e3
    assert train_on(moved, tmp_path, "moved") == (weights, losses)
    # the same change at labelled steps does change them (the comparison can fail)
    changed = Trajectories(data.x.copy(), data.y, data.u, data.meta, data.labelled)
    changed.x[:, 5] += 1.0
    assert train_on(changed, tmp_path, "changed")[0] != weights
    # without the mask the placeholder would be trained on: another model
    unmasked = Trajectories(moved.x, data.y, data.u, data.meta, None)
    assert train_on(unmasked, tmp_path, "unmasked")[0] != weights


@pytest.mark.slow
def test_a_covariance_head_is_fitted_on_the_labelled_steps_only(tmp_path):
    from neural_estimator.robot import DataScenario
    from neural_estimator.serving.load import load_neural_estimator
    from neural_estimator.serving.uncertainty.fit import FitSettings, fit_covariance_head

    data = tiny_dataset()
    train_on(data, tmp_path, "model")
    moved = Trajectories(data.x.copy(), data.y, data.u, data.meta, data.labelled)
    moved.x[~data.labelled] = 1e3  # other placeholders in the gaps
    est = load_neural_estimator("gru", DataScenario(data.meta), tmp_path / "model", covariance=False)
    settings = FitSettings(steps=20)
    heads = [fit_covariance_head(est, settings, head_data=d, calibration_data=d) for d in (data, moved)]
    assert heads[0][1]["nll_history"] == heads[1][1]["nll_history"]
    assert heads[0][1]["calibration"]["scale"] == heads[1][1]["calibration"]["scale"]
    unmasked = Trajectories(moved.x, data.y, data.u, data.meta, None)  # the comparison can fail
    assert (
        fit_covariance_head(est, settings, head_data=unmasked, calibration_data=unmasked)[1]["nll_history"]
        != (heads[0][1]["nll_history"])
    )


@pytest.mark.slow
def test_a_fully_labelled_mask_trains_as_no_mask(tmp_path):
    from neural_estimator.robot import DataScenario
    from neural_estimator.training.loop import train
    from neural_estimator.training.recipe import TrainConfig

    data = tiny_dataset()
    data = Trajectories(data.x, data.y, data.u, data.meta, None)
    ones = Trajectories(data.x, data.y, data.u, data.meta, np.ones(data.x.shape[:2], bool))
    cfg = TrainConfig(epochs=2, windows_per_epoch=16, window=20, warmup=2, device="cpu")
    digests = []
    for name, d in (("none", data), ("ones", ones)):  # the mask passed to train() itself, not dropped on save
        sets = (d.subset(slice(0, 6)), d.subset(slice(6, 8)))
        out = train(DataScenario(d.meta), "gru", tmp_path / name, cfg, progress=False, data=sets)
        digests.append(hashlib.sha256((out / "model.safetensors").read_bytes()).hexdigest())
    assert digests[0] == digests[1]


# ---- scoring --------------------------------------------------------------------------------------
def test_scoring_on_the_labelled_steps_equals_a_hand_computation():
    rng = np.random.default_rng(4)
    n, T, dx, warmup = 5, 30, 2, 3
    x = rng.normal(size=(n, T, dx))
    x_hat = x + rng.normal(size=(n, T, dx))
    lab = rng.random((n, T)) < 0.6
    lab[:, warmup] = True  # every trajectory has a labelled scored step
    x_hat[~lab] += 1e6  # huge errors where there is no truth: never scored
    rep = M.compute_labelled_metrics(x, x_hat, (), lab, warmup=warmup)
    e, m = (x_hat - x)[:, warmup:], lab[:, warmup:]
    mse_n = np.array([np.mean(e[i][m[i]] ** 2) for i in range(n)])  # each trajectory on its labelled steps
    assert rep.rmse == pytest.approx(math.sqrt(mse_n.mean()), rel=1e-12)
    assert rep.mae == pytest.approx(np.mean(np.abs(e[m])), rel=1e-12)
    assert rep.medae == pytest.approx(np.median(np.abs(e[m])), rel=1e-12)
    assert rep.rmse_components[1] == pytest.approx(
        math.sqrt(np.mean([np.mean(e[i][m[i], 1] ** 2) for i in range(n)])), rel=1e-12
    )
    t = 7
    assert rep.rmse_t[t] == pytest.approx(math.sqrt(np.mean(e[:, t][m[:, t]] ** 2)), rel=1e-12)
    assert (rep.scored_steps, rep.unlabelled_steps) == (int(m.sum()), int((~m).sum()))
    assert rep.n_diverged == 0 and rep.n_outliers == 0
    # the per-trajectory errors behind the confidence intervals agree with the report
    errs = M.trajectory_errors(x, x_hat, (), rep.outlier_idx, warmup, lab)
    assert M.run_rmse(errs) == pytest.approx(rep.rmse, rel=1e-12)
    # a fully labelled mask scores exactly as no mask
    full = M.compute_labelled_metrics(x, x + 0.1, (), np.ones((n, T), bool), warmup=warmup)
    assert M.to_json(full) == M.to_json(M.compute_metrics(x, x + 0.1, (), warmup=warmup))
    assert full.scored_steps is None


@pytest.mark.slow
def test_evaluate_and_metrics_say_how_many_steps_were_scored(bags, tmp_path, capsys):
    _, gap_bag = bags
    expected = truth_coverage(gap_bag, load_spec(SPEC))
    data = tmp_path / "part.npz"
    assert main(["dataset", str(gap_bag), "--spec", str(SPEC), "--length", str(LENGTH), "--out", str(data)]) == 0
    out = capsys.readouterr().out
    n_lab, n_unlab = int(expected.sum()), int((~expected).sum())
    assert f"ground truth on {n_lab} of {expected.size} steps ({n_unlab} unlabelled" in out
    assert main(["metrics", str(tmp_path / "part.robot_filter.npz")]) == 0
    after = expected[:, M.EVALUATION_WARMUP :]  # the steps after the warm-up
    line = f"partial ground truth: {int(after.sum())} labelled steps scored, {int((~after).sum())} unlabelled"
    assert line in capsys.readouterr().out


def test_a_live_runs_truth_gap_is_left_unscored_not_cut(tmp_path):
    """The evaluator's scoring of a live run (score_recording): a recorded bag with the truth silent in
    [12, 18) s and an estimate stream at every tick, off by 0.5 m in x where the truth is fresh."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    from neural_estimator.robot.score import score_recording

    ts, T_ = robot_bag.TS, robot_bag.T
    t0, ms = 1_700_000_000 * 10**9, 1_000_000
    lo, hi = 12_000, 18_000  # the gap [ms]
    truth_ms = np.array([k * 10 for k in range(3000) if not lo <= k * 10 < hi])
    ticks_ms = np.arange(300) * 100

    def pose(t_ms):
        s = t_ms / 1000.0
        return s, math.sin(s), 0.1 * s  # x, y, yaw

    with Writer(tmp_path / "live", version=9, storage_plugin=StoragePlugin.MCAP) as bag:
        mocap = bag.add_connection("/mocap/pose", "geometry_msgs/msg/PoseStamped", typestore=ts)
        est = bag.add_connection("/estimates/m", "sensor_msgs/msg/JointState", typestore=ts)
        events = [(int(t), 0) for t in truth_ms] + [(int(t), 1) for t in ticks_ms]
        for t, kind in sorted(events):
            stamp = t0 + t * ms
            x, y, yaw = pose(t)
            if kind == 0:
                p = T_["geometry_msgs/msg/Pose"](
                    position=T_["geometry_msgs/msg/Point"](x=x, y=y, z=0.0), orientation=robot_bag.quaternion(yaw)
                )
                msg = T_["geometry_msgs/msg/PoseStamped"](header=robot_bag.header(stamp, "map"), pose=p)
                bag.write(mocap, stamp, ts.serialize_cdr(msg, mocap.msgtype))
            else:
                msg = T_["sensor_msgs/msg/JointState"](
                    header=robot_bag.header(stamp, ""),
                    name=["x", "y", "yaw"],
                    position=np.array([x + 0.5, y, yaw]),
                    velocity=np.zeros(0),
                    effort=np.zeros(0),
                )
                bag.write(est, stamp, ts.serialize_cdr(msg, est.msgtype))
    reports, truth = score_recording(tmp_path / "live", SPEC, length=LENGTH, warmup=0)
    rep = reports["m"]
    assert truth.n == 6  # 300 ticks in 6 trajectories: the gap cut nothing
    # by hand: the truth at a tick is its latest message at most 0.25 s old, else the step is unlabelled
    latest = np.array([truth_ms[truth_ms <= t].max() for t in ticks_ms])
    labelled = (ticks_ms - latest) <= 250
    e = np.array([np.subtract((pose(t)[0] + 0.5, *pose(t)[1:]), pose(s)) for t, s in zip(ticks_ms, latest)])
    e, labelled = e.reshape(6, LENGTH, 3), labelled.reshape(6, LENGTH)
    mse_n = [np.mean(e[i][labelled[i]] ** 2) for i in range(6)]
    assert (rep.scored_steps, rep.unlabelled_steps) == (300 - 57, 57)
    assert rep.rmse == pytest.approx(math.sqrt(np.mean(mse_n)), rel=1e-9)


@pytest.mark.ros
@pytest.mark.slow
def test_served_live_a_recording_with_truth_gaps_scores_what_evaluate_scored(tmp_path, capsys):
    """The live chain (player -> estimator -> evaluator, default parameters) on a recording whose truth
    is silent 10 s of each run: the evaluator scores the labelled steps evaluate scored, no more."""
    pytest.importorskip("rclpy")
    import json
    import signal

    from ros_tester import fresh_domain

    from neural_estimator.nodes.launch import ESTIMATOR, EVALUATOR, isolated_env, node_command, start_node
    from neural_estimator.robot.score import score_recording

    bag = robot_bag.write_bag(tmp_path / "bag", runs=2, seconds=42.0, seed=3, truth_gaps=10.0)
    data = tmp_path / "data.npz"
    assert main(["dataset", str(bag), "--spec", str(SPEC), "--length", "200", "--out", str(data), "--quiet"]) == 0
    model = tmp_path / "gru"
    args = ["train", "--data", str(data), "--model", "gru", "--out", str(model), "--epochs", "1", "--quiet"]
    assert main(args + ["--windows-per-epoch", "16", "--window", "20", "--warmup", "2", "--val-fraction", "0.25"]) == 0
    capsys.readouterr()
    assert main(["evaluate", "--data", str(data), "--checkpoint", f"gru={model}", "--json", "--quiet"]) == 0
    run = json.loads(capsys.readouterr().out)["methods"]["gru"]["runs"][0]
    assert run["unlabelled_steps"] > 0
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
                dict(bag=str(bag), rate=4.0, wait_for_subscribers=1, wait_topic="/imu"),
            ),
        ):
            procs.append(start_node(node_command(sys.executable, module, name, params), tmp_path / f"{name}.log", env))
        assert procs[0].wait(timeout=180) == 0, "".join(
            (tmp_path / f"{n}.log").read_text() for n in ("rec", "est", "player")
        )
    finally:
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for p in procs:
            try:
                p.wait(timeout=5)
            except Exception:
                p.kill()
    reports, truth = score_recording(rec, SPEC, length=200)
    live = reports["gru"]
    print(f"gru: evaluate RMSE {run['rmse']:.4f}, live {live.rmse:.4f} ({truth.n} trajectories)")
    assert (live.scored_steps, live.unlabelled_steps) == (run["scored_steps"], run["unlabelled_steps"])
    assert abs(live.rmse - run["rmse"]) <= 0.05 * run["rmse"], (run["rmse"], live.rmse)
    written = json.loads(rec.with_suffix(".metrics.json").read_text())  # the evaluator's own scoring
    assert written["methods"]["gru"]["scored_steps"] == run["scored_steps"]
    assert written["partial_ground_truth"].startswith("partial ground truth: ")
