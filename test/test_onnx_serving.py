"""The ONNX Runtime backend: the exported step equals the torch step, through the estimator interface."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("onnxruntime")
pytest.importorskip("onnx")

from neural_estimator.data import simulate  # noqa: E402
from neural_estimator.methods.interface import EstimatorError  # noqa: E402
from neural_estimator.models.onnx_step import export_step  # noqa: E402
from neural_estimator.serving.onnx_runtime import OrtStep  # noqa: E402
from neural_estimator.serving.load import load_neural_estimator  # noqa: E402
from neural_estimator.scenarios import make_scenario  # noqa: E402
from ros_tester import fresh_domain  # noqa: E402


@pytest.fixture(scope="module")
def l96():
    scen = make_scenario("lorenz96")
    return scen, simulate(scen, 1, 300, 4)


@pytest.mark.slow
@pytest.mark.parametrize("method", ["gru", "lstm", "gpt2", "filterformer", "mamba", "mamba2"])
def test_onnx_step_equals_torch_step(method, l96, tmp_path):
    """The step exported at load (a checkpoint without step.onnx beside its card): 300 steps (GPT-2
    and Filterformer: past a window of 100, so the KV cache wraps), a missing observation included;
    estimates (and the covariance) within 1e-5 relative."""
    import shutil

    from neural_estimator.serving.card import default_checkpoint

    scen, data = l96
    context = 100 if method in ("gpt2", "filterformer") else 0
    directory = tmp_path / method
    shutil.copytree(default_checkpoint("lorenz96", method), directory, ignore=shutil.ignore_patterns("step.onnx"))
    torch_est = load_neural_estimator(method, scen, directory, context=context)
    ort_est = load_neural_estimator(method, scen, directory, context=context, backend="onnxruntime")
    assert type(ort_est).__name__ == "NeuralEstimator" and ort_est.backend == "onnxruntime"
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
        if torch_est.has_covariance:
            assert ort_est.has_covariance
            P, Q = torch_est.covariance, ort_est.covariance
            worst = max(worst, float(np.abs(P - Q).max() / (1.0 + np.abs(P).max())))
    assert worst < 1e-5, worst
    # a reset starts over: the first estimates repeat
    ort_est.reset(1)
    torch_est.reset(1)
    np.testing.assert_allclose(ort_est.step(y[:1]), torch_est.step(y[:1]), rtol=1e-5, atol=1e-5)


@pytest.mark.slow
@pytest.mark.parametrize("method", ["gru", "lstm", "mamba", "mamba2", "kalmannet"])
def test_bounded_context_onnx_step_equals_the_batched_copies(method, l96, tmp_path):
    """A recurrent model with its context bounded (L = 30 steps, K = 4 restarted copies), exported
    at load as its copies' step at batch K: 150 steps, so every copy restarts four or five times and
    the served copy changes at every restart past step L, a missing observation included (the
    hybrid's reaches it as NaN); the estimates and covariances equal those of torch's BatchedCopies
    within 1e-5 relative at every step."""
    import shutil

    from neural_estimator.serving.card import default_checkpoint
    from neural_estimator.serving.context import copy_offsets, restart_of

    scen, data = l96
    directory = tmp_path / method
    shutil.copytree(default_checkpoint("lorenz96", method), directory, ignore=shutil.ignore_patterns("step.onnx"))
    bounded = {"context": 30, "context_copies": 4}
    torch_est = load_neural_estimator(method, scen, directory, **bounded)
    ort_est = load_neural_estimator(method, scen, directory, backend="onnxruntime", **bounded)
    assert torch_est.context_by_copies and ort_est._ort.context_by_copies and ort_est._ort.context_copies == 4
    assert ort_est.has_covariance == torch_est.has_covariance
    graph = ort_est._ort.ort
    y = data.y[0, :150].copy()
    y[50] = np.nan
    torch_est.reset(1)
    ort_est.reset(1)
    served, worst = [], 0.0
    for k in range(y.shape[0]):
        a = torch_est.step(y[k : k + 1])
        b = ort_est.step(y[k : k + 1])
        served.append(int(graph.inputs["copy"][0]))
        assert ort_est.skipped[0] == torch_est.skipped[0] == (k == 50)
        worst = max(worst, float(np.abs(a - b).max() / (1.0 + np.abs(a).max())))
        if torch_est.has_covariance:
            P, Q = torch_est.covariance, ort_est.covariance
            worst = max(worst, float(np.abs(P - Q).max() / (1.0 + np.abs(P).max())))
    assert worst < 1e-5, worst
    # the served copy is the one whose last restart is s(t), the oldest: copy 0 until step L, then each in turn
    offsets = copy_offsets(30, 4)
    assert served[:30] == [0] * 30 and set(served) == {0, 1, 2, 3}
    for t, k in enumerate(served):
        assert offsets[k] <= t and offsets[k] + (t - offsets[k]) // 30 * 30 == restart_of(t, 30, 4), t
    ort_est.reset(1)  # a reset starts over: the first estimate repeats
    torch_est.reset(1)
    np.testing.assert_allclose(ort_est.step(y[:1]), torch_est.step(y[:1]), rtol=1e-5, atol=1e-5)


def test_onnx_backend_refuses_what_it_cannot_serve(l96):
    scen, data = l96
    with pytest.raises(EstimatorError, match="serves the unbounded context"):  # the graph beside it is unbounded
        load_neural_estimator("gru", scen, context=50, backend="onnxruntime")
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
    # the K restarted copies' step too, and it is not the unbounded one
    bounded = [export_step(load_neural_estimator("gru", scen, context=0).model, "gru", copies=(20, 4)) for _ in "ab"]
    assert bounded[0] == bounded[1] != a


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


def _exported_beside(tmp_path, method):
    """A copy of the shipped lorenz96 checkpoint with its step exported beside the card."""
    import shutil

    from neural_estimator.serving.card import default_checkpoint
    from scripts.export_onnx import main as export_main

    directory = tmp_path / f"lorenz96-{method}"
    shutil.copytree(default_checkpoint("lorenz96", method), directory)
    assert export_main(["--scenario", "lorenz96", "--method", method, "--checkpoint", str(directory), "--beside"]) == 0
    return directory


@pytest.mark.parametrize("method", ["gpt2", "filterformer"])
def test_graph_beside_the_card_serves_like_the_torch_step(method, l96, tmp_path):
    """``step.onnx`` beside the card: backend onnxruntime serves it (the torch-free estimator), equal to
    the torch step within 1e-5 relative over 300 steps, covariance included."""
    from neural_estimator.serving.onnx_runtime import OnnxEstimator

    scen, data = l96
    directory = _exported_beside(tmp_path, method)
    ort_est = load_neural_estimator(method, scen, checkpoint=directory, backend="onnxruntime")
    torch_est = load_neural_estimator(method, scen, checkpoint=directory)
    assert isinstance(ort_est, OnnxEstimator) and ort_est.has_covariance == torch_est.has_covariance
    y = data.y[0]
    ort_est.reset(1)
    torch_est.reset(1)
    worst = 0.0
    for k in range(y.shape[0]):
        a, b = torch_est.step(y[k : k + 1]), ort_est.step(y[k : k + 1])
        worst = max(worst, float(np.abs(a - b).max() / (1.0 + np.abs(a).max())))
        if torch_est.has_covariance:
            P, Q = torch_est.covariance, ort_est.covariance
            worst = max(worst, float(np.abs(P - Q).max() / (1.0 + np.abs(P).max())))
    assert worst < 1e-5, worst
    # run is a loop of step
    est = ort_est.run(data.y[:1, :20])
    ort_est.reset(1)
    np.testing.assert_array_equal(est.x[0, 19], [ort_est.step(y[k : k + 1])[0] for k in range(20)][-1])


def test_graph_beside_the_card_refuses_other_weights_and_windows(l96, tmp_path):
    import json

    scen, _ = l96
    directory = _exported_beside(tmp_path, "gpt2")
    with pytest.raises(EstimatorError, match="attention window"):
        load_neural_estimator("gpt2", scen, checkpoint=directory, backend="onnxruntime", context=7)
    card = json.loads((directory / "card.json").read_text())
    card["weights"]["sha256"] = "0" * 64  # the card now names other weights than those exported
    (directory / "card.json").write_text(json.dumps(card))
    with pytest.raises(EstimatorError, match="export it again"):
        load_neural_estimator("gpt2", scen, checkpoint=directory, backend="onnxruntime")


_NO_TORCH = """
import sys
sys.modules["torch"] = None  # `import torch` now raises ImportError
"""


@pytest.mark.slow
def test_served_without_torch_step_and_node(tmp_path):
    """With step.onnx beside the card, ``Estimator.step`` and the estimator node run where torch cannot
    be imported: the estimator is built and stepped, and the node builds it, steps its warm-up and
    says so, then exits cleanly on SIGINT."""
    import os
    import signal
    import subprocess
    import sys
    import time

    directory = _exported_beside(tmp_path, "gru")
    step_code = (
        _NO_TORCH
        + f"""
import numpy as np
from neural_estimator.methods.registry import make_estimator
from neural_estimator.scenarios import make_scenario
scen = make_scenario("lorenz96")
est = make_estimator("gru", scen, checkpoint={str(directory)!r}, backend="onnxruntime")
est.reset(1)
x = est.step(np.zeros((1, scen.dy)))
assert x.shape == (1, scen.dx) and np.isfinite(x).all()
assert sys.modules.get("torch") is None
print(type(est).__name__)
"""
    )
    env = dict(os.environ, ROS_DOMAIN_ID=str(fresh_domain()), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    out = subprocess.run([sys.executable, "-c", step_code], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "OnnxEstimator"
    node_code = _NO_TORCH + "from neural_estimator.nodes.estimator_node import main\nsys.exit(main())\n"
    args = ["--ros-args", "-p", "method:=gru", "-p", "scenario:=lorenz96", "-p", f"checkpoint:={directory}"]
    args += ["-p", "options:=[backend=onnxruntime]"]
    proc = subprocess.Popen(
        [sys.executable, "-c", node_code, *args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env
    )
    try:
        lines = []
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            if "served by ONNX Runtime without torch" in line:
                break
        assert any("served by ONNX Runtime without torch" in ln for ln in lines), "".join(lines)[-2000:]
        time.sleep(3.0)  # the rest of the start-up (a few ms), then the node spins
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=30) == 0, proc.stdout.read()[-2000:]
    finally:
        if proc.poll() is None:
            proc.kill()


def test_compiled_pre_and_post_processing_equal_the_numpy_expressions_to_the_bit():
    from neural_estimator.serving.onnx_kernels import denormalize, denormalize_covariance, normalize_into

    rng = np.random.default_rng(3)
    dy, du, dx = 5, 2, 4
    in_mean, in_std = rng.normal(size=dy + du), rng.uniform(0.1, 3.0, dy + du)
    out_mean, out_std = rng.normal(size=dx), rng.uniform(0.1, 3.0, dx)
    for y_bad in (False, True):
        y, u = rng.normal(size=(1, dy)) * 100, rng.normal(size=(1, du))
        if y_bad:
            y[0, 2] = np.nan
        z = np.zeros((1, dy + du), dtype=np.float32)
        skipped = normalize_into(y, u, in_mean, in_std, z)
        want = ((np.concatenate([y, u], axis=1) - in_mean) / in_std).astype(np.float32)
        if y_bad:
            want[:, :dy] = 0.0
        assert skipped == y_bad
        np.testing.assert_array_equal(z, want)
    m = rng.normal(size=(1, dx)).astype(np.float32)
    x, finite = denormalize(m, out_std, out_mean)
    assert finite and x.dtype == np.float64
    np.testing.assert_array_equal(x, m * out_std + out_mean)
    m[0, 1] = np.inf
    assert not denormalize(m, out_std, out_mean)[1]
    c = rng.normal(size=(1, dx, dx)).astype(np.float32)
    scale = out_std[:, None] * out_std[None, :]
    p, finite = denormalize_covariance(c, scale)
    assert finite
    np.testing.assert_array_equal(p, c * scale)
    c[0, 0, 3] = np.nan
    assert not denormalize_covariance(c, scale)[1]


def test_an_interrupt_while_onnxruntime_initialises_is_a_stop_not_a_missing_package(monkeypatch):
    """ONNX Runtime's extension turns a Ctrl-C during its initialisation into "ImportError: initialization
    failed" (the interrupt in its chain): that is a KeyboardInterrupt (the node stops with status 0,
    test_node_cli.py), while an ImportError of its own still names the package to install."""
    import builtins
    import sys

    real_import = builtins.__import__

    def failing(interrupt):
        def fake_import(name, *args, **kwargs):
            if name != "onnxruntime":
                return real_import(name, *args, **kwargs)
            try:
                if interrupt:
                    raise KeyboardInterrupt
                raise OSError("libonnxruntime.so: cannot open shared object file")
            except BaseException:
                raise ImportError("initialization failed")  # noqa: B904  as the extension does

        return fake_import

    monkeypatch.delitem(sys.modules, "onnxruntime", raising=False)  # imported afresh (restored after)
    monkeypatch.setattr(builtins, "__import__", failing(True))
    with pytest.raises(KeyboardInterrupt):
        OrtStep(b"")
    monkeypatch.setattr(builtins, "__import__", failing(False))
    with pytest.raises(EstimatorError, match="needs the onnxruntime package"):
        OrtStep(b"")
