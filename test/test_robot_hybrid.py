"""The robot flow with the system's model: a spec naming a scenario (``model:``), a recording with no
ground-truth topic, a hybrid (KalmanNet) trained on its observations, filters run on the recording."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from neural_estimator.bags.writer import TYPESTORE, BagWriter
from neural_estimator.cli import main
from neural_estimator.data import load_trajectories
from neural_estimator.data.simulate import simulate
from neural_estimator.robot import DataScenario, SpecError, build_dataset, load_spec
from neural_estimator.scenarios import make_scenario

SCENARIO = "quadrotor"  # dx 6, dy 3, du 2, dt 0.01 s
TYPE = "std_msgs/msg/Float64MultiArray"


def array_msg(values: np.ndarray):
    """A std_msgs/Float64MultiArray holding ``values``."""
    M = TYPESTORE.types
    layout = M["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0)
    return M[TYPE](layout=layout, data=np.asarray(values, dtype=np.float64))


def fields(n: int) -> list[str]:
    return [f"data[{i}]" for i in range(n)]


def spec_dict(state: bool = False, **model) -> dict:
    """A spec reading the simulated quadrotor's topics, naming it as the model (``model`` overrides)."""
    s = make_scenario(SCENARIO)
    out = {
        "rate": 1.0 / s.dt,
        "stamp": "log",
        "observation": {"/y": fields(s.dy)},
        "control": {"/u": fields(s.du)},
        "model": {"scenario": SCENARIO, **model},
    }
    if state:
        out["state"] = {"/truth": fields(s.dx)}
    return out


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """(bags, simulated trajectories): 6 quadrotor flights of 40 steps, one MCAP each, written with
    the project's writer at the model's period: /y the observations, /u the controls, /truth the state."""
    s = make_scenario(SCENARIO)
    sim = simulate(s, 6, 40, np.random.SeedSequence(3))
    step = int(round(s.dt * 1e9))
    bags = []
    for n in range(sim.n):
        path = tmp_path_factory.mktemp("rec") / f"flight{n}.mcap"
        with BagWriter(path) as bag:
            for k in range(sim.horizon):
                t = (k + 1) * step
                bag.write_message("/y", t, array_msg(sim.y[n, k]), TYPE)
                bag.write_message("/u", t, array_msg(sim.u[n, k]), TYPE)
                bag.write_message("/truth", t, array_msg(sim.x[n, k]), TYPE)
        bags.append(path)
    return bags, sim


# ---- the spec ---------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "spec, message",
    [
        (
            {**spec_dict(), "observation": {"/y": fields(2)}},
            "observation has 2 fields, but the model 'quadrotor' has 3",
        ),
        ({**spec_dict(), "control": {"/u": fields(1)}}, "control has 1 fields, but the model 'quadrotor' has 2"),
        (
            {**spec_dict(state=True), "state": {"/truth": fields(5)}},
            "state has 5 fields, but the model 'quadrotor' has 6",
        ),
        ({**spec_dict(), "rate": 50.0}, r"dt = 0.01 s, but rate 50 Hz samples every 0.02 s: add set: \{dt: 0.02\}"),
        (spec_dict(set={"dt": 0.02}), r"dt = 0.02 s, but rate 100 Hz samples every 0.01 s: add set: \{dt: 0.01\}"),
        (spec_dict(scenario="nosuch"), "unknown scenario 'nosuch'"),
        (spec_dict(preset="v0"), "has no preset 'v0'"),
        ({**spec_dict(), "model": "quadrotor"}, "model must be a mapping"),
        ({k: v for k, v in spec_dict().items() if k != "model"}, "missing 'state'"),
    ],
)
def test_a_model_that_does_not_fit_the_spec_is_refused_in_one_line(spec, message):
    with pytest.raises(SpecError, match=message) as err:
        load_spec(spec)
    assert "\n" not in str(err.value)


def test_the_digest_covers_the_model_and_the_state_comes_from_it():
    s = load_spec(spec_dict())
    model = make_scenario(SCENARIO)
    assert not s.has_state and s.names["state"] == model.state_names and s.angles("state") == tuple(model.angle_states)
    assert s.digest() != load_spec(spec_dict(set={"mass": 1.1 * model.config.mass})).digest()
    assert load_spec(spec_dict(set={"dt": 0.01})).model.dt == model.dt


