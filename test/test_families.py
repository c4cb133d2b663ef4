"""The sealed evaluation family stays apart from development, and the headline command measures and
renders the headline table (tiny scale, development family)."""

import json
import math
import subprocess
from pathlib import Path

import numpy as np
import pytest

from neural_estimator.cli import main
from neural_estimator.evaluation import evaluate
from neural_estimator.evaluation import families as F
from neural_estimator.scenarios import make_scenario

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def _repo_cwd(monkeypatch, tmp_path):
    monkeypatch.chdir(ROOT)
    monkeypatch.setenv("NEURAL_ESTIMATOR_CACHE", str(tmp_path / "cache"))


def test_the_families_split_the_seeds():
    assert F.family_of(0) == F.family_of(777) == F.family_of(F.SEALED_FLOOR - 1) == F.DEVELOPMENT
    assert F.family_of(F.SEALED_FLOOR) == F.family_of(F.family_seed(F.SEALED)) == F.SEALED
    assert F.family_of(F.family_seed(F.DEVELOPMENT)) == F.DEVELOPMENT
    with pytest.raises(ValueError, match="family must be one of"):
        F.family_seed("fresh")


def test_evaluate_refuses_a_sealed_seed_unless_the_headline_asks(capsys):
    sc = make_scenario("ballistic")
    sealed = F.family_seed(F.SEALED)
    with pytest.raises(ValueError, match="sealed evaluation family"):
        evaluate(sc, ["ekf"], trajectories=2, horizon=12, sets=1, seed=sealed, cache_dir=False, progress=False)
    assert main(["evaluate", "--scenario", "ballistic", "--seed", str(sealed), "--trajectories", "2"]) == 2
    err = capsys.readouterr().err
    assert "sealed evaluation family" in err and len(err.strip().splitlines()) == 1
    # a development seed runs as before
    res = evaluate(sc, ["ekf"], trajectories=2, horizon=12, sets=1, seed=777, cache_dir=False, progress=False)
    assert res["ekf"].reports


def test_no_other_code_reads_the_sealed_seed():
    """Only the families module defines it and only the headline asks for it: a script, experiment,
    benchmark or test that measured on the sealed family would name one of these."""
    tracked = subprocess.run(["git", "ls-files", "*.py"], cwd=ROOT, capture_output=True, text=True)
    if tracked.returncode != 0:
        pytest.skip("not a git checkout")
    allowed = {
        "neural_estimator/evaluation/families.py",
        "neural_estimator/evaluation/headline.py",
        "test/test_families.py",
    }
    words = ("SEALED_SEED", "SEALED_FLOOR", "family_seed", "sealed=True", str(F.family_seed(F.SEALED)))
    readers = {
        path
        for path in tracked.stdout.split()
        if path not in allowed and any(w in (ROOT / path).read_text(errors="replace") for w in words)
    }
    assert not readers, f"these files read the sealed evaluation family: {sorted(readers)}"


def test_headline_measures_and_renders_on_the_development_family(tmp_path, capsys):
    out = tmp_path / "headline"
    argv = ["headline", "--family", "development", "--scenarios", "ballistic", "--methods", "ekf,ukf,gru"]
    assert main(argv + ["--trajectories", "10", "--sets", "2", "--horizon", "40", "--out", str(out), "--quiet"]) == 0
    table = capsys.readouterr().out
    data = json.loads((out / "headline.json").read_text())
    assert data["family"] == "development" and data["seed"] == F.family_seed(F.DEVELOPMENT)
    (row,) = data["rows"]
    assert row["best_filter"] in ("ekf", "ukf") and row["best_network"] == "gru"
    assert row["ci95"][0] <= row["ratio"] <= row["ci95"][1]
    assert row["verdict"] in ("network better", "tied", "filter better")
    assert row["not_estimated"] == ["drag_coefficient"]  # no method beats the open loop on the drag
    assert [c["name"] for c in row["components"]] == ["altitude", "velocity"]
    assert table == (out / "headline.md").read_text()
    # each side by its display name and median figure, the network with its count of instances
    best = {"ekf": "EKF", "ukf": "UKF"}[row["best_filter"]]
    assert f"| ballistic | {best} {row['filter_value']:.3g} | GRU {row['network_value']:.3g} (1 instance) | " in table
    results = json.loads((out / "ballistic" / "results.json").read_text())
    assert "openloop" in results["methods"] and results["methods"]["openloop"]["reference_row"]


