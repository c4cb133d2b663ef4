"""The evaluation protocol and the evaluate/train verbs end to end (small sizes)."""

import json
from pathlib import Path

import numpy as np
import pytest

from neural_estimator.cli import main
from neural_estimator.data import simulate
from neural_estimator.methods.registry import make_estimator
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
    l96 = make_scenario("lorenz96", n_vars=40)
    n = chunk_size(l96, "ukf", 500, 8000, budget=1 << 30)
    per_traj = 500 * (40 + 1600 + 40) * 8
    assert 1 <= n < 8000 and n * per_traj <= 1 << 30
    assert chunk_size(l96, "pf", 500, 8000) < n  # the particles take room too
    assert chunk_size(l96, "ukf", 500, 10, budget=1 << 40) == 10


def test_ekf_and_ukf_are_consistent_on_a_linear_gaussian_system(oscillator):
    """On a linear-Gaussian system the filters are exact: NEES ~ dx and 95% coverage ~ 0.95."""
    results = evaluate(
        oscillator, ["ekf", "ukf"], trajectories=200, horizon=60, sets=2, cache_dir=False, progress=False
    )
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
    assert (
        main(
            [
                "evaluate",
                *PLUGIN,
                "--scenario",
                "oscillator",
                "--methods",
                "ekf,pf",
                "--trajectories",
                "30",
                "--horizon",
                "25",
                "--sets",
                "2",
                "--option",
                "pf.n_particles=256",
                "--quiet",
                "--out",
                str(out),
            ]
        )
        == 0
    )
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
        assert (
            main(
                [
                    "evaluate",
                    *PLUGIN,
                    "--scenario",
                    "oscillator",
                    "--methods",
                    "ukf,enkf",
                    "--trajectories",
                    "40",
                    "--horizon",
                    "20",
                    "--sets",
                    "1",
                    "--threads",
                    threads,
                    "--no-cache",
                    "--quiet",
                    "--out",
                    str(out),
                ]
            )
            == 0
        )
        capsys.readouterr()
        runs[threads] = json.loads((out / "results.json").read_text())["methods"]
    for m in ("ukf", "enkf"):
        assert runs["1"][m]["runs"] == runs["3"][m]["runs"]
    assert main(["evaluate", *PLUGIN, "--scenario", "oscillator", "--methods", "ukf", "--threads", "0", "--quiet"]) == 2
    assert "--threads must be >= 1" in capsys.readouterr().err


@pytest.mark.slow
def test_train_then_evaluate_neural_next_to_classical(tmp_path, capsys):
    ckpt = tmp_path / "gru"
    assert (
        main(
            [
                "train",
                *PLUGIN,
                "--scenario",
                "oscillator",
                "--model",
                "gru",
                "--out",
                str(ckpt),
                "--trajectories",
                "32",
                "--train-length",
                "120",
                "--val-trajectories",
                "16",
                "--epochs",
                "2",
                "--windows-per-epoch",
                "64",
                "--quiet",
                "--no-keep-resume",
            ]
        )
        == 0
    )
    assert sorted(p.name for p in ckpt.iterdir()) == ["card.json", "model.safetensors", "step.onnx"]
    capsys.readouterr()
    assert (
        main(
            [
                "evaluate",
                *PLUGIN,
                "--scenario",
                "oscillator",
                "--methods",
                "ukf,gru",
                "--checkpoint",
                f"gru={ckpt}",
                "--trajectories",
                "20",
                "--horizon",
                "150",
                "--sets",
                "1",
                "--quiet",
                "--json",
            ]
        )
        == 0
    )
    res = json.loads(capsys.readouterr().out)
    assert set(res["methods"]) == {"ukf", "gru"}
    # a checkpoint for another scenario is refused with a message naming both
    assert (
        main(
            [
                "evaluate",
                "--scenario",
                "bearings",
                "--methods",
                "gru",
                "--checkpoint",
                f"gru={ckpt}",
                "--trajectories",
                "5",
                "--sets",
                "1",
                "--quiet",
            ]
        )
        == 2
    )
    assert "oscillator" in capsys.readouterr().err


# ---- long runs: per-step progress, cached runs, resume ------------------------------------------------


@pytest.mark.parametrize("method", ["ekf", "ukf", "enkf", "pf"])
def test_stepwise_run_equals_run_and_reports_every_step(oscillator, method):
    from neural_estimator.evaluation import run_stepwise

    data = simulate(oscillator, 7, 12, seed=2)
    opts = {"n_particles": 64} if method == "pf" else {}
    whole = make_estimator(method, oscillator, seed=3, **opts).run(data.y, data.u)
    calls = []
    stepped = run_stepwise(make_estimator(method, oscillator, seed=3, **opts), data.y, data.u, lambda: calls.append(1))
    np.testing.assert_array_equal(stepped.x, whole.x)
    np.testing.assert_array_equal(stepped.cov, whole.cov)
    assert len(calls) == 12
    # run_method reports B per time step for the filters: the calls add up to N T
    counts = []
    run_method(make_estimator(method, oscillator, seed=3, **opts), data, 3, (), on_steps=counts.append)
    assert sum(counts) == 7 * 12 and len(counts) == 3 * 12 and max(counts) == 3