# ---- the dataset and the data scenario --------------------------------------------------------------------
def test_a_recording_without_ground_truth_gives_a_dataset_with_no_label(recording, tmp_path):
    bags, sim = recording
    data, _, _ = build_dataset(bags, load_spec(spec_dict()), length=40)
    assert data.n == sim.n and data.labelled is not None and not data.labelled.any()
    assert data.meta["ground_truth"] is False and data.meta["labelled_steps"] == 0
    np.testing.assert_allclose(data.y, sim.y)
    np.testing.assert_allclose(data.u, sim.u)
    path = tmp_path / "d.npz"
    assert (
        main(
            [
                "dataset",
                *map(str, bags),
                "--spec",
                str(_yaml(tmp_path, spec_dict())),
                "--length",
                "40",
                "--out",
                str(path),
                "--quiet",
            ]
        )
        == 0
    )
    loaded, _ = load_trajectories(path)
    assert loaded.labelled is not None and not loaded.labelled.any()


def test_data_scenario_with_a_model_has_the_models_equations(recording):
    bags, sim = recording
    data, _, _ = build_dataset(bags, load_spec(spec_dict(state=True)), length=40)
    assert data.labelled is None  # every step has ground truth
    np.testing.assert_allclose(data.x, sim.x)
    s, model = DataScenario(data.meta), make_scenario(SCENARIO)
    x, u = sim.x[:, 5], sim.u[:, 5]
    np.testing.assert_array_equal(s.f(x, u), model.f(x, u))
    np.testing.assert_array_equal(s.h(x), model.h(x))
    np.testing.assert_array_equal(s.jac_h(x), model.jac_h(x))
    np.testing.assert_array_equal(s.process_cov(), model.process_cov())
    np.testing.assert_array_equal(s.obs_cov(), model.obs_cov())
    np.testing.assert_array_equal(s.prior()[0], model.prior()[0])
    assert s.torch_dynamics() is not None and s.describe()["model"] == {"scenario": SCENARIO}
    other = DataScenario({**data.meta, "model": {"scenario": SCENARIO, "set": {"mass": 2 * model.config.mass}}})
    assert other.describe()["config"]["model_sha256"] != s.describe()["config"]["model_sha256"]


# ---- training and evaluation ----------------------------------------------------------------------------
def _yaml(tmp_path: Path, spec: dict) -> Path:
    import yaml

    path = tmp_path / f"spec{len(list(tmp_path.glob('spec*.yaml')))}.yaml"
    path.write_text(yaml.safe_dump(spec))
    return path


def _dataset(tmp_path, bags, spec: dict, name: str) -> Path:
    out = tmp_path / name
    args = ["dataset", *map(str, bags), "--spec", str(_yaml(tmp_path, spec)), "--length", "40", "--out", str(out)]
    assert main(args + ["--quiet"]) == 0
    return out


TRAIN = ["--model", "kalmannet", "--epochs", "1", "--window", "20", "--warmup", "2", "--batch-size", "2", "--quiet"]


def _evaluate(data: Path, methods: str, checkpoint: Path, *extra: str) -> int:
    return main(
        ["evaluate", "--data", str(data), "--methods", methods, "--checkpoint", f"kalmannet={checkpoint}", *extra]
    )


def test_a_hybrid_trains_on_observations_of_a_recording_without_ground_truth(recording, tmp_path, capsys):
    import json

    from neural_estimator.serving.load import load_neural_estimator

    bags, _ = recording
    data = _dataset(tmp_path, bags, spec_dict(), "unlabelled.npz")
    out = tmp_path / "knet"
    # a state-supervised run has nothing to learn from
    assert main(["train", "--data", str(data), "--out", str(out), *TRAIN]) == 2
    err = capsys.readouterr().err.strip()
    assert "no state labels: train a hybrid with --supervision observations" in err and "\n" not in err
    assert main(["train", "--data", str(data), "--out", str(out), *TRAIN, "--supervision", "observations"]) == 0
    card = json.loads((out / "card.json").read_text())
    assert card["training"]["supervision"] == "observations" and card["metrics"] is None  # nothing to score
    assert card["scenario"]["model"] == {"scenario": SCENARIO}
    # the checkpoint loads for the recording's scenario and filters it
    recorded, _ = load_trajectories(data)
    est = load_neural_estimator("kalmannet", DataScenario(recorded.meta), out, covariance=False)
    x_hat = est.run(recorded.y, recorded.u).x
    assert x_hat.shape == recorded.x.shape and np.isfinite(x_hat).all()
    # evaluate: nothing to score on a recording without ground truth, said in one line
    assert _evaluate(data, "ekf,kalmannet", out) == 2
    err = capsys.readouterr().err.strip()
    assert "nothing to score against" in err and "\n" not in err