def _synthetic_results(rng, x, scales, failures=None):
    """MethodResults of errors N(0, scale^2) per method (one scale, or one per component), the first
    ``failures[m]`` trajectories of method m multiplied by 1e3: failures the outlier rule drops."""
    from neural_estimator import metrics as M
    from neural_estimator.evaluation.protocol import MethodResult

    results = {}
    for m, scale in scales.items():
        e = rng.standard_normal(x.shape) * np.asarray(scale)
        e[: (failures or {}).get(m, 0)] *= 1e3
        rep = M.compute_metrics(x, x + e)
        results[m] = MethodResult(m)
        results[m].add(rep, M.trajectory_errors(x, x + e, (), rep.outlier_idx))
    return results


def test_the_headline_ranks_on_the_full_rmse_where_the_outlier_rule_changes_the_best():
    """The EnKF is best on its kept trajectories, but the outlier rule dropped its failures: over
    every trajectory the EKF is best, and the headline says so and ranks on the Full RMSE."""
    from neural_estimator.evaluation.headline import headline_row

    rng = np.random.default_rng(0)
    x = rng.standard_normal((60, 20, 3))
    results = _synthetic_results(rng, x, {"ekf": 1.0, "enkf": 0.8, "gru": 1.2}, failures={"enkf": 3})
    assert results["enkf"].summary["rmse"].median < results["ekf"].summary["rmse"].median
    row = headline_row(make_scenario("ballistic"), results)
    assert row["figure"] == "full_rmse" and row["best_filter"] == "ekf" and row["best_network"] == "gru"
    assert row["verdict"] == "filter better" and row["ci95"][0] > 1.0


def test_the_verdict_rests_on_the_estimated_components_not_on_the_aggregate():
    """Ballistic-like: a drag error that no method reduces (the open loop's own) swamps the aggregate,
    which ties; the network's altitude and velocity errors are 3x and 1.5x the filter's, so the
    verdict is "filter better", the aggregate's "tied" is kept beside it and both are printed."""
    from neural_estimator.evaluation.headline import headline_row, render_headline

    rng = np.random.default_rng(4)
    x = rng.standard_normal((80, 20, 3))
    scales = {"ekf": (1.0, 1.0, 100.0), "gru": (3.0, 1.5, 100.0), "openloop": (10.0, 10.0, 100.0)}
    results = _synthetic_results(rng, x, scales)
    row = headline_row(make_scenario("ballistic"), results)
    assert row["best_filter"] == "ekf" and row["best_network"] == "gru"
    assert row["not_estimated"] == ["drag_coefficient"]
    assert row["verdict_aggregate"] == "tied" and row["ci95"][0] < 1.0 < row["ci95"][1]
    altitude, velocity = row["components"]
    assert altitude["ratio"] == pytest.approx(3.0, rel=0.1) and velocity["ratio"] == pytest.approx(1.5, rel=0.1)
    g = row["estimated"]
    assert g["ratio"] == pytest.approx(math.sqrt(altitude["ratio"] * velocity["ratio"]))
    assert 1.0 < g["ci95"][0] <= g["ratio"] <= g["ci95"][1]
    assert row["verdict"] == g["verdict"] == "filter better"
    table = render_headline(dict(family="development", seed=0, sets=1, trajectories=80, rows=[row]))
    assert f"together {g['ratio']:.2f} [" in table and "| filter better (aggregate: tied) |" in table


def test_the_headline_ranks_on_the_full_rmse_where_the_outlier_rule_puts_the_filter_ahead():
    """The only filter and the only network: on its kept trajectories the EKF is ahead, but its
    dropped failures put it behind over every trajectory; the headline ranks on the Full RMSE."""
    from neural_estimator.evaluation.headline import headline_row

    rng = np.random.default_rng(2)
    x = rng.standard_normal((60, 20, 3))
    results = _synthetic_results(rng, x, {"ekf": 0.8, "gru": 1.0}, failures={"ekf": 4})
    ekf, gru = results["ekf"].summary, results["gru"].summary
    assert ekf["rmse"].median < gru["rmse"].median and ekf["full_rmse"].median > gru["full_rmse"].median
    row = headline_row(make_scenario("ballistic"), results)
    assert row["figure"] == "full_rmse" and (row["best_filter"], row["best_network"]) == ("ekf", "gru")
    assert row["verdict_aggregate"] == "network better" and row["ci95"][1] < 1.0
