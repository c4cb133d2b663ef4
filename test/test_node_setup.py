"""The setup the nodes share: the estimator and lifecycle nodes read their method's options
through one function (nodes/estimator_setup.py), and the evaluator and robot estimator resolve a
published type and throttle their warnings through one each (nodes/common.py). No ROS graph: the
functions are called with stand-in nodes."""

from __future__ import annotations

import dataclasses

import pytest

pytest.importorskip("rclpy")

from neural_estimator.nodes import common  # noqa: E402
from neural_estimator.nodes.common import StartupError, subscribable_class, warn_throttled  # noqa: E402
from neural_estimator.nodes.estimator_params import EstimatorParams  # noqa: E402
from neural_estimator.nodes.estimator_setup import checked_method, method_options  # noqa: E402


class _Logger:
    def __init__(self) -> None:
        self.lines: list[tuple[str, str]] = []

    def error(self, text: str) -> None:
        self.lines.append(("error", text))

    def warning(self, text: str) -> None:
        self.lines.append(("warning", text))


class _Node:
    def __init__(self) -> None:
        self.logger = _Logger()

    def get_logger(self) -> _Logger:
        return self.logger


def _params(**changes) -> EstimatorParams:
    return dataclasses.replace(EstimatorParams(), **changes)


def test_method_options_add_a_filters_start_but_not_a_models():
    p = _params(options=("n_particles=64",), init="observation")
    assert method_options("pf", p) == {"n_particles": "64", "init": "observation"}
    assert method_options("pf", _params(options=("init=prior",), init="observation"))["init"] == "prior"
    assert "init" not in method_options("gru", p)  # a neural method has no start to choose
    assert method_options("gru", p)["backend"] == "auto"  # the per-message backend, as replay's
    assert "init" not in method_options("ekf", _params())  # the default start is the filter's own


def test_an_option_that_is_not_name_value_is_one_startup_error():
    with pytest.raises(StartupError, match=r"options must be name=value, got \['n_particles'\]"):
        method_options("pf", _params(options=("n_particles",)))


@pytest.mark.parametrize(
    "changes, words",
    [
        (dict(method="kalmanette"), "kalmanette"),
        (dict(checkpoint="/no/such/checkpoint"), "does not exist"),
        (dict(observation_qos="fast"), "observation_qos must be one of"),
        (dict(history_depth=0), "history_depth must be >= 1"),
    ],
)
def test_the_parameters_both_estimator_nodes_check_before_building(changes, words):
    assert checked_method(_params(method="ekf")) == "ekf"
    with pytest.raises(StartupError, match=words):
        checked_method(_params(**changes))


def test_a_type_that_cannot_be_subscribed_is_refused_once():
    node, refused = _Node(), set()
    assert subscribable_class(node, "/odd", "no_such_pkg/msg/Thing", refused, "recorded") is None
    assert subscribable_class(node, "/odd", "no_such_pkg/msg/Thing", refused, "recorded") is None
    assert refused == {"/odd"}
    assert len(node.logger.lines) == 1
    level, text = node.logger.lines[0]
    assert level == "error" and text.startswith("'/odd': ") and text.endswith("; not recorded")
    cls = subscribable_class(node, "/js", "sensor_msgs/msg/JointState", refused, "recorded")
    assert cls is not None and cls.__name__ == "JointState" and refused == {"/odd"}


def test_warnings_of_one_kind_are_throttled_and_other_kinds_are_not(monkeypatch):
    now = [100.0]
    monkeypatch.setattr(common.time, "monotonic", lambda: now[0])
    node, last = _Node(), {}
    warn_throttled(node, last, "gap", "a", 2.0)
    warn_throttled(node, last, "gap", "b", 2.0)  # the same kind within 2 s: not logged
    warn_throttled(node, last, "held", "c", 2.0)  # another kind: logged
    now[0] += 2.0
    warn_throttled(node, last, "gap", "d", 2.0)  # 2 s later: logged again
    assert [t for _, t in node.logger.lines] == ["a", "c", "d"]
    assert {level for level, _ in node.logger.lines} == {"warning"}