def test_filters_and_the_hybrid_are_scored_on_a_recording_with_ground_truth(recording, tmp_path, capsys):
    import json

    bags, _ = recording
    data = _dataset(tmp_path, bags, spec_dict(state=True), "labelled.npz")
    out = tmp_path / "knet"
    assert main(["train", "--data", str(data), "--out", str(out), *TRAIN, "--supervision", "observations"]) == 0
    card = json.loads((out / "card.json").read_text())
    assert np.isfinite(card["metrics"]["rmse"])  # the card's metrics on the labelled validation set
    capsys.readouterr()
    assert _evaluate(data, "ekf,openloop,kalmannet", out, "--json", "--no-cache") == 0
    methods = json.loads(capsys.readouterr().out)["methods"]
    rmse = {m: methods[m]["summary"]["rmse"]["median"] for m in ("ekf", "openloop", "kalmannet")}
    assert all(np.isfinite(v) and v > 0 for v in rmse.values())
    assert rmse["ekf"] < rmse["openloop"]  # the model's filter reads the recording's observations
    # a recording of another model (and so another spec): the checkpoint is refused in one line
    other = _dataset(tmp_path, bags, spec_dict(state=True, set={"mass": 0.6}), "other.npz")
    assert _evaluate(other, "kalmannet", out) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "model_sha256" in err


def test_a_plugins_scenario_is_a_model_once_the_plugin_is_loaded(tmp_path):
    from neural_estimator.scenarios import load_plugins

    root = Path(__file__).resolve().parents[1]
    spec = {"rate": 10.0, "observation": {"/y": ["data[0]"]}, "model": {"scenario": "oscillator"}}
    load_plugins([root / "examples" / "custom_scenario.py"])  # registers "oscillator": dx 2, dy 1, dt 0.1 s
    s = load_spec(spec)
    assert (s.model.name, s.names["state"], s.model.dt) == ("oscillator", s.model.state_names, 0.1)
    with pytest.raises(SpecError, match="observation has 2 fields, but the model 'oscillator' has 1"):
        load_spec({**spec, "observation": {"/y": fields(2)}})


def test_a_run_is_not_scored_against_a_spec_without_ground_truth():
    from neural_estimator.robot.score import scoring_spec

    with pytest.raises(SpecError, match="no ground truth .*nothing to score against"):
        scoring_spec(load_spec(spec_dict()), ["/estimates/gru"], "/", None)


