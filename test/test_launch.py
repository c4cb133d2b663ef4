"""The launch files and `neural-estimator live` read one description of the graph
(neural_estimator.nodes.graph); the launch files are checked without the `launch` package (not on
PyPI): they run against stand-ins of launch / launch_ros that record what they are given."""

from __future__ import annotations

import ast
import importlib.util
import sys
import types
from pathlib import Path

import pytest
import yaml

from neural_estimator.nodes import graph as G
from neural_estimator.nodes.launch import PipelineConfig, build_parser
from ros_tester import fresh_domain

ROOT = Path(__file__).resolve().parents[1]
LAUNCH_FILES = sorted((ROOT / "launch").glob("*.launch.py"))


class _Recorder:
    def __init__(self, *args, **kwargs):
        self.args, self.kwargs = args, kwargs


@pytest.fixture
def fake_launch(monkeypatch):
    """Minimal stand-ins of launch and launch_ros: what the launch files use, recorded."""

    class LaunchConfiguration:
        def __init__(self, name):
            self.name = name

        def perform(self, context):
            return context.launch_configurations[self.name]

    mods = {
        "launch": types.ModuleType("launch"),
        "launch.actions": types.ModuleType("launch.actions"),
        "launch.substitutions": types.ModuleType("launch.substitutions"),
        "launch_ros": types.ModuleType("launch_ros"),
        "launch_ros.actions": types.ModuleType("launch_ros.actions"),
    }
    mods["launch"].LaunchDescription = type("LaunchDescription", (_Recorder,), {})
    for name in ("DeclareLaunchArgument", "OpaqueFunction", "Shutdown"):
        setattr(mods["launch.actions"], name, type(name, (_Recorder,), {}))
    mods["launch.substitutions"].LaunchConfiguration = LaunchConfiguration
    mods["launch_ros.actions"].Node = type("Node", (_Recorder,), {})
    for name, mod in mods.items():
        monkeypatch.setitem(sys.modules, name, mod)
    return mods


