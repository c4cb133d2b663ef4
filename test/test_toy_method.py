"""Adding a method is one table entry plus its code (docs/architecture.md, "Adding a method"): a toy
"mean of the prior" (test/toy_method.py, its only file), registered in a temporary table, is built by
make_estimator, run by evaluate and the evaluate verb, accepted by the estimator node's parameters
and by the name-list tests, and leaves nothing behind."""

from __future__ import annotations

import json

import numpy as np
import pytest
import test_method_table as names_tests
import toy_method

from neural_estimator import metrics as M
from neural_estimator.data import simulate
from neural_estimator.evaluation import evaluate
from neural_estimator.methods import table
from neural_estimator.methods.interface import EstimatorError, check_method
from neural_estimator.methods.registry import make_estimator
from neural_estimator.scenarios import make_scenario

TOY = toy_method.NAME


@pytest.fixture
def toy(monkeypatch):
    """The table with the toy method appended, for this test only."""
    monkeypatch.setattr(table, "TABLE", (*table.TABLE, toy_method.SPEC))
    yield toy_method.SPEC
    monkeypatch.undo()
    assert not table.has(TOY)  # nothing left behind
    with pytest.raises(EstimatorError, match="unknown method"):
        check_method(TOY)


def test_without_registration_the_toy_is_unknown():
    assert not table.has(TOY)
    with pytest.raises(EstimatorError, match="unknown method 'toymean'"):
        make_estimator(TOY, make_scenario("ballistic"))


def test_make_estimator_builds_the_toy_and_its_queries_answer(toy):
    s = make_scenario("ballistic")
    est = make_estimator(TOY, s, seed=3)
    assert isinstance(est, toy_method.MeanOfPrior) and est.seed == 3
    data = simulate(s, 3, 12, seed=1)
    x = est.run(data.y, data.u).x
    assert np.array_equal(x, np.broadcast_to(s.prior()[0], x.shape))  # the prior mean at every step
    assert TOY in table.names() and TOY in table.names(family="classical") and TOY not in table.names(takes_init=True)
    assert check_method("Toy-Mean") == TOY


def test_evaluate_runs_the_toy_beside_a_filter(toy):
    s = make_scenario("ballistic")
    results = evaluate(s, ["ekf", TOY], trajectories=6, horizon=20, sets=1, cache_dir=False, progress=False)
    toy_rmse = results[TOY].summary["rmse"].median
    assert np.isfinite(toy_rmse) and toy_rmse > results["ekf"].summary["rmse"].median  # a prior mean is no filter
    assert results[TOY].init == "prior"  # it takes no start mode


@pytest.mark.slow  # a second or more: it imports torch, walks the package or runs a verb
def test_the_evaluate_verb_takes_the_toy(toy, tmp_path, capsys):
    from neural_estimator.cli import main

    out = tmp_path / "ev"
    argv = ["evaluate", "--scenario", "ballistic", "--methods", f"ekf,{TOY}", "--trajectories", "4"]
    assert main([*argv, "--horizon", "15", "--sets", "1", "--out", str(out), "--no-cache"]) == 0
    assert f"{TOY} " in capsys.readouterr().out
    written = json.loads((out / "results.json").read_text())
    assert set(written["methods"]) == {"ekf", TOY} and written["methods"][TOY]["summary"]["rmse"]["median"] > 0


@pytest.mark.slow  # a second or more: it imports torch, walks the package or runs a verb
def test_the_name_lists_take_the_toy_with_no_edit(toy):
    """The lists shown to people are generated from the table, so the toy is on each; no literal list
    of names had to learn it."""
    assert names_tests.demo_methods().split(",")[-1] == TOY
    assert names_tests.node_help_methods() == list(table.names())
    assert TOY in names_tests.documented_methods()
    assert names_tests.package_collections() <= names_tests.ALLOWED


@pytest.mark.ros
def test_the_estimator_node_runs_the_toy(toy):
    rclpy = pytest.importorskip("rclpy")
    from neural_estimator.stream import messages as B
    from neural_estimator.nodes.estimator_node import EstimatorNode

    rclpy.init(args=["--ros-args", "-p", f"method:={TOY}", "-p", "scenario:=ballistic"])
    try:
        node = EstimatorNode()
        try:
            assert isinstance(node.online.estimator, toy_method.MeanOfPrior)
            labels = B.observation_labels(node.online.scenario)
            node._on_observation(B.encode_vector(0, "ballistic", 0, 0, labels, np.ones(len(labels))))
            assert node.stats.estimated == 1 and node.context.ok()
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown()


def test_metrics_of_the_toy_are_those_of_the_prior_mean(toy):
    """evaluate's numbers for the toy are the metrics of the prior mean on the same trajectories."""
    s = make_scenario("ballistic")
    data = simulate(s, 5, 20, seed=7)
    results = evaluate(s, [TOY], datasets=[data], cache_dir=False, progress=False)
    x_hat = np.broadcast_to(s.prior()[0], data.x.shape).copy()
    want = M.compute_labelled_metrics(data.x, x_hat, s.angle_states, data.labelled, warmup=M.EVALUATION_WARMUP)
    assert results[TOY].reports[0].rmse == want.rmse