# ---- served live: the robot estimator node ----------------------------------------------------------------
def stamped_spec() -> dict:
    """The quadrotor's observation and control as header-stamped messages (the live node and the
    dataset tick on the same stamps, whatever the delivery's timing), no state, the model named."""
    return {
        "rate": 100.0,
        "stamp": "header",
        "observation": {"/y": ["point.x", "point.y", "point.z"]},
        "control": {"/u": ["vector.x", "vector.y"]},
        "model": {"scenario": SCENARIO},
    }


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """(bag, spec file, dataset file, checkpoint): three 40-step quadrotor flights 0.2 s apart written as
    geometry_msgs/PointStamped (y) and Vector3Stamped (u), no ground truth; their dataset; a kalmannet
    trained on its observations for one epoch (plumbing, not accuracy)."""
    M = TYPESTORE.types
    d = tmp_path_factory.mktemp("served")
    s = make_scenario(SCENARIO)
    sim = simulate(s, 3, 40, np.random.SeedSequence(5))
    step, t0 = int(round(s.dt * 1e9)), 1_700_000_000 * 10**9

    def header(t):
        stamp = M["builtin_interfaces/msg/Time"](sec=t // 10**9, nanosec=t % 10**9)
        return M["std_msgs/msg/Header"](stamp=stamp, frame_id="map")

    bag = d / "flights.mcap"
    with BagWriter(bag) as w:
        for n in range(sim.n):
            for k in range(sim.horizon):
                t = t0 + (60 * n + k + 1) * step
                y, u = sim.y[n, k].tolist(), sim.u[n, k].tolist()
                point = M["geometry_msgs/msg/Point"](x=y[0], y=y[1], z=y[2])
                w.write_message("/y", t, M["geometry_msgs/msg/PointStamped"](header=header(t), point=point))
                vector = M["geometry_msgs/msg/Vector3"](x=u[0], y=u[1], z=0.0)
                w.write_message("/u", t, M["geometry_msgs/msg/Vector3Stamped"](header=header(t), vector=vector))
    spec = _yaml(d, stamped_spec())
    data, model = d / "flights.npz", d / "knet"
    assert main(["dataset", str(bag), "--spec", str(spec), "--length", "40", "--out", str(data), "--quiet"]) == 0
    assert main(["train", "--data", str(data), "--out", str(model), *TRAIN, "--supervision", "observations"]) == 0
    return bag, spec, data, model


def _live_estimates(tmp_path, bag: Path, model: Path, expected: int, monkeypatch) -> list[tuple[int, list[float]]]:
    """(stamp, position) of each estimate the robot estimator node publishes while the player plays
    ``bag`` into it (a private domain; reliable inputs, so no message is lost to the comparison)."""
    import signal

    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState

    from neural_estimator.nodes.launch import isolated_env, node_command, start_node
    from ros_tester import Tester, fresh_domain

    domain = fresh_domain()
    env = isolated_env(domain)
    node = "neural_estimator.nodes.robot_estimator_node"
    params = {"checkpoint": str(model), "input_qos": "reliable"}
    procs = [start_node(node_command(sys.executable, node, "est", params), tmp_path / "est.log", env)]
    tester = Tester(monkeypatch, domain, lambda: (tmp_path / "est.log").read_text(), timeout=60.0)
    got: list[tuple[int, list[float]]] = []
    try:
        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        sub = tester.node.create_subscription(
            JointState,
            "/estimates/kalmannet",
            lambda m: got.append((m.header.stamp.sec * 10**9 + m.header.stamp.nanosec, list(m.position))),
            qos,
        )
        tester.spin_until(lambda: "recorded-data spec" in (tmp_path / "est.log").read_text())
        # this subscription is volatile (no history): play only once it is matched to the node's publisher
        tester.spin_until(lambda: sub.get_publisher_count() >= 1)
        player = dict(bag=str(bag), wait_for_subscribers=1, wait_topic="/y")
        procs.append(
            start_node(
                node_command(sys.executable, "neural_estimator.nodes.player_node", "player", player),
                tmp_path / "player.log",
                env,
            )
        )
        tester.spin_until(lambda: len(got) >= expected)
    finally:
        tester.shutdown()
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for p in procs:
            try:
                p.wait(timeout=10)
            except Exception:
                p.kill()
    return got


@pytest.mark.ros
@pytest.mark.slow
def test_the_robot_estimator_serves_the_hybrid_with_the_estimates_evaluate_scores(served, tmp_path, monkeypatch):
    """The recording played by the player into `robot_estimator -p checkpoint:=DIR` (reliable
    inputs: a lost message would change a tick's inputs): per tick, the estimates of the model run
    on the recording's dataset, as `evaluate --data` runs it."""
    pytest.importorskip("rclpy")
    from neural_estimator.methods.registry import make_estimator

    bag, _, data, model = served
    recorded, _ = load_trajectories(data)
    offline = make_estimator("kalmannet", DataScenario(recorded.meta), checkpoint=model).run(recorded.y, recorded.u).x
    # per flight: its 40 ticks (a trajectory) and 2 more while its last message is within max_age (the
    # dataset's remainder), but the last flight's 2: no later message settles them
    got = _live_estimates(tmp_path, bag, model, 3 * 42 - 2, monkeypatch)
    stamps = np.array([t for t, _ in got])
    assert np.all(np.diff(stamps) > 0), "estimates out of tick order"
    flights = np.split(np.arange(stamps.size), np.flatnonzero(np.diff(stamps) > 10**8) + 1)
    assert [f.size for f in flights] == [42, 42, 40]
    live = np.array([[got[i][1] for i in f[:40]] for f in flights])
    assert live.shape == offline.shape
    np.testing.assert_allclose(live, offline, rtol=1e-4, atol=1e-4)  # float32 steps vs the parallel form
    assert np.abs(offline).max() > 1.0  # a comparison of estimates, not of zeros


@pytest.mark.ros
def test_the_robot_estimator_refuses_a_hybrid_whose_spec_names_no_model(served, tmp_path):
    """A kalmannet card whose spec lost its model (edited: `train` refuses to make one) is refused at
    start-up in one line, before its step.onnx (an f and h of its own) could serve it."""
    pytest.importorskip("rclpy")
    import json
    import shutil
    import subprocess

    from neural_estimator.nodes.launch import isolated_env, node_command
    from ros_tester import fresh_domain

    _, _, _, model = served
    edited = tmp_path / "knet"
    shutil.copytree(model, edited)
    card = json.loads((edited / "card.json").read_text())
    assert (edited / "step.onnx").exists() and card["scenario"]["model"] == {"scenario": SCENARIO}
    desc = card["scenario"]
    del desc["model"], desc["spec"]["model"]
    desc["spec"]["state"] = [["/truth", fields(6)]]  # a spec without a model must read the state
    desc["config"]["model_sha256"] = ""
    (edited / "card.json").write_text(json.dumps(card))
    node = "neural_estimator.nodes.robot_estimator_node"
    cmd = node_command(sys.executable, node, "est", {"checkpoint": str(edited)})
    proc = subprocess.run(cmd, env=isolated_env(fresh_domain()), capture_output=True, text=True, timeout=60)
    out = proc.stdout + proc.stderr
    fatal = [ln for ln in out.splitlines() if "FATAL" in ln or "error" in ln.lower()]
    assert proc.returncode == 1 and "Traceback" not in out, out
    refusal = "a kalmannet model runs the system's f and h, but its card's spec names no model"
    assert len(fatal) == 1 and refusal in fatal[0], out
