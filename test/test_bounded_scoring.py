"""Scoring in memory that does not grow with the recording (metrics/streaming.py, metrics/spill.py,
bags/spilled_cells.py, evaluation/bag_scoring.py) gives the figures of the whole-array computation: the
block scorer equals compute_metrics, the spilled median equals np.median, and a bag scored block by
block equals load_bag_dataset + compute_metrics, with missing cells, repeats, messages outside the
announced run, a diverged stream and a method left out. The memory figures are in
benchmarks/bench_scoring_memory.py, not here."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from neural_estimator.bags import spilled_cells
from neural_estimator.evaluation import bag_scoring as bounded
from neural_estimator.stream import messages as MSG
from neural_estimator.bags.dataset import load_bag_dataset
from neural_estimator.bags.errors import BagError
from neural_estimator.evaluation.bag_report import evaluate_bag
from neural_estimator.bags.writer import BagWriter
from neural_estimator.data import simulate
from neural_estimator.evaluation.decision import estimates_decision
from neural_estimator.metrics import MetricsError, compute_metrics, trajectory_errors
from neural_estimator.metrics import spill as S
from neural_estimator.metrics.streaming import BlockScorer, score_in_blocks
from neural_estimator.scenarios import make_scenario


def assert_same_report(want, got):
    """Every field of two MetricReports equal to 1e-12 (relative), NaN and inf in the same places."""
    for field in dataclasses.fields(want):
        a, b = getattr(want, field.name), getattr(got, field.name)
        assert (a is None) == (b is None), field.name
        if a is None:
            continue
        a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
        assert a.shape == b.shape, field.name
        np.testing.assert_allclose(b, a, rtol=1e-12, atol=0, equal_nan=True, err_msg=field.name)


def _run(seed=0, n=37, t=30, dx=3):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, t, dx)) * np.array([1.0, 3.0, 0.5])[:dx]
    xh = x + 0.1 * rng.normal(size=x.shape)
    xh[2] += 40.0  # an outlier
    xh[4, 17, 1] = np.nan  # diverged after the warm-up
    xh[6, 3, 0] = np.inf  # diverged in the warm-up
    xh[8, 11, 2] = 1e200  # overflowing squared error: diverged too
    a = rng.normal(size=(n, t, dx, dx))
    P = a @ np.swapaxes(a, -1, -2) * 0.01 + 1e-3 * np.eye(dx)
    P[9, 12] = 0.0  # degenerate
    P[10, 13, 0, 0] = np.nan  # unusable
    P[11, 14] = np.ones((dx, dx))  # singular
    return x, xh, P


@pytest.mark.parametrize("warmup", [0, 10])
@pytest.mark.parametrize("block", [1, 5, 37])
def test_block_scorer_equals_compute_metrics(monkeypatch, warmup, block):
    monkeypatch.setattr(S, "CHUNK_VALUES", 50)  # many chunks per pass
    x, xh, P = _run()
    flags = np.zeros(len(x), dtype=bool)
    flags[20] = True
    for angles, with_p, diverged in (((), True, None), ((1,), True, flags), ((0, 2), False, None)):
        want = compute_metrics(x, xh, angles, P_hat=P if with_p else None, diverged=diverged, warmup=warmup)
        with BlockScorer(x.shape[1], x.shape[2], angles, warmup=warmup, covariance=with_p) as scorer:
            for a in range(0, len(x), block):
                sl = slice(a, a + block)
                scorer.add(x[sl], xh[sl], P[sl] if with_p else None, None if diverged is None else diverged[sl])
            got = scorer.report()
            errors = scorer.trajectory_errors()
        assert_same_report(want, got)
        old = trajectory_errors(x, xh, angles, want.outlier_idx, warmup)
        np.testing.assert_allclose(errors.mse, old.mse, rtol=1e-12, equal_nan=True)
        np.testing.assert_array_equal(errors.kept, old.kept)


def test_block_scorer_every_trajectory_diverged_and_bad_input():
    x, xh, P = _run(n=12)
    xh[:, 5] = np.nan
    assert_same_report(compute_metrics(x, xh, P_hat=P, warmup=2), score_in_blocks(x, xh, P_hat=P, warmup=2)[0])
    with pytest.raises(MetricsError, match="warmup must be an integer in"):
        BlockScorer(5, 3, warmup=5)
    x[1, 3, 0] = np.nan
    with pytest.raises(MetricsError, match="ground truth must be finite"):
        score_in_blocks(x, xh)
    with pytest.raises(MetricsError, match="spread must be positive"):
        score_in_blocks(np.ones((2, 4, 1)), np.ones((2, 4, 1)))


@pytest.mark.parametrize("size", [1, 2, 7, 200, 201])
def test_spilled_median_equals_numpy(monkeypatch, size):
    monkeypatch.setattr(S, "CHUNK_VALUES", 13)
    rng = np.random.default_rng(size)
    width = 3
    rows = np.abs(rng.normal(size=(size, width))) * 10.0 ** rng.integers(-5, 5, size=(size, 1))
    rows[rng.random(rows.shape) < 0.2] = 0.0
    rows[rng.random(rows.shape) < 0.1] = np.inf
    rows[rng.random(rows.shape) < 0.2] = 1.5  # ties
    keep = rng.random(size) < 0.6
    keep[0] = True
    spill = S.RowSpill(width)
    for a in range(0, size, 4):
        spill.append(rows[a : a + 4])
    assert S.exact_median(spill) == np.median(rows)
    assert S.exact_median(spill, keep) == np.median(rows[keep])
    rows[0, 0] = np.nan
    spill = S.RowSpill(width)
    spill.append(rows)
    assert np.isnan(S.exact_median(spill))
    assert S.exact_median(spill, nan_as_inf=True) == np.median(np.where(np.isnan(rows), np.inf, rows))
    spill.close()


def _hostile_bag(path, scen, data):
    """A recorded run with what a live one can carry: a lost cell, repeats, messages outside the
    announced run, a malformed one, a diverged estimate stream and one that is mostly lost."""
    n_traj, horizon = data.x.shape[:2]
    dx = scen.dx
    obs, truth, cov = MSG.observation_labels(scen), MSG.state_labels(scen), MSG.covariance_labels(dx)
    rng = np.random.default_rng(5)
    topics = ["/scenario", "/observation", "/ground_truth", "/estimates/ekf", "/estimates/ekf/covariance"]
    topics += ["/estimates/gru", "/estimates/pf", "/run_status"]
    with BagWriter(path) as bag:
        for topic in topics:
            bag.add_topic(topic, MSG.STRING if topic in ("/scenario", "/run_status") else MSG.JOINT_STATE)
        bag.write("/scenario", 0, MSG.encode_scenario(scen.describe(), trajectories=n_traj, horizon=horizon))
        t = 1

        def put(topic, raw):
            nonlocal t
            bag.write(topic, t, raw)
            t += 1

        for n in range(n_traj):
            for k in range(horizon):
                put("/observation", MSG.encode_vector(t, "b", n, k, obs, data.y[n, k]))
                if (n, k) != (3, 7):  # lost: trajectory 3 is left out
                    put("/ground_truth", MSG.encode_vector(t, "b", n, k, truth, data.x[n, k]))
                est = data.x[n, k] + 0.2 * rng.normal(size=dx)
                if n == 5 and k >= 12:
                    est = est * np.nan  # a diverged trajectory
                put("/estimates/ekf", MSG.encode_vector(t, "ekf", n, k, truth, est))
                a = rng.normal(size=(dx, dx))
                put("/estimates/ekf/covariance", MSG.encode_vector(t, "ekf", n, k, cov, (a @ a.T + np.eye(dx)).ravel()))
                put(
                    "/estimates/gru", MSG.encode_vector(t, "gru", n, k, truth, data.x[n, k] + 0.3 * rng.normal(size=dx))
                )
                if n < 2:  # mostly lost: the method is left out rather than shrinking everyone's set
                    put("/estimates/pf", MSG.encode_vector(t, "pf", n, k, truth, data.x[n, k]))
        put("/estimates/gru", MSG.encode_vector(t, "gru", 1, 2, truth, data.x[1, 2] + 9.0))  # a repeat: the last kept
        put("/observation", MSG.encode_vector(t, "b", 0, 3, obs, data.y[0, 3]))  # a repeat
        put("/estimates/ekf", MSG.encode_vector(t, "ekf", 0, horizon + 3, truth, data.x[0, 0]))  # outside the run
        put("/ground_truth", MSG.encode_vector(t, "b", n_traj + 40, 0, truth, data.x[0, 0]))  # outside the run
        put("/ground_truth", MSG.encode_vector(t, "b", 0, 1, ["x"], [1.0]))  # wrong names: rejected
        put("/run_status", MSG.encode_string('{"status": "complete"}'))


@pytest.mark.parametrize("warmup", [0, 10])
def test_bag_scored_in_blocks_equals_the_arrays(tmp_path, monkeypatch, warmup):
    monkeypatch.setattr(bounded, "block_trajectories", lambda horizon, dx: 3)  # several blocks
    monkeypatch.setattr(spilled_cells, "CHUNK_RECORDS_BYTES", 4096)  # several chunks per stream file
    monkeypatch.setattr(S, "CHUNK_VALUES", 64)
    scen = make_scenario("bearings")
    data = simulate(scen, 11, 24, seed=2)
    path = tmp_path / "hostile.mcap"
    _hostile_bag(path, scen, data)
    truth, estimates, angles = load_bag_dataset(path)
    run = bounded.score_bag(path, warmup=warmup)
    assert run.meta == truth.meta
    bag = run.meta["bag"]
    assert bag["left_out"] == [3] and "pf" in bag["methods_left_out"]
    assert bag["duplicates"] == {"estimates/gru": 1, "observation": 1}
    assert bag["outside"] == {"estimates/ekf": 1, "ground_truth": 1} and bag["rejected"] == {"ground_truth": 1}
    assert (run.n, run.horizon) == (truth.n, truth.horizon) and sorted(run.reports) == ["ekf", "gru"]
    want = {m: compute_metrics(truth.x, xh, angles, P_hat=P, warmup=warmup) for m, (xh, P) in estimates.items()}
    assert want["ekf"].n_diverged == 1 and want["ekf"].has_covariance
    for m in want:
        assert_same_report(want[m], run.reports[m])
    for fmt in ("text", "markdown"):
        old = estimates_decision(truth, estimates, angles, want, warmup, fmt)
        assert estimates_decision(run, None, (), run.reports, warmup, fmt, errors=run.errors) == old
    report = evaluate_bag(path, warmup=warmup)
    assert report.bag == truth.meta["bag"] and report.n_trajectories == truth.n
    for m in want:
        assert_same_report(want[m], report.reports[m])


def test_a_run_shorter_than_the_warmup(tmp_path):
    scen = make_scenario("bearings")
    data = simulate(scen, 3, 6, seed=1)
    path = tmp_path / "short.mcap"
    _hostile_bag(path, scen, data)
    with pytest.raises(MetricsError, match="warmup must be an integer"):
        evaluate_bag(path, warmup=10)
    report = evaluate_bag(path, warmup=10, short_runs="score_all")
    assert report.warmup == 0 and "every step scored" in report.note
    truth, estimates, angles = load_bag_dataset(path)
    for m, (xh, P) in estimates.items():
        assert_same_report(compute_metrics(truth.x, xh, angles, P_hat=P), report.reports[m])


def test_no_room_for_the_temporary_files_is_one_line(tmp_path):
    scen = make_scenario("bearings")
    path = tmp_path / "run.mcap"
    _hostile_bag(path, scen, simulate(scen, 3, 12, seed=1))
    with pytest.raises(BagError, match=r"scoring needs temporary files in .*missing.*set TMPDIR") as info:
        bounded.score_bag(path, spill_dir=str(tmp_path / "missing"))
    assert "\n" not in str(info.value)
    x, xh, _ = _run(n=12)
    with pytest.raises(MetricsError, match=r"scoring needs temporary files in .*missing.*set TMPDIR"):
        score_in_blocks(x, xh, spill_dir=str(tmp_path / "missing"))


def test_an_announcement_or_a_span_too_large_is_refused_before_anything_is_allocated(tmp_path):
    scen = make_scenario("bearings")
    truth = MSG.state_labels(scen)
    for run, n, k, want in (
        ({"trajectories": 3 * 10**7, "horizon": 1000}, 0, 0, r"announces 30000000 trajectories: .* over the bound of"),
        ({}, 0, 10**8, r"span 1 trajectories x 100000001 steps: .* over the bound of 4.0 GiB"),
    ):
        path = tmp_path / f"big{k}.mcap"
        with BagWriter(path) as bag:
            bag.add_topic("/scenario", MSG.STRING)
            bag.add_topic("/ground_truth", MSG.JOINT_STATE)
            bag.add_topic("/estimates/ekf", MSG.JOINT_STATE)
            bag.write("/scenario", 0, MSG.encode_scenario(scen.describe(), **run))
            for i, topic in enumerate(("/ground_truth", "/estimates/ekf")):
                bag.write(topic, 1 + i, MSG.encode_vector(0, "b", n, k, truth, np.zeros(len(truth))))
        with pytest.raises(BagError, match=want):
            bounded.score_bag(path)


def test_metrics_verb_scores_a_bag_in_blocks_and_names_a_warmup_too_long(tmp_path, capsys):
    from neural_estimator.cli import main

    scen = make_scenario("bearings")
    data = simulate(scen, 5, 16, seed=4)
    path = tmp_path / "run.mcap"
    _hostile_bag(path, scen, data)
    assert main(["metrics", str(path), "--warmup", "16"]) == 2
    assert "--warmup 16 leaves no step of 16-step trajectories" in capsys.readouterr().err
    assert main(["metrics", str(path), "--json", "--warmup", "3"]) == 0
    truth, estimates, angles = load_bag_dataset(path)
    got = json.loads(capsys.readouterr().out)["methods"]
    for m, (xh, P) in estimates.items():
        want = compute_metrics(truth.x, xh, angles, P_hat=P, warmup=3)
        np.testing.assert_allclose(got[m]["rmse"], want.rmse, rtol=1e-12)
        np.testing.assert_allclose(got[m]["medae"], want.medae, rtol=1e-12)
