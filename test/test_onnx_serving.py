"""The ONNX Runtime backend: the exported step equals the torch step, through the estimator interface."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("onnxruntime")
pytest.importorskip("onnx")

from neural_estimator.data import simulate  # noqa: E402
from neural_estimator.estimator import EstimatorError  # noqa: E402
from neural_estimator.models.onnx_step import OrtStep, export_step  # noqa: E402
from neural_estimator.serving.load import load_neural_estimator  # noqa: E402
from neural_estimator.scenarios import make_scenario  # noqa: E402


@pytest.fixture(scope="module")
def l96():
    scen = make_scenario("lorenz96")
    return scen, simulate(scen, 1, 300, 4)


@pytest.mark.slow
@pytest.mark.parametrize("method", ["gru", "lstm", "mamba", "mamba2"])
def test_onnx_step_equals_torch_step(method, l96):
    scen, data = l96
    torch_est = load_neural_estimator(method, scen, context=0)
    ort_est = load_neural_estimator(method, scen, context=0, backend="onnxruntime")
    y = data.y[0].copy()
    y[50] = np.nan  # a missing observation: both use the training mean
    torch_est.reset(1)
    ort_est.reset(1)
    worst = 0.0
    for k in range(y.shape[0]):
        a = torch_est.step(y[k : k + 1])
        b = ort_est.step(y[k : k + 1])
        assert b.shape == a.shape == (1, scen.dx) and b.dtype == np.float64
        assert ort_est.skipped[0] == torch_est.skipped[0] == (k == 50)
        worst = max(worst, float(np.abs(a - b).max() / (1.0 + np.abs(a).max())))
    assert worst < 1e-5, worst
    # a reset starts over: the first estimates repeat
    ort_est.reset(1)
    torch_est.reset(1)
    np.testing.assert_allclose(ort_est.step(y[:1]), torch_est.step(y[:1]), rtol=1e-5, atol=1e-5)


def test_onnx_backend_refuses_what_it_cannot_serve(l96):
    scen, data = l96
    with pytest.raises(EstimatorError, match="backend onnxruntime serves"):
        load_neural_estimator("gpt2", scen, backend="onnxruntime")
    with pytest.raises(EstimatorError, match="backend must be one of"):
        load_neural_estimator("gru", scen, backend="tensorrt")
    est = load_neural_estimator("gru", scen, context=0, backend="onnxruntime")
    with pytest.raises(EstimatorError, match="batch 1"):
        est.reset(2)
    with pytest.raises(EstimatorError, match="observation must be"):
        est.step(np.zeros((1, scen.dy + 1)))
    # a one-dimensional observation goes through the full checks and still works
    est.reset(1)
    assert est.step(data.y[0, 0]).shape == (1, scen.dx)


def test_export_is_reproducible_from_the_checkpoint(tmp_path, l96):
    """The same card and weights give the same graph, and a graph file serves without the estimator."""
    scen, data = l96
    a = export_step(load_neural_estimator("gru", scen, context=0).model, "gru", tmp_path / "a.onnx")
    b = export_step(load_neural_estimator("gru", scen, context=0).model, "gru")
    assert a == b
    step = OrtStep(tmp_path / "a.onnx")
    out1 = step.step(np.ones((1, step.d_in), dtype=np.float32)).copy()
    step.reset()
    out2 = step.step(np.ones((1, step.d_in), dtype=np.float32)).copy()
    np.testing.assert_array_equal(out1, out2)
    assert not np.array_equal(out1, step.step(np.ones((1, step.d_in), dtype=np.float32)))  # the state moved


def test_normalised_graph_is_the_whole_estimator_step(l96):
    """With the card's normalisation inside, the graph alone (numpy + onnxruntime, no torch at serving)
    gives the estimator's estimates, a missing observation included."""
    scen, data = l96
    est = load_neural_estimator("mamba", scen, context=0)
    step = OrtStep(export_step(est.model, "mamba", normalizer=est.normalizer))
    assert step.normalized and set(step.outputs) == {"x", "skipped"}
    y = data.y[0, :40].copy()
    y[7, 3] = np.inf
    est.reset(1)
    for k in range(len(y)):
        np.copyto(step.inputs["y"], y[k : k + 1])
        step.run()
        want = est.step(y[k : k + 1])
        np.testing.assert_allclose(step.outputs["x"], want, rtol=1e-5, atol=1e-5)
        assert bool(step.outputs["skipped"][0, 0]) == (k == 7)
