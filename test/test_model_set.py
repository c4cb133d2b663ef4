"""A wrong model on purpose (``--model-set``): the model-based methods are built with the model
scenario, the data and the data-trained networks are not; every output and the cache key record it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from neural_estimator.cli import main
from neural_estimator.data.protocol import evaluation_sets
from neural_estimator.evaluation import evaluate, write_evaluation
from neural_estimator.evaluation.cache import run_key
from neural_estimator.methods import table
from neural_estimator.methods.registry import make_estimator
from neural_estimator.scenarios import ScenarioError, make_scenario
from neural_estimator.scenarios.model import model_scenario, model_set_of, parse_model_set
from neural_estimator.serving.load import EstimatorError, check_scenario


@pytest.fixture(scope="module")
def lorenz():
    scenario = make_scenario("lorenz96")
    (data,) = evaluation_sets(scenario, seed=3, trajectories=8, horizon=60, sets=1, cache_dir=False)
    return scenario, data


def test_model_scenario_changes_constants_and_scales_only_what_filters_are_told():
    s = make_scenario("lorenz96")
    m = model_scenario(s, {"forcing": "9", "Q": "2", "R": "0.5"})
    assert m.config.forcing == 9.0 and s.config.forcing != 9.0
    assert m.config.noise_scale == s.config.noise_scale  # the simulator's noise level is not what changes
    np.testing.assert_allclose(m.process_cov(), 2 * s.process_cov())
    np.testing.assert_allclose(m.obs_cov(), 0.5 * s.obs_cov())
    assert m.describe()["model_set"] == {"forcing": "9", "Q": "2", "R": "0.5"}
    assert model_set_of(m) == {"forcing": "9", "Q": "2", "R": "0.5"} and model_set_of(s) == {}
    assert model_scenario(s, {}) is s
    assert parse_model_set(" forcing=8.5, g=9.0 ") == {"forcing": "8.5", "g": "9.0"}


@pytest.mark.parametrize(
    "items, words",
    [
        ({"forcin": "9"}, "no constant 'forcin'"),
        ({"forcing": "abc"}, "forcing"),
        ({"Q": "0"}, "Q must be a finite scale > 0"),
        ({"R": "-1"}, "R must be a finite scale > 0"),
        ({"R": "x"}, "R must be a number"),
    ],
)
def test_bad_model_set_is_the_scenarios_one_line_error(items, words):
    with pytest.raises(ScenarioError, match=words) as info:
        model_scenario(make_scenario("lorenz96"), items)
    assert "\n" not in str(info.value)


def test_ekf_estimates_change_with_the_model_and_the_networks_do_not(lorenz):
    scenario, data = lorenz
    model = model_scenario(scenario, {"forcing": "9"})
    network = next(m for m in table.names(family="neural") if m == "gru")  # the shipped zoo model
    kwargs = dict(datasets=[data], cache_dir=False, progress=False)
    exact = evaluate(scenario, ["ekf", network], **kwargs)
    wrong = evaluate(scenario, ["ekf", network], model_scenario=model, **kwargs)
    assert wrong["ekf"].reports[0].rmse > exact["ekf"].reports[0].rmse * 1.05  # a wrong forcing costs accuracy
    np.testing.assert_array_equal(wrong[network].errors[0].mse, exact[network].errors[0].mse)
    assert wrong["ekf"].model_set == {"forcing": "9"} and wrong[network].model_set == {}
    direct = make_estimator("ekf", model, seed=0).run(data.y, data.u).x
    np.testing.assert_allclose(direct, make_estimator("ekf", model, seed=0).run(data.y, data.u).x)
    assert not np.allclose(direct, make_estimator("ekf", scenario, seed=0).run(data.y, data.u).x)


def test_cache_key_and_outputs_record_the_model(lorenz, tmp_path):
    scenario, data = lorenz
    model = model_scenario(scenario, {"forcing": "9"})
    keys = {run_key(s, "ekf", {}, None, 0, "cpu", "digest") for s in (scenario, model)}
    assert len(keys) == 2
    q = model_scenario(scenario, {"Q": "2"})  # a scale changes no constant: keyed all the same
    assert run_key(q, "ekf", {}, None, 0, "cpu", "digest") not in keys
    results = evaluate(scenario, ["ekf"], datasets=[data], cache_dir=False, progress=False, model_scenario=model)
    info = dict(trajectories=8, horizon=60, sets=1, seed=3, init="prior", warmup=10, model_set={"forcing": "9"})
    write_evaluation(tmp_path, scenario, results, info, {"ekf": 1}, plot=False)
    payload = json.loads((tmp_path / "results.json").read_text())
    assert payload["model_set"] == {"forcing": "9"} and payload["methods"]["ekf"]["model_set"] == {"forcing": "9"}
    assert payload["scenario"]["preset"]  # the data's preset, beside it
    header, row = (tmp_path / "table.csv").read_text().splitlines()[:2]
    assert header.endswith(",preset,model_set") and row.endswith(f",{payload['scenario']['preset']},forcing=9")


def test_cached_run_of_another_model_is_not_reused(lorenz, tmp_path):
    scenario, data = lorenz
    kwargs = dict(datasets=[data], cache_dir=tmp_path, progress=False)
    evaluate(scenario, ["ekf"], **kwargs)
    again = evaluate(scenario, ["ekf"], model_scenario=model_scenario(scenario, {"forcing": "9"}), **kwargs)
    assert again["ekf"].cached == 0
    assert evaluate(scenario, ["ekf"], **kwargs)["ekf"].cached == 1


def test_a_hybrid_checkpoint_accepts_the_model_sets_constants_only():
    scenario = make_scenario("lorenz96")
    card = scenario.describe()  # a checkpoint trained on the true system
    check_scenario(card, model_scenario(scenario, {"forcing": "9", "Q": "2"}), "ckpt")
    with pytest.raises(EstimatorError, match="other constants"):
        check_scenario(card, make_scenario("lorenz96", forcing=9.0), "ckpt")


@pytest.mark.parametrize(
    "flags, words",
    [
        (["--model-set", "forcin=9"], "no constant 'forcin'"),
        (["--model-set", "Q=0"], "Q must be a finite scale > 0"),
        (["--model-set", "forcing"], "expects NAME=VALUE"),
    ],
)
def test_evaluate_flag_errors_are_one_line(flags, words, capsys):
    rc = main(["evaluate", "--scenario", "lorenz96", "--methods", "ekf", "--no-cache", "--quiet", *flags])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and words in err and "\n" not in err


def test_evaluate_verb_records_the_model_set(tmp_path, capsys):
    out = tmp_path / "ev"
    argv = ["evaluate", "--scenario", "lorenz96", "--methods", "ekf", "--trajectories", "4", "--horizon", "40"]
    argv += [
        "--sets",
        "1",
        "--no-cache",
        "--quiet",
        "--model-set",
        "forcing=9",
        "--model-set",
        "R=2",
        "--out",
        str(out),
    ]
    assert main(argv) == 0
    assert "forcing=9, R=2" in capsys.readouterr().out
    assert json.loads((out / "results.json").read_text())["model_set"] == {"forcing": "9", "R": "2"}


def test_replay_builds_the_filters_with_the_model_set(tmp_path, capsys):
    pytest.importorskip("rosbags")
    bag = str(Path(__file__).resolve().parents[1] / "bags" / "lorenz96.mcap")
    argv = ["replay", bag, "--methods", "ekf", "--metrics", "--overwrite"]
    assert main([*argv, "--out", str(tmp_path / "a.mcap")]) == 0
    exact = capsys.readouterr().out
    assert main([*argv, "--out", str(tmp_path / "b.mcap"), "--model-set", "forcing=9"]) == 0
    wrong = capsys.readouterr().out
    assert "told a wrong model on purpose (--model-set): forcing=9" in wrong
    row = [line for line in exact.splitlines() if line.startswith("ekf ")]
    assert row and row[0] not in wrong  # the EKF's row of numbers changed
    assert main([*argv, "--out", str(tmp_path / "c.mcap"), "--model-set", "forcin=9"]) == 2
    assert "no constant 'forcin'" in capsys.readouterr().err