def _count_builds(monkeypatch):
    import neural_estimator.evaluation.protocol as ev

    built = []
    real = ev.make_estimator

    def counting(method, *a, **k):
        built.append(method)
        return real(method, *a, **k)

    monkeypatch.setattr(ev, "make_estimator", counting)
    return built


def test_cached_runs_are_reused_and_keyed(oscillator, tmp_path, monkeypatch):
    built = _count_builds(monkeypatch)
    kw = dict(trajectories=20, horizon=15, sets=2, cache_dir=tmp_path, progress=False)
    first = evaluate(oscillator, ["ekf", "pf"], options={"pf": {"n_particles": 64}}, **kw)
    assert built == ["ekf", "pf"] and first["pf"].cached == 0
    assert len(list((tmp_path / "results").glob("oscillator-*.npz"))) == 4  # one file per (method, set)
    built.clear()
    # adding a method computes only that one; the others come from the cache, numbers identical
    second = evaluate(oscillator, ["ekf", "pf", "ukf"], options={"pf": {"n_particles": 64}}, **kw)
    assert built == ["ukf"] and second["ekf"].cached == 2 and second["pf"].cached == 2 and second["ukf"].cached == 0
    for m in ("ekf", "pf"):
        assert (
            results_json(oscillator, {m: second[m]})["methods"][m]["runs"]
            == results_json(oscillator, {m: first[m]})["methods"][m]["runs"]
        )
        assert second[m].seconds == first[m].seconds  # the time of the run that made them
    built.clear()
    # what defines the result is in the key: other options, seed or sets recompute; threads do not
    evaluate(oscillator, ["pf"], options={"pf": {"n_particles": 32}}, **kw)
    evaluate(oscillator, ["pf"], options={"pf": {"n_particles": 64, "threads": 2}}, **kw)
    assert built == ["pf"]
    built.clear()
    evaluate(oscillator, ["ekf"], **{**kw, "trajectories": 21})
    evaluate(oscillator, ["ekf"], recompute=True, **kw)  # forced
    assert built == ["ekf", "ekf"]
    built.clear()
    every = evaluate(oscillator, ["ekf"], warmup=0, **kw)["ekf"]  # the scored steps are keyed too
    again = evaluate(oscillator, ["ekf"], warmup=0, **kw)["ekf"]
    assert built == ["ekf"] and again.cached == 2
    scored = evaluate(oscillator, ["ekf"], **kw)["ekf"]  # the default: the paper's warm-up left out
    assert [r.warmup for r in scored.reports] == [10, 10] and [r.warmup for r in every.reports] == [0, 0]
    assert scored.reports[0].rmse_t.shape == (5,) and every.reports[0].rmse_t.shape == (15,)
    np.testing.assert_allclose(scored.reports[0].rmse_t, every.reports[0].rmse_t[10:])
    with pytest.raises(ValueError, match="warmup must be in \\[0, 15\\)"):
        evaluate(oscillator, ["ekf"], warmup=15, **kw)
    # a damaged cache entry is recomputed, not trusted
    built.clear()
    for f in (tmp_path / "results").glob("oscillator-ekf-*.npz"):
        f.write_bytes(b"not a zip")
    evaluate(oscillator, ["ekf"], **kw)
    assert built == ["ekf"]
    # no cache: nothing written
    before = sorted((tmp_path / "results").iterdir())
    evaluate(oscillator, ["ukf"], **{**kw, "cache_dir": False, "trajectories": 5})
    assert sorted((tmp_path / "results").iterdir()) == before


def test_interrupted_evaluate_resumes_from_finished_runs(tmp_path, capsys, monkeypatch):
    import neural_estimator.evaluation.protocol as ev

    out = tmp_path / "ev"
    args = [
        "evaluate",
        *PLUGIN,
        "--scenario",
        "oscillator",
        "--methods",
        "ekf,ukf",
        "--trajectories",
        "15",
        "--horizon",
        "20",
        "--sets",
        "2",
        "--quiet",
        "--out",
        str(out),
    ]
    real, calls = ev.run_method, []

    def interrupted(*a, **k):  # the third run is interrupted (Ctrl-C)
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(ev, "run_method", interrupted)
    assert main(args) == 130
    partial = json.loads((out / "results.json").read_text())
    assert (
        partial["complete"] is False and len(partial["methods"]["ekf"]["runs"]) == 2 and "ukf" not in partial["methods"]
    )
    capsys.readouterr()
    calls.clear()
    assert main(args) == 0  # resumes: only the two ukf runs are computed
    assert len(calls) == 2
    done = json.loads((out / "results.json").read_text())
    assert (
        done["complete"] is True
        and done["methods"]["ekf"]["cached_runs"] == 2
        and done["methods"]["ukf"]["cached_runs"] == 0
    )
    assert done["methods"]["ekf"]["runs"] == partial["methods"]["ekf"]["runs"]


