"""The batch-1 step forms that Mamba, Mamba-2, GPT-2 and Filterformer export (models/onnx_forms.py):
equal to the models' own step, deterministic, and the operator fusions they are written for fire in
ONNX Runtime."""

from __future__ import annotations

import collections
import json

import numpy as np
import pytest
import torch

pytest.importorskip("onnxruntime")
pytest.importorskip("onnx")

from neural_estimator.models.onnx_step import export_step  # noqa: E402
from neural_estimator.scenarios import make_scenario  # noqa: E402
from neural_estimator.serving.load import load_neural_estimator  # noqa: E402

FORMS = ["mamba", "mamba2", "gpt2", "filterformer"]
ATTENTION = ("gpt2", "filterformer")


@pytest.fixture(scope="module")
def l96():
    return make_scenario("lorenz96")


def _model(l96, method: str, window: int = 0):
    """The shipped Lorenz 96 model with its covariance head (a ``GaussianModel``), an attention model
    with a short window when asked (so that the ring buffer wraps many times)."""
    model = load_neural_estimator(method, l96, context=window).model
    assert type(model).__name__ == "GaussianModel"
    return model


@pytest.mark.parametrize("method", FORMS)
def test_step_form_equals_the_models_step(method, l96):
    """300 steps of inputs of unit size (the attention models with a window of 7: the cache wraps 42
    times), through the model's ``step_with_cov`` and its form's: estimates and covariances within
    1e-5 relative."""
    model = _model(l96, method, window=7 if method in ATTENTION else 0)
    form = model.onnx_form().eval()
    assert type(form.trunk).__name__.endswith("StepForm") and type(form.cov_head).__name__ == "_CholeskyStepForm"
    gen = torch.Generator().manual_seed(3)
    a_state, b_state = model.init_state(1), form.init_state(1)
    worst = 0.0
    with torch.no_grad():
        for _ in range(300):
            z = torch.randn(1, model.input_proj.in_features, generator=gen)
            mean_a, cov_a, a_state = model.step_with_cov(z, a_state)
            mean_b, cov_b, b_state = form.step_with_cov(z, b_state)
            worst = max(worst, float((mean_a - mean_b).abs().max() / (1.0 + mean_a.abs().max())))
            worst = max(worst, float((cov_a - cov_b).abs().max() / (1.0 + cov_a.abs().max())))
    assert worst < 1e-5, worst


def test_a_form_steps_one_stream_and_a_model_without_one_is_traced_itself(l96):
    form = _model(l96, "mamba").trunk.onnx_form()
    with pytest.raises(ValueError, match="batch 1"):
        form.init_state(2)
    with pytest.raises(NotImplementedError):
        form.features(torch.zeros(1, 3, form.input_proj.in_features))
    gru = _model(l96, "gru")
    assert gru.onnx_form().trunk is gru.trunk  # no form of its own: the GRU's graph is its step (and the head's form)


def test_the_covariance_heads_step_form_equals_the_head():
    """The head's form gives the head's covariance, the calibration scale and a correlation
    shrinkage included, for read-outs that reach the clamp of the log-diagonal: 1e-6 relative."""
    from neural_estimator.serving.uncertainty.heads import CholeskyHead

    gen = torch.Generator().manual_seed(5)
    head = CholeskyHead(12, 5)
    with torch.no_grad():
        head.linear.weight.copy_(torch.randn(head.linear.weight.shape, generator=gen) * 3.0)
        head.linear.bias.copy_(torch.randn(head.linear.bias.shape, generator=gen))
        head.unit.copy_(torch.rand(5, generator=gen) + 0.1)
        head.scale.copy_(torch.rand(5, generator=gen) + 0.5)
    for shrink in (0.0, 0.3):
        head.shrink = shrink
        form = head.onnx_form()
        for _ in range(50):
            h = torch.randn(1, 12, generator=gen) * 4.0
            with torch.no_grad():
                want, got = head(h), form(h)
            assert got.dtype == want.dtype == torch.float64 and got.shape == want.shape == (1, 5, 5)
            assert float((got - want).abs().max() / want.abs().max()) < 1e-6


def test_step_form_export_is_reproducible(l96):
    """The same checkpoint gives the same bytes through a form too (its constants are computed from
    the weights at export)."""
    for method in ("mamba2", "gpt2"):
        a = export_step(_model(l96, method), method, covariance=True)
        b = export_step(_model(l96, method), method, covariance=True)
        assert a == b, method


def _optimized_ops(data: bytes, tmp_path) -> collections.Counter:
    """Operator counts of the graph as ONNX Runtime runs it (the serving session's optimisation
    level), read back from the optimised model it writes."""
    import onnx
    import onnxruntime as ort

    path = tmp_path / "optimized.onnx"
    opts = ort.SessionOptions()
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.optimized_model_filepath = str(path)
    opts.log_severity_level = 3  # its note that an optimised file is machine specific
    ort.InferenceSession(data, opts, providers=["CPUExecutionProvider"])
    return collections.Counter(n.op_type for n in onnx.load(str(path)).graph.node)