def _load(path: Path):
    spec = importlib.util.spec_from_file_location(path.stem.replace(".", "_"), path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _console_scripts() -> set[str]:
    """The node executables setup.py gives colcon (its ``_NODES`` list, lib/neural_estimator)."""
    tree = ast.parse((ROOT / "setup.py").read_text())
    nodes = next(n for n in ast.walk(tree) if isinstance(n, ast.Assign) and getattr(n.targets[0], "id", "") == "_NODES")
    return {s.split("=")[0].strip() for s in ast.literal_eval(nodes.value)}


def _documented(executable: str) -> set[str]:
    raw = yaml.safe_load((ROOT / "params" / f"{executable}.yaml").read_text())
    return set(raw["/**"]["ros__parameters"]) | {"use_sim_time"}


REQUIRED = {  # arguments without a usable default, per graph
    "robot_estimator": {"checkpoint": "runs/robot-gru", "bag": "runs/robot_bag", "spec": "examples/robot_spec.yaml"},
    "replay": {"bag": "bags/bearings.mcap"},
}


def test_one_launch_file_per_graph_installed_by_setup():
    assert {p.name for p in LAUNCH_FILES} == {f"{g}.launch.py" for g in G.GRAPHS}
    assert 'glob("launch/*.launch.py")' in (ROOT / "setup.py").read_text()


@pytest.mark.parametrize("path", LAUNCH_FILES, ids=lambda p: p.name)
def test_launch_file_declares_the_graphs_arguments_and_starts_its_nodes(path, fake_launch):
    graph = path.name.removesuffix(".launch.py")
    desc = _load(path).generate_launch_description()
    assert isinstance(desc, fake_launch["launch"].LaunchDescription)
    entities = desc.args[0]
    declared = [e for e in entities if type(e).__name__ == "DeclareLaunchArgument"]
    opaque = [e for e in entities if type(e).__name__ == "OpaqueFunction"]
    assert [d.args[0] for d in declared] == list(G.GRAPHS[graph].arguments)
    assert all(d.kwargs["description"] for d in declared)
    assert len(opaque) == 1 and len(entities) == len(declared) + 1
    # run the deferred part as `ros2 launch` does, with the defaults and the required arguments
    values = {d.args[0]: d.kwargs["default_value"] for d in declared} | REQUIRED.get(graph, {})
    context = types.SimpleNamespace(launch_configurations=values)
    nodes = opaque[0].kwargs["function"](context)
    specs = G.build(graph, REQUIRED.get(graph, {}))
    assert [n.kwargs["name"] for n in nodes] == [s.name for s in specs]
    scripts = _console_scripts()
    for node, spec in zip(nodes, specs):
        kw = node.kwargs
        assert kw["package"] == "neural_estimator" and kw["executable"] in scripts
        *files, params = kw["parameters"]
        assert params == spec.ros_params() and tuple(files) == spec.params_files
        assert all(Path(f).is_file() for f in files), files
        unknown = set(params) - _documented(kw["executable"])
        assert not unknown, f"{graph}: {kw['name']} gets undocumented parameters {unknown}"
        assert (kw["on_exit"] is not None) == spec.required
    assert any(s.required for s in specs) or graph in ("estimator",) or not REQUIRED.get(graph, {}).get("bag")


def test_live_launch_and_the_live_verb_build_the_same_nodes():
    """`ros2 launch neural_estimator live.launch.py ...` and `neural-estimator live ...` with the same
    values start the same nodes with the same parameters."""
    a = build_parser().parse_args(
        ["--scenario", "bearings", "--methods", "ekf,gru", "--rate-hz", "50", "--trajectories", "3", "--seed", "4"]
    )
    cfg = PipelineConfig(
        scenario=a.scenario,
        methods=tuple(a.methods.split(",")),
        rate_hz=a.rate_hz,
        trajectories=a.trajectories,
        seed=a.seed,
    )
    verb = G.live_nodes(cfg, "runs/b.mcap")
    launched = G.build(
        "live",
        {
            "scenario": "bearings",
            "methods": "ekf,gru",
            "rate_hz": "50",
            "trajectories": "3",
            "seed": "4",
            "output": "runs/b.mcap",
        },
    )
    assert verb == launched
    assert [s.name for s in verb] == ["evaluator", "estimator_ekf", "estimator_gru", "simulator"]
    assert verb[-1].params["wait_for_subscribers"] == 3 and verb[-1].params["rate_hz"] == 50.0
    cmd = G.command("python", verb[1])
    assert cmd[:6] == ["python", "-m", G.ESTIMATOR, "--ros-args", "-r", "__node:=estimator_ekf"]
    assert 'method:="ekf"' in cmd and "set:=[]" not in " ".join(cmd)  # empty lists left out


def test_robot_replay_graph_runs_everything_on_the_players_clock():
    specs = {s.name: s for s in G.build("robot_estimator", REQUIRED["robot_estimator"] | {"rate": "4"})}
    assert specs["player"].params["publish_clock"] is True and specs["player"].params["rate"] == 4.0
    assert specs["robot_estimator"].params["use_sim_time"] is True
    assert specs["evaluator"].params["use_sim_time"] is True and "/mocap/pose" in specs["evaluator"].params["topics"]
    live = {s.name for s in G.build("robot_estimator", {"checkpoint": "runs/robot-gru"})}
    assert live == {"robot_estimator"}  # no bag: the robot's own topics, no player, no evaluator


@pytest.mark.parametrize(
    "graph, args, message",
    [
        ("live", {"methods": " , "}, "methods is empty"),
        ("live", {"rate_hz": "fast"}, "rate_hz must be a float"),
        ("live", {"colour": "red"}, "unknown launch argument(s) colour"),
        ("robot_estimator", {}, "checkpoint is required"),
        ("robot_estimator", {"checkpoint": "x", "use_sim_time": "maybe"}, "use_sim_time must be true or false"),
        ("replay", {}, "bag is required"),
        ("nope", {}, "unknown graph"),
    ],
)
def test_bad_launch_arguments_are_one_line(graph, args, message):
    with pytest.raises(G.GraphError, match=message.replace("(", r"\(").replace(")", r"\)")) as err:
        G.build(graph, args)
    assert "\n" not in str(err.value)


@pytest.mark.ros
def test_ros2_launch_of_the_pip_shim_runs_the_replay_graph(tmp_path, monkeypatch, capsys):
    """`ros2 launch neural_estimator replay.launch.py ...` in a pip environment (the ros2 shim): the
    replay graph's nodes started from the description, a sample bag played into two estimators,
    recorded and scored by the evaluator (the required node: its exit ends the launch)."""
    pytest.importorskip("rclpy")

    from neural_estimator.cli import ros2_shim
    from neural_estimator.bags import BagReader

    monkeypatch.setattr(ros2_shim, "_real_ros2", lambda: None)
    assert ros2_shim.main(["launch", "neural_estimator", "replay.launch.py", "--show-args"]) == 0
    assert "'bag':" in capsys.readouterr().out
    assert ros2_shim.main(["launch", "neural_estimator", "nope.launch.py"]) == 1
    assert ros2_shim.main(["launch", "neural_estimator", "replay.launch.py", "bag=x"]) == 2
    assert "expected <name>:=<value>" in capsys.readouterr().err
    monkeypatch.setenv("ROS_DOMAIN_ID", str(fresh_domain()))
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    out = tmp_path / "replay.mcap"
    bag = ROOT / "bags" / "bearings.mcap"
    args = [f"bag:={bag}", "methods:=ekf,ukf", "rate:=20", f"output:={out}"]
    from neural_estimator.nodes import launch as L

    started, popen = [], L.subprocess.Popen
    monkeypatch.setattr(L.subprocess, "Popen", lambda *a, **k: started.append(popen(*a, **k)) or started[-1])
    assert ros2_shim.main(["launch", "neural_estimator", "replay.launch.py", *args]) == 0
    assert len(started) == 4 and all(p.poll() is not None for p in started)  # no node outlives the launch
    with BagReader(out) as reader:
        n_obs = reader.topics["/observation"].msgcount
        for m in ("ekf", "ukf"):
            assert reader.topics[f"/estimates/{m}"].msgcount == n_obs
            assert reader.topics[f"/estimates/{m}/odometry"].msgcount == n_obs  # bearings has a pose
            assert reader.topics[f"/estimates/{m}/state"].msgcount == n_obs
    table = out.with_name(out.stem + ".metrics.md").read_text()
    assert "ekf" in table and "ukf" in table


def test_graph_command_prints_the_pip_path_of_a_graph(capsys):
    assert G.main(["replay", "bag:=bags/bearings.mcap", "methods:=ekf"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 3 and "neural_estimator.nodes.player_node" in lines[-1] and "__node:=estimator_ekf" in lines[1]
    assert G.main(["replay"]) == 2 and "bag is required" in capsys.readouterr().err
    assert G.main(["live", "methods=ekf"]) == 2 and "expected name:=value" in capsys.readouterr().err


def test_each_test_worker_takes_its_own_share_of_the_ros_domains(monkeypatch):
    """Under pytest-xdist (scripts/run_tests.sh) each worker confines NEURAL_ESTIMATOR_DOMAINS to its
    share (test/conftest.py), so two workers' ROS tests never meet on one domain."""
    import os

    from conftest import _confine_worker_domains

    from neural_estimator.nodes.launch import domain_range

    shares = []
    for worker in ("gw0", "gw1", "gw2"):
        monkeypatch.setenv("NEURAL_ESTIMATOR_DOMAINS", "200-232")
        monkeypatch.setenv("PYTEST_XDIST_WORKER", worker)
        monkeypatch.setenv("PYTEST_XDIST_WORKER_COUNT", "3")
        _confine_worker_domains()
        shares.append(set(range(domain_range()[0], domain_range()[1] + 1)))
    assert [len(s) for s in shares] == [11, 11, 11] and set().union(*shares) == set(range(200, 233))
    monkeypatch.delenv("NEURAL_ESTIMATOR_DOMAINS")  # the tests' default range, 200..232, is shared out too
    monkeypatch.setenv("PYTEST_XDIST_WORKER", "gw1")
    monkeypatch.setenv("PYTEST_XDIST_WORKER_COUNT", "2")
    _confine_worker_domains()
    assert os.environ["NEURAL_ESTIMATOR_DOMAINS"] == "216-231"
    monkeypatch.setenv("NEURAL_ESTIMATOR_DOMAINS", "40")  # one domain, two workers: refused, never shared
    with pytest.raises(pytest.UsageError, match="fewer ROS domains than the 2 test workers"):
        _confine_worker_domains()
    monkeypatch.delenv("PYTEST_XDIST_WORKER")  # not under xdist: the range is left alone
    _confine_worker_domains()
    assert os.environ["NEURAL_ESTIMATOR_DOMAINS"] == "40"


def test_ros_domains_come_from_the_range_variable_then_ros_domain_id(monkeypatch):
    """Tools pick NEURAL_ESTIMATOR_DOMAINS's range, else the user's ROS_DOMAIN_ID, else 100..199;
    the tests pick from the same range (default 200..232), so one variable confines a whole run."""
    from neural_estimator.nodes.launch import DomainError, pick_domain_id

    monkeypatch.setenv("NEURAL_ESTIMATOR_DOMAINS", "40-42")
    monkeypatch.setenv("ROS_DOMAIN_ID", "17")
    assert {pick_domain_id() for _ in range(30)} <= {40, 41, 42}
    assert {fresh_domain() for _ in range(6)} <= {40, 41, 42}
    monkeypatch.delenv("NEURAL_ESTIMATOR_DOMAINS")
    assert pick_domain_id() == 17
    monkeypatch.delenv("ROS_DOMAIN_ID")
    assert 100 <= pick_domain_id() <= 199 and 200 <= fresh_domain() <= 232
    for bad in ("40-300", "x", "9-3"):
        monkeypatch.setenv("NEURAL_ESTIMATOR_DOMAINS", bad)
        with pytest.raises(DomainError, match="NEURAL_ESTIMATOR_DOMAINS"):
            pick_domain_id()