# ---- one table and one JSON schema for every scenario and method ------------------------------------------


ZOO = Path(__file__).resolve().parents[1] / "neural_estimator" / "serving" / "zoo"


def test_same_columns_and_schema_for_every_scenario_and_method(tmp_path):
    from neural_estimator.metrics import SCALAR_METRICS
    from neural_estimator.paper import PAPER_SCENARIOS
    from neural_estimator.scenarios import scenario_names

    headers, report_keys, summary_keys = set(), set(), set()
    for name in PAPER_SCENARIOS:  # the zoo ships a GRU for each of the paper's five
        assert name in scenario_names()
        # the shipped GRU's own constants (the calibration changed some scenarios after the zoo was trained)
        card = json.loads((ZOO / f"{name}-gru" / "card.json").read_text())
        sc = make_scenario(name, **card["scenario"]["config"])
        res = evaluate(
            sc,
            ["ekf", "gru"],
            trajectories=3,
            horizon=14,
            sets=1,
            cache_dir=False,
            progress=False,
            options={"gru": {"covariance": False}},  # a method without a covariance (its head switched off)
        )
        headers.add(results_table(res, fmt="markdown").splitlines()[0])
        headers.add(results_table(res, fmt="csv").splitlines()[0])
        payload = json.loads(json.dumps(results_json(sc, res, complete=True), allow_nan=False))  # strict JSON
        assert payload["schema"] == "neural_estimator.results/2"
        for m, entry in payload["methods"].items():
            summary_keys.add(tuple(entry["summary"]))
            report_keys.add(tuple(entry["runs"][0]))
            assert set(entry) == {
                "summary",
                "runs",
                "cached_runs",
                "seconds",
                "trajectory_steps_per_second",
                "context",  # the bounded context served (0: continuous)
                "start",  # how a filter started (neural: prior, unused)
                "marks",  # the departures from the paper's protocol (neural_estimator/paper/departures.py)
                "rmse_components",  # one summary per state component, in state order
                "paired",  # the RMSE ratio to the best filter with its 95 % interval
                "paired_full",  # the same on the Full RMSE
                "reference_row",  # a baseline, never ranked
                "model_set",  # the wrong model it was told on purpose (--model-set; {} the true one)
                "instances",  # the trained instances run (count, RMSE of each, checkpoints)
            }
            assert len(entry["rmse_components"]) == sc.dx
            assert all(set(stat) == {"median", "iqr", "n", "max", "applies"} for stat in entry["rmse_components"])
            assert set(entry["paired"]) == {"reference", "ratio", "ci95", "verdict", "instances"}
            assert entry["runs"][0]["rmse_every_step"] >= 0
            assert all(set(stat) == {"median", "iqr", "n", "max", "applies"} for stat in entry["summary"].values())
        assert payload["methods"]["ekf"]["summary"]["nees_median"]["applies"] is True
        gru = payload["methods"]["gru"]
        assert gru["summary"]["nees"]["applies"] is False and gru["runs"][0]["nees"] is None
        assert gru["runs"][0]["has_covariance"] is False
    assert len(headers) == 2  # one markdown header and one csv header, the same for all five
    assert summary_keys == {tuple(SCALAR_METRICS)} and len(report_keys) == 1


def test_metrics_verb_json_is_strict_with_every_key(tmp_path, capsys, oscillator):
    """metrics --json: one schema for a method with covariances and one without, nulls not strings."""
    from neural_estimator.data import save_estimates
    from neural_estimator.metrics import SCALAR_METRICS

    data = simulate(oscillator, 6, 12, seed=4)
    est = make_estimator("ukf", oscillator).run(data.y, data.u)
    with_p = save_estimates(tmp_path / "ukf.npz", data, est.x, "ukf", P_hat=est.cov)
    x_bad = est.x.copy()
    x_bad[0, 3] = np.nan  # one diverged trajectory: Full RMSE and NRMSE are infinite
    without_p = save_estimates(tmp_path / "net.npz", data, x_bad, "net")
    assert main(["metrics", *PLUGIN, str(with_p), str(without_p), "--json"]) == 0
    raw = capsys.readouterr().out
    assert "Infinity" not in raw and "NaN" not in raw and '"inf"' not in raw
    methods = json.loads(raw)["methods"]
    assert set(methods["ukf"]) == set(methods["net"]) and set(SCALAR_METRICS) <= set(methods["net"])
    assert methods["net"]["full_rmse"] is None and methods["net"]["nrmse"] is None and methods["net"]["n_diverged"] == 1
    assert methods["net"]["nees_median"] is None and methods["net"]["has_covariance"] is False
    assert methods["ukf"]["nees_median"] > 0 and methods["ukf"]["cov_degenerate"] == 0.0
