"""ONNX Runtime by default for per-message serving: every shipped model's step.onnx equals its torch
step, the per-message default (backend ``auto``) picks it where it serves the request and torch
elsewhere, and the estimator node's default command runs without torch in its process."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("onnxruntime")

from neural_estimator.data import simulate  # noqa: E402
from neural_estimator.methods import table  # noqa: E402
from neural_estimator.methods.interface import EstimatorError, previous_controls  # noqa: E402
from neural_estimator.methods.registry import make_estimator, per_message_options  # noqa: E402
from neural_estimator.scenarios import make_scenario, scenario_from_description  # noqa: E402
from neural_estimator.serving.load import load_neural_estimator  # noqa: E402

ZOO = Path(__file__).resolve().parents[1] / "neural_estimator" / "serving" / "zoo"
WITH_GRAPH = sorted(p.name for p in ZOO.glob("*-*") if (p / "step.onnx").is_file())


def _scenario(name: str):
    return scenario_from_description(json.loads((ZOO / name / "card.json").read_text())["scenario"])


def test_every_servable_zoo_model_ships_its_step_graph():
    """All 30 networks, the two GRUs validated with a bounded context (their restarted copies at
    batch K) included; every shipped hybrid whose system's f and h export (all but N-link's)."""
    networks = [n for n in WITH_GRAPH if table.has(n.rsplit("-", 1)[1], family="neural")]
    assert len(networks) == 30, WITH_GRAPH
    without = sorted(set(p.name for p in ZOO.glob("*-*")) - set(WITH_GRAPH))
    torch_served = ["nlink-kalmannet"] if (ZOO / "nlink-kalmannet").is_dir() else []  # linalg.solve: no ONNX form
    assert without == torch_served


@pytest.mark.slow
@pytest.mark.parametrize("name", WITH_GRAPH)
def test_shipped_step_graph_equals_the_torch_step(name):
    """300 steps of fresh data (a missing observation at step 40), through the per-message default
    (step.onnx, ONNX Runtime) and through torch (the bounded-context GRUs: L = 100, K = 4, so each
    copy restarts three times and the served copy changes from step 100 on; torch's BatchedCopies
    against the graph's copies at batch 4): estimates within 1e-5 relative at every step, the
    covariance head's covariance within 1e-5 relative after the card's warm-up (the steps the
    training loss skipped) and 1e-4 within it, the skipped flag alike. (Measured: the one covariance
    beyond 1e-5 is quadrotor Mamba-2's at step 0, 1.8e-5: float32 round-off of the head's read-out
    of the first step's features, summed in another order by ONNX Runtime.)"""
    scen = _scenario(name)
    method = name.rsplit("-", 1)[1]
    ort = make_estimator(method, scen, **per_message_options(method, {}))
    ref = make_estimator(method, scen)  # torch: make_estimator's own default
    assert type(ort).__name__ == "OnnxEstimator" and type(ref).__name__ == "NeuralEstimator"
    assert ort.context_by_copies == ref.context_by_copies  # the bounded GRUs: the same restarted copies
    if ref.context_by_copies:
        assert (ort.context, ort.context_copies) == (ref.context, ref.context_copies)
    # every shipped network has a covariance head; a hybrid reports none (KalmanNet tracks none)
    assert ort.has_covariance == ref.has_covariance == table.has(method, family="neural")
    data = simulate(scen, 1, 300, 11)
    y, u = data.y[0].copy(), previous_controls(data.u)[0]
    y[40] = np.nan
    ort.reset(1)
    ref.reset(1)
    worst, worst_cov, worst_cov_warmup = 0.0, 0.0, 0.0
    for k in range(y.shape[0]):
        a = ref.step(y[k : k + 1], u[k : k + 1])
        b = ort.step(y[k : k + 1], u[k : k + 1])
        assert ort.skipped[0] == ref.skipped[0] == (k == 40)
        worst = max(worst, float(np.abs(a - b).max() / (1.0 + np.abs(a).max())))
        P, Q = ref.covariance, ort.covariance
        if P is None or Q is None:  # a hybrid: none from either
            assert P is None and Q is None
            continue
        err = float(np.abs(P - Q).max() / (1.0 + np.abs(P).max()))
        if k < ref.untrained_steps:
            worst_cov_warmup = max(worst_cov_warmup, err)
        else:
            worst_cov = max(worst_cov, err)
    assert ort.untrained_steps == ref.untrained_steps
    assert worst < 1e-5 and worst_cov < 1e-5 and worst_cov_warmup < 1e-4, (worst, worst_cov, worst_cov_warmup)


def test_auto_serves_the_graph_where_it_fits_and_torch_elsewhere():
    l96 = make_scenario("lorenz96")
    auto = {"backend": "auto"}
    assert type(load_neural_estimator("gru", l96, **auto)).__name__ == "OnnxEstimator"
    # what the graph does not serve: restarted copies, torch.compile, another attention window
    bounded = load_neural_estimator("gru", l96, context=50, **auto)
    assert type(bounded).__name__ == "NeuralEstimator" and bounded.context_by_copies
    assert type(load_neural_estimator("gru", l96, compile_step="true", **auto)).__name__ == "NeuralEstimator"
    window = load_neural_estimator("gpt2", l96, context=50, **auto)
    assert type(window).__name__ == "NeuralEstimator" and window.context == 50
    with pytest.raises(EstimatorError, match="attention window"):  # asked for explicitly, it is an error
        load_neural_estimator("gpt2", l96, context=50, backend="onnxruntime")
    # a model validated with a bounded context serves its restarted copies from its graph; another
    # context than the graph's is torch's under auto, and refused when ONNX Runtime is asked for
    ballistic = _scenario("ballistic-gru")
    ballistic_gru = make_estimator("gru", ballistic, **per_message_options("gru", {}))
    assert type(ballistic_gru).__name__ == "OnnxEstimator" and ballistic_gru.context_by_copies
    assert (ballistic_gru.context, ballistic_gru.context_copies) == (100, 4)
    for other in ({"context": 0}, {"context": 100}, {"context": 50, "context_copies": 4}):
        est = make_estimator("gru", ballistic, **per_message_options("gru", other))
        assert type(est).__name__ == "NeuralEstimator" and est.context == other["context"]
        assert est.context_copies == other.get("context_copies", 10) or not est.context
        with pytest.raises(EstimatorError, match="serves a context bounded to 100 steps .4 copies., not context="):
            make_estimator("gru", ballistic, backend="onnxruntime", **other)
    same = make_estimator("gru", ballistic, **per_message_options("gru", {"context": "100", "context_copies": "4"}))
    assert type(same).__name__ == "OnnxEstimator"
    # the classical filters take no backend option
    assert per_message_options("ekf", {}) == {} and per_message_options("mamba", {})["backend"] == "auto"
    with pytest.raises(EstimatorError, match="backend must be one of"):
        load_neural_estimator("gru", l96, backend="tensorrt")


def test_cov_scale_and_a_refitted_head_are_honoured(tmp_path):
    """The graph serves ``cov_scale`` as torch does, and a graph older than the card's covariance head
    (another shrinkage, e.g. refitted) is refused until it is exported again."""
    from neural_estimator.serving.export import export_beside

    l96 = make_scenario("lorenz96")
    directory = tmp_path / "gru"
    shutil.copytree(ZOO / "lorenz96-gru", directory)
    ort = load_neural_estimator("gru", l96, directory, backend="auto", cov_scale="2.5")
    ref = load_neural_estimator("gru", l96, directory, cov_scale=2.5)
    y = simulate(l96, 1, 5, 0).y[0]
    ort.reset(1)
    ref.reset(1)
    for k in range(5):
        ort.step(y[k : k + 1])
        ref.step(y[k : k + 1])
    np.testing.assert_allclose(ort.covariance, ref.covariance, rtol=1e-5, atol=1e-5 * np.abs(ref.covariance).max())
    card = json.loads((directory / "card.json").read_text())
    card["covariance_head"]["shrink"] = 0.25
    (directory / "card.json").write_text(json.dumps(card))
    with pytest.raises(EstimatorError, match="export it again"):
        load_neural_estimator("gru", l96, directory, backend="auto")
    assert export_beside(directory) == directory / "step.onnx"
    ort = load_neural_estimator("gru", l96, directory, backend="auto")
    ref = load_neural_estimator("gru", l96, directory)
    ort.reset(1)
    ref.reset(1)
    ort.step(y[:1])
    ref.step(y[:1])
    np.testing.assert_allclose(ort.covariance, ref.covariance, rtol=1e-5, atol=1e-5 * np.abs(ref.covariance).max())


_NO_TORCH = 'import sys\nsys.modules["torch"] = None  # `import torch` now raises ImportError\n'

_PER_MESSAGE = """
import json
import numpy as np
import neural_estimator.nodes.estimator_node  # the node's own imports
from neural_estimator.stream import messages as MSG
from neural_estimator.data import simulate
from neural_estimator.nodes.estimator_params import EstimatorParams, online_estimator
from neural_estimator.stream.online import warm_up
from neural_estimator.methods.registry import make_estimator, per_message_options
from neural_estimator.scenarios import make_scenario

scen = make_scenario({scenario!r})
est = make_estimator({method!r}, scen, **per_message_options({method!r}, {{}}))  # as EstimatorNode._build
warm_up(est, scen)
online = online_estimator(est, {method!r}, EstimatorParams())
data = simulate(scen, 1, {steps}, 5)
out = []
for k in range({steps}):
    for r in online.feed(MSG.encode_observation(scen, 10**6 * (k + 1), 0, k, data.y[0, k]), now=0.0):
        out.append(r.x_hat.tolist())
assert "torch" not in sys.modules or sys.modules["torch"] is None
print(type(est).__name__, json.dumps(out))
"""


@pytest.mark.slow
@pytest.mark.parametrize("scenario,method,steps", [("lorenz96", "mamba", 60), ("bearings", "gru", 260)])
def test_the_node_per_message_path_runs_without_torch_and_equals_torch(scenario, method, steps):
    """The estimator node's per-message path (its imports, the estimator its defaults build, the
    warm-up, OnlineEstimator.feed on CDR messages) in a process where torch cannot be imported;
    its estimates equal those of the torch backend on the same messages (1e-5 relative to their
    size, as the other ONNX equality tests hold them). The bearings GRU is a
    bounded-context model (L = 100, K = 4): 260 steps, past two restarts of every copy."""
    from neural_estimator.stream import messages as MSG
    from neural_estimator.nodes.estimator_params import EstimatorParams, online_estimator

    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    code = _NO_TORCH + _PER_MESSAGE.format(scenario=scenario, method=method, steps=steps)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=180)
    assert out.returncode == 0, out.stderr[-2000:]
    kind, text = out.stdout.strip().splitlines()[-1].split(" ", 1)
    served = np.array(json.loads(text))
    scen = make_scenario(scenario)
    torch_est = make_estimator(method, scen)
    assert kind == "OnnxEstimator" and type(torch_est).__name__ == "NeuralEstimator"
    online = online_estimator(torch_est, method, EstimatorParams())
    data = simulate(scen, 1, steps, 5)
    ref = [
        r.x_hat
        for k in range(steps)
        for r in online.feed(MSG.encode_observation(scen, 10**6 * (k + 1), 0, k, data.y[0, k]), now=0.0)
    ]
    assert served.shape == (steps, scen.dx)
    np.testing.assert_allclose(served, np.array(ref), rtol=1e-5, atol=1e-5 * np.abs(ref).max())


@pytest.mark.slow
@pytest.mark.ros
def test_the_design_card_command_serves_without_torch(tmp_path):
    """``ros2 run neural_estimator estimator --ros-args -p method:=mamba`` (with the scenario given,
    so that it builds at once) in a process where torch cannot be imported: the node starts, builds
    the shipped Mamba on ONNX Runtime, says so and exits cleanly on SIGINT."""
    pytest.importorskip("rclpy")
    domain = os.environ.get("ROS_DOMAIN_ID") or str(120 + os.getpid() % 60)
    env = dict(os.environ, ROS_DOMAIN_ID=domain, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1")
    code = _NO_TORCH + "from neural_estimator.nodes.estimator_node import main\nsys.exit(main())\n"
    args = ["--ros-args", "-p", "method:=mamba", "-p", "scenario:=lorenz96"]
    proc = subprocess.Popen(
        [sys.executable, "-c", code, *args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env
    )
    try:
        lines = []
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            if "served by ONNX Runtime without torch" in line:
                break
        assert any("served by ONNX Runtime without torch" in ln for ln in lines), "".join(lines)[-2000:]
        time.sleep(2.0)
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=30) == 0, proc.stdout.read()[-2000:]
    finally:
        if proc.poll() is None:
            proc.kill()


_REPLAY = """
from neural_estimator.evaluation.replay import replay
res = replay({bag!r}, ["mamba"], {out!r})
assert "torch" not in sys.modules or sys.modules["torch"] is None
print(res.estimates["mamba"])
"""


@pytest.mark.slow
def test_replay_serves_as_the_live_node_without_torch(tmp_path):
    """Replay takes the live node's default (step.onnx, no torch): it runs where torch cannot be
    imported, and its estimates equal the torch backend's replay of the same bag within 1e-5."""
    from neural_estimator.bags import bag_to_arrays
    from neural_estimator.evaluation.replay import replay

    bag = Path(__file__).resolve().parents[1] / "bags" / "lorenz96.mcap"
    out = tmp_path / "ort.mcap"
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    code = _NO_TORCH + _REPLAY.format(bag=str(bag), out=str(out))
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    assert int(run.stdout.strip().splitlines()[-1]) > 0
    ref = replay(bag, ["mamba"], tmp_path / "torch.mcap", options={"mamba": {"backend": "torch"}})
    a, b = bag_to_arrays(out), bag_to_arrays(ref.path)
    assert a.x_hat["mamba"].shape == b.x_hat["mamba"].shape
    np.testing.assert_allclose(a.x_hat["mamba"], b.x_hat["mamba"], rtol=1e-5, atol=1e-5)
