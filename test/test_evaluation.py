"""The evaluation protocol and the evaluate/train verbs end to end (small sizes)."""

import json

import numpy as np
import pytest

from neural_estimator.cli import main
from neural_estimator.data import simulate
from neural_estimator.estimators import make_estimator
from neural_estimator.evaluation import chunk_size, evaluate, results_json, results_table, run_method
from neural_estimator.scenarios import make_scenario

PLUGIN = ["--plugin", "examples/custom_scenario.py"]


@pytest.fixture(autouse=True)
def _repo_cwd(monkeypatch, tmp_path):
    from pathlib import Path

    monkeypatch.chdir(Path(__file__).resolve().parents[1])
    monkeypatch.setenv("NEURAL_ESTIMATOR_CACHE", str(tmp_path / "cache"))


def test_chunking_does_not_change_results(oscillator):
    data = simulate(oscillator, 13, 20, seed=1)
    est = make_estimator("ukf", oscillator)
    whole = run_method(est, data, 13, ())
    pieces = run_method(est, data, 4, ())
    np.testing.assert_array_equal(whole[0], pieces[0])
    np.testing.assert_allclose(whole[1], pieces[1])


def test_chunk_size_respects_the_memory_budget():
    l96 = make_scenario("lorenz96")
    n = chunk_size(l96, "ukf", 500, 8000, budget=1 << 30)
    per_traj = 500 * (40 + 1600 + 40) * 8
    assert 1 <= n < 8000 and n * per_traj <= 1 << 30
    assert chunk_size(l96, "pf", 500, 8000) < n  # the particles take room too
    assert chunk_size(l96, "ukf", 500, 10, budget=1 << 40) == 10


def test_ekf_and_ukf_are_consistent_on_a_linear_gaussian_system(oscillator):
    """On a linear-Gaussian system the filters are exact: NEES ~ dx and 95% coverage ~ 0.95."""
    results = evaluate(oscillator, ["ekf", "ukf"], trajectories=200, horizon=60, sets=2, cache_dir=False, progress=False)
    for m in ("ekf", "ukf"):
        s = results[m].summary
        assert s["nees"].median == pytest.approx(2.0, abs=0.15)
        assert s["coverage95"].median == pytest.approx(0.95, abs=0.015)
        assert s["rmse"].n == 2 and s["diverged_ratio"].median == 0
    # identical estimates on a linear system
    assert results["ekf"].summary["rmse"].median == pytest.approx(results["ukf"].summary["rmse"].median, rel=1e-9)
    table = results_table(results, fmt="markdown")
    assert "| ekf |" in table and "NEES" in table
    js = results_json(oscillator, results, trajectories=200)
    assert js["methods"]["ukf"]["summary"]["rmse"]["median"] > 0 and len(js["methods"]["ukf"]["runs"]) == 2


def test_evaluate_verb_writes_table_json_and_plot(tmp_path, capsys):
    out = tmp_path / "ev"
    assert main(["evaluate", *PLUGIN, "--scenario", "oscillator", "--methods", "ekf,pf", "--trajectories", "30",
                 "--horizon", "25", "--sets", "2", "--option", "pf.n_particles=256", "--quiet", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "oscillator: 2 sets x 30 trajectories x 25 steps" in text and "pf" in text
    res = json.loads((out / "results.json").read_text())
    assert set(res["methods"]) == {"ekf", "pf"} and len(res["methods"]["pf"]["runs"]) == 2
    assert (out / "rmse_over_time.png").stat().st_size > 1000
    assert (out / "table.csv").read_text().startswith("method,")


def test_evaluate_threads_do_not_change_the_numbers(tmp_path, capsys):
    """--threads runs the filters' blocks on threads; the results are the same as on one."""
    runs = {}
    for threads in ("1", "3"):
        out = tmp_path / f"t{threads}"
        assert main(["evaluate", *PLUGIN, "--scenario", "oscillator", "--methods", "ukf,enkf", "--trajectories", "40",
                     "--horizon", "20", "--sets", "1", "--threads", threads, "--no-cache", "--quiet", "--out", str(out)]) == 0
        capsys.readouterr()
        runs[threads] = json.loads((out / "results.json").read_text())["methods"]
    for m in ("ukf", "enkf"):
        assert runs["1"][m]["runs"] == runs["3"][m]["runs"]
    assert main(["evaluate", *PLUGIN, "--scenario", "oscillator", "--methods", "ukf", "--threads", "0", "--quiet"]) == 2
    assert "--threads must be >= 1" in capsys.readouterr().err


def test_train_then_evaluate_neural_next_to_classical(tmp_path, capsys):
    ckpt = tmp_path / "gru"
    assert main(["train", *PLUGIN, "--scenario", "oscillator", "--model", "gru", "--out", str(ckpt),
                 "--trajectories", "32", "--train-length", "120", "--val-trajectories", "16", "--epochs", "2",
                 "--windows-per-epoch", "64", "--quiet", "--no-keep-resume"]) == 0
    assert sorted(p.name for p in ckpt.iterdir()) == ["card.json", "model.safetensors"]
    capsys.readouterr()
    assert main(["evaluate", *PLUGIN, "--scenario", "oscillator", "--methods", "ukf,gru", "--checkpoint",
                 f"gru={ckpt}", "--trajectories", "20", "--horizon", "150", "--sets", "1", "--quiet", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert set(res["methods"]) == {"ukf", "gru"}
    # a checkpoint for another scenario is refused with a message naming both
    assert main(["evaluate", "--scenario", "bearings", "--methods", "gru", "--checkpoint", f"gru={ckpt}",
                 "--trajectories", "5", "--sets", "1", "--quiet"]) == 2
    assert "oscillator" in capsys.readouterr().err
