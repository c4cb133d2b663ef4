"""The mismatch sweep: filters told a wrong constant (or noise level), networks once, the paired
ratio to the best filter at every value and the interpolated crossover."""

from __future__ import annotations

import json

import pytest

from neural_estimator.cli import main
from neural_estimator.evaluation import evaluate
from neural_estimator.evaluation.mismatch import EXPERIMENT, crossover, mismatch, rows_csv
from neural_estimator.data.protocol import evaluation_sets
from neural_estimator.scenarios import make_scenario
from neural_estimator.scenarios.model import model_scenario

SMALL = dict(trajectories=4, sets=1, horizon=40, cache_dir=False)


def _points(errors, ratios, lows, highs):
    return [
        {"relative_error": e, "methods": {"net": {"ratio": r, "ci95": [lo, hi]}}}
        for e, r, lo, hi in zip(errors, ratios, lows, highs)
    ]


def test_crossover_interpolates_between_grid_points_on_each_side():
    pts = _points(
        [-0.5, -0.2, 0.0, 0.2, 0.5], [0.5, 1.1, 1.4, 1.2, 0.6], [0.4, 0.9, 1.3, 0.9, 0.5], [0.6, 1.3, 1.5, 1.3, 0.7]
    )
    c = crossover(pts, "net")
    assert c["above"]["at"] == pytest.approx(0.2 + 0.2 / 0.6 * 0.3)  # between e = 0.2 (1.2) and 0.5 (0.6)
    assert c["above"]["ci95"][0] == pytest.approx(0.0 + 0.3 / 0.4 * 0.2)  # the lower bound crosses first
    assert c["above"]["ci95"][1] == pytest.approx(0.2 + 0.3 / 0.6 * 0.3)
    assert c["below"]["at"] == pytest.approx(0.2 + 0.1 / 0.6 * 0.3)
    never = crossover(_points([0.0, 0.5], [1.5, 1.2], [1.4, 1.1], [1.6, 1.3]), "net")
    assert never["above"]["at"] is None and never["above"]["largest_error"] == 0.5 and never["below"] is None
    assert crossover(_points([0.0, 0.5], [0.9, 0.5], [0.8, 0.4], [1.1, 0.6]), "net")["above"]["at"] == 0.0


def test_filters_get_the_wrong_constant_and_the_network_runs_once():
    scenario = make_scenario("lorenz96")
    res = mismatch(scenario, "forcing", [0.8, 1.0, 1.25], ["ekf", "ukf", "gru"], **SMALL)
    rmse = {p["value"]: {m: row["rmse"] for m, row in p["methods"].items()} for p in res["points"]}
    assert len({r["gru"] for r in rmse.values()}) == 1  # the network does not see the model
    assert rmse[0.8]["ekf"] > rmse[1.0]["ekf"] and rmse[1.25]["ekf"] > rmse[1.0]["ekf"]
    (data,) = evaluation_sets(scenario, seed=0, trajectories=4, horizon=40, sets=1, cache_dir=False)
    wrong = evaluate(
        scenario,
        ["ekf"],
        datasets=[data],
        cache_dir=False,
        progress=False,
        model_scenario=model_scenario(scenario, {"forcing": repr(1.25 * 8.0)}),
    )
    assert rmse[1.25]["ekf"] == pytest.approx(wrong["ekf"].summary["rmse"].median)
    for p in res["points"]:
        best = p["best_filter"]
        assert p["methods"][best]["ratio"] == pytest.approx(1.0)
        assert all(p["methods"][best]["rmse"] <= p["methods"][m]["rmse"] for m in ("ekf", "ukf"))
    assert set(res["crossover"]) == {"network"} and res["crossover"]["network"]["method"] == "gru"
    json.dumps(res, allow_nan=False)  # strict JSON
    assert len(rows_csv(res).splitlines()) == 1 + 3 * 3


def test_noise_scale_sweep_tells_the_filters_another_covariance():
    res = mismatch(make_scenario("lorenz96"), "R", [0.1, 1.0], ["ekf"], **SMALL)
    assert res["true_value"] == 1.0
    assert res["points"][0]["methods"]["ekf"]["rmse"] != res["points"][1]["methods"]["ekf"]["rmse"]


def test_the_experiment_names_a_real_constant_of_each_scenario():
    from neural_estimator.evaluation.mismatch import true_value

    for name, parameters in EXPERIMENT.items():
        for parameter in parameters:
            assert true_value(make_scenario(name), parameter) > 0


@pytest.mark.parametrize(
    "flags, words",
    [
        (["--parameter", "forcin"], "no constant 'forcin'"),
        (["--parameter", "n_vars"], "not a real-valued constant"),
        (["--parameter", "forcing", "--values", "0,1"], "finite and > 0"),
        (["--parameter", "forcing", "--values", "a"], "comma-separated numbers"),
        (["--parameter", "forcing", "--methods", "gru"], "at least one filter"),
        ([], "--parameter"),
    ],
)
def test_mismatch_verb_errors_are_one_line(flags, words, capsys, tmp_path):
    argv = ["mismatch", "--scenario", "lorenz96", "--trajectories", "4", "--sets", "1", "--horizon", "30"]
    rc = main([*argv, "--no-cache", "--quiet", "--out", str(tmp_path), *flags])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and words in err and "\n" not in err


def test_mismatch_verb_writes_json_csv_and_figure(tmp_path, capsys):
    argv = ["mismatch", "--scenario", "lorenz96", "--parameter", "forcing", "--values", "0.9,1,1.1"]
    argv += ["--methods", "ekf,gru", "--trajectories", "4", "--sets", "1", "--horizon", "30", "--no-cache", "--quiet"]
    assert main([*argv, "--out", str(tmp_path)]) == 0
    assert "crossover of the network (gru)" in capsys.readouterr().out
    payload = json.loads((tmp_path / "lorenz96-forcing.json").read_text())
    assert payload["schema"] == "neural_estimator.mismatch/1" and payload["values"] == [0.9, 1.0, 1.1]
    assert (tmp_path / "lorenz96-forcing.csv").read_text().startswith("scenario,parameter,value")
    assert (tmp_path / "lorenz96-forcing.png").stat().st_size > 1000


def test_the_results_page_table_is_generated_from_the_committed_sweeps():
    import importlib.util
    from pathlib import Path

    from neural_estimator.evaluation.mismatch import crossover_text

    root = Path(__file__).resolve().parents[1]
    spec = importlib.util.spec_from_file_location("docs_generate", root / "docs" / "hooks" / "generate.py")
    generate = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(generate)
    table = generate.mismatch()
    assert "<!-- generate: mismatch -->" in (root / "docs" / "results.md").read_text()
    for scenario, parameters in EXPERIMENT.items():
        for parameter in parameters:
            r = json.loads((root / "docs/results/mismatch" / f"{scenario}-{parameter}.json").read_text())
            net = r["crossover"]["network"]
            assert f"| {scenario} | `{parameter}` (" in table
            for side, words in (("above", "too large"), ("below", "too small")):
                assert f"| {words} | {net['method']} {crossover_text(net[side])} |" in table