@pytest.mark.parametrize("method", FORMS)
def test_the_fusions_the_forms_are_written_for_fire(method, l96, tmp_path):
    """Each (RMS)LayerNorm is one operator, each GELU one (Gelu, GPT-2's tanh form FastGelu), each
    SiLU one QuickGelu; no transposing or gathering operator is left in the SSM graphs, and the
    attention caches are written with one ScatterND per layer and tensor (no Slice, Concat or Where
    copies them)."""
    model = _model(l96, method).trunk
    ops = _optimized_ops(export_step(model, method), tmp_path)
    assert not ops["ReduceMean"] and not ops["Tanh"] and not ops["Erf"] and not ops["Sigmoid"], ops
    if method in ATTENTION:
        L = model.cfg.n_layer if method == "gpt2" else 1
        assert ops["LayerNormalization"] == 2 * L + 1 and ops["FastGelu" if method == "gpt2" else "Gelu"] == L, ops
        assert ops["ScatterND"] == 2 * L + 1, ops  # + the slots' ages
        assert not ops["Concat"] and not ops["Slice"] and not ops["Where"], ops
        return
    L = model.cfg.n_layer
    norms = (2 if method == "mamba2" else 1) * L + 1  # Mamba-2's gated RMSNorm in every mixer too
    assert ops["SimplifiedLayerNormalization"] == norms and ops["QuickGelu"] == 2 * L, ops
    assert not any(ops[op] for op in ("Unsqueeze", "Squeeze", "Transpose", "Gather")), ops
    if method == "mamba":  # (Mamba-2 views its state as (H, P N) and (E, N): Reshapes that copy nothing)
        assert not ops["Reshape"], ops
    assert ops["Concat"] == L and ops["Slice"] == L, ops  # the conv window's shift, once a layer


def test_the_shipped_graphs_serve_the_forms_state():
    """A shipped step.onnx of each form's model has the form's state: the attention models' first
    state is the slots' ages (+inf at reset), the SSMs' states carry no batch axis."""
    import json

    from neural_estimator.serving.card import default_checkpoint
    from neural_estimator.serving.onnx_runtime import ONNX_FILE, OrtStep

    for method in FORMS:
        step = OrtStep(default_checkpoint("lorenz96", method) / ONNX_FILE)
        fills = json.loads(step.metadata["initial_fill"])
        if method in ATTENTION:
            assert fills[0] == float("inf") and step.state[0].shape == (int(step.metadata["window"]),)
            assert step.inplace and 0 not in step.inplace  # the caches in place, the ages double-buffered
        else:
            assert all(f == 0.0 for f in fills) and all(s.ndim == 2 for s in step.state), method
        assert np.all(np.isfinite(step.step(np.zeros((1, step.d_in), dtype=np.float32))))


@pytest.mark.parametrize("method", FORMS)
def test_the_attention_caches_are_updated_in_place_and_nothing_else(method, l96):
    """An attention graph lists its KV caches in ``inplace_states`` (each read by its ScatterND
    alone), and ``OrtStep`` keeps one buffer for each; 300 steps over a window of 7 (the caches wrap)
    equal, to the bit, the same graph served double-buffered (the list removed). The SSM graphs list
    nothing: their states have other readers."""
    import onnx

    from neural_estimator.serving.onnx_runtime import OrtStep

    model = _model(l96, method, window=7 if method in ATTENTION else 0).trunk
    data = export_step(model, method)
    graph = onnx.load_from_string(data)
    meta = {p.key: p.value for p in graph.metadata_props}
    if method not in ATTENTION:
        assert "inplace_states" not in meta and OrtStep(data).inplace == ()
        return
    L = model.cfg.n_layer if method == "gpt2" else 1
    assert json.loads(meta["inplace_states"]) == list(range(1, 2 * L + 1))  # not the ages: other readers
    shared = OrtStep(data)
    assert shared.inplace == tuple(range(1, 2 * L + 1))
    assert all(shared._sets[0][k] is shared._sets[1][k] for k in shared.inplace)
    kept = [p for p in graph.metadata_props if p.key != "inplace_states"]
    del graph.metadata_props[:]
    graph.metadata_props.extend(kept)
    double = OrtStep(graph.SerializeToString())
    assert double.inplace == ()
    gen = np.random.default_rng(5)
    for _ in range(300):
        z = gen.standard_normal((1, shared.d_in)).astype(np.float32)
        np.testing.assert_array_equal(shared.step(z), double.step(z))


def test_inplace_states_needs_a_scatter_that_is_the_states_only_reader():
    import onnx
    from onnx import TensorProto, helper

    from neural_estimator.models.onnx_step import inplace_states

    def graph(extra_reader: bool):
        s = helper.make_tensor_value_info("state_0", TensorProto.FLOAT, [4, 2])
        idx = helper.make_tensor_value_info("idx", TensorProto.INT64, [1, 1])
        upd = helper.make_tensor_value_info("upd", TensorProto.FLOAT, [1, 2])
        out = [helper.make_tensor_value_info("new_state_0", TensorProto.FLOAT, [4, 2])]
        nodes = [helper.make_node("ScatterND", ["state_0", "idx", "upd"], ["new_state_0"])]
        if extra_reader:
            out.append(helper.make_tensor_value_info("total", TensorProto.FLOAT, []))
            nodes.append(helper.make_node("ReduceSum", ["state_0"], ["total"], keepdims=0))
        return onnx.helper.make_graph(nodes, "g", [s, idx, upd], out)

    assert inplace_states(graph(False)) == [0]
    assert inplace_states(graph(True)) == []  # the sum could read rows the scatter already wrote