@pytest.mark.parametrize("name, backend", [("lorenz96", "onnxruntime"), ("nlink", "torch")])
def test_the_estimator_nodes_host_the_hybrid(tmp_path, name, backend):
    """``method:=kalmannet`` goes through the networks' setup: its checkpoint, the per-message backend
    (the exported step where the system's f and h export, torch for N-link), a stream stepped message
    by message equal to the batched estimator, a dropped reading predicted through."""
    import numpy as np
    import torch

    from neural_estimator.data import simulate
    from neural_estimator.methods.registry import previous_controls
    from neural_estimator.models import build_model
    from neural_estimator.nodes.estimator_setup import build_online
    from neural_estimator.scenarios import make_scenario
    from neural_estimator.serving.checkpoint import save_checkpoint
    from neural_estimator.serving.export import export_beside
    from neural_estimator.serving.load import load_neural_estimator
    from neural_estimator.serving.normalization import Normalizer
    from neural_estimator.stream import messages as MSG

    scenario = make_scenario(name)
    data = simulate(scenario, 2, 10, seed=3)
    norm = Normalizer.from_data(scenario, data)
    torch.manual_seed(0)
    model = build_model("kalmannet", scenario)
    model.set_normalization(norm)
    save_checkpoint(tmp_path, model, norm, {"scenario": scenario.describe()})
    export_beside(tmp_path, scenario)
    p = _params(method="kalmannet", checkpoint=str(tmp_path))
    method = checked_method(p)
    assert method_options(method, p)["backend"] == "auto"
    est, online = build_online(method, scenario, p)
    assert est.backend == backend and est.covariance is None
    y = data.y[0].copy()
    y[4] = np.nan
    u = previous_controls(data.u)[0]
    got = []
    for k in range(10):
        (r,) = online.feed(MSG.encode_observation(scenario, k, 0, k, y[k], u[k]), 0.0)
        assert r.status == "estimated"
        got.append(r.x_hat)
    ref = load_neural_estimator("kalmannet", scenario, tmp_path, backend="torch").run(y[None], data.u[:1]).x[0]
    np.testing.assert_allclose(np.array(got), ref, rtol=1e-5, atol=1e-5 * float(np.max(norm.out_std)))


# ---- model_set: the model a model-based method is told --------------------------------------------------
def test_model_set_parameter_builds_the_model_based_methods_with_the_model_scenario():
    from neural_estimator.nodes.estimator_setup import model_note, told_scenario
    from neural_estimator.scenarios import make_scenario

    scenario = make_scenario("lorenz96")
    p = _params(model_set="forcing=9, Q=2")
    told = told_scenario("ekf", scenario, p)
    assert told.config.forcing == 9.0 and told.describe()["model_set"] == {"forcing": "9", "Q": "2"}
    assert told_scenario("gru", scenario, p) is scenario  # a data-trained network never sees it
    assert told_scenario("ekf", scenario, _params()) is scenario
    assert "forcing=9" in model_note("ekf", p) and model_note("gru", p) == ""


@pytest.mark.parametrize(
    "value, words",
    [("forcing", "expects name=value"), ("forcin=9", "no constant 'forcin'"), ("Q=-2", "Q must be a finite")],
)
def test_a_bad_model_set_is_one_startup_error_line(value, words):
    from neural_estimator.nodes.estimator_setup import told_scenario
    from neural_estimator.scenarios import make_scenario

    p = _params(model_set=value)
    with pytest.raises(StartupError, match=words) as info:
        checked_method(p)  # its form at start-up, before anything is built
        told_scenario("ekf", make_scenario("lorenz96"), p)  # its names and values with the scenario
    assert str(info.value).startswith("parameter model_set: ") and "\n" not in str(info.value)
