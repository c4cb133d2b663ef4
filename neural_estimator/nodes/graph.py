"""The one description of the node graphs that ``ros2 launch`` and ``neural-estimator live`` start.

Each graph (``live``, ``estimator``, ``robot_estimator``, ``replay``) is a table of launch
arguments (name -> default, help) and a builder from their values to a list of :class:`NodeSpec`
(node name, executable, module, parameters, params files, whether its exit ends the graph). Two
front ends read it:

- the launch files under ``launch/`` (installed to ``share/neural_estimator/launch``) are three
  lines each: ``generate_launch_description()`` returns :func:`launch_description` of their graph,
  which declares the arguments and turns each NodeSpec into a ``launch_ros.actions.Node`` when the
  launch runs;
- ``neural-estimator live`` (:mod:`neural_estimator.nodes.launch`, no ``launch`` package needed:
  it is not on PyPI) starts the same NodeSpecs as ``python -m <module> --ros-args ...`` processes.

No rclpy and no ``launch`` import at module level: tests check the graphs and the launch files
without either.
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from neural_estimator.methods import table

PACKAGE = "neural_estimator"
SIMULATOR = "neural_estimator.nodes.simulator_node"
ESTIMATOR = "neural_estimator.nodes.estimator_node"
EVALUATOR = "neural_estimator.nodes.evaluator_node"
PLAYER = "neural_estimator.nodes.player_node"
ROBOT_ESTIMATOR = "neural_estimator.nodes.robot_estimator_node"
# module -> the executable `ros2 run neural_estimator <executable>` runs (setup.py's console_scripts)
EXECUTABLES = {
    SIMULATOR: "simulator",
    ESTIMATOR: "estimator",
    EVALUATOR: "evaluator",
    PLAYER: "player",
    ROBOT_ESTIMATOR: "robot_estimator",
}
MAX_DEPTH = 100_000  # queue depth cap (about 30 MB per transient_local stream)


class GraphError(ValueError):
    """A launch argument cannot be used (one line naming it)."""


@dataclasses.dataclass(frozen=True)
class NodeSpec:
    """One node of a graph."""

    name: str  # node name (also the log file's name)
    module: str  # `python -m <module>`; the ros2 executable is EXECUTABLES[module]
    params: dict[str, Any]  # parameters (after the params files)
    params_files: tuple[str, ...] = ()  # YAML params files applied first
    required: bool = False  # its exit ends the graph (the evaluator: it exits when the run is scored)

    @property
    def executable(self) -> str:
        return EXECUTABLES[self.module]

    def ros_params(self) -> dict[str, Any]:
        """The parameters without empty lists (an empty YAML list has no type: the default stays)."""
        return {k: v for k, v in self.params.items() if not (isinstance(v, (list, tuple)) and not v)}


@dataclasses.dataclass(frozen=True)
class PipelineConfig:
    """One live run (the simulator's, estimators' and evaluator's parameters that matter)."""

    scenario: str
    methods: tuple[str, ...]
    trajectories: int = 2
    horizon: int = 0  # 0 = the scenario's
    rate_hz: float = 0.0  # 0 = real time (1 / dt)
    seed: int = 0
    set: tuple[str, ...] = ()  # scenario constants name=value
    preset: str = ""  # named scenario constants applied before set; empty = the defaults
    plugins: tuple[str, ...] = ()  # files registering user scenarios
    noise_scale: float = -1.0  # negative = the scenario's
    checkpoints: tuple[str, ...] = ()  # method=path for neural methods
    options: tuple[str, ...] = ()  # method.name=value filter hyperparameters
    init: str = "prior"  # how the classical filters start: prior (the paper's) or observation
    device: str = "cpu"
    publish_covariance: bool = True
    output: str = ""  # bag path; empty = runs/<scenario>-<date>-<time>.mcap
    domain_id: int | None = None
    timeout: float = 600.0  # s for the whole run
    record_topics: tuple[str, ...] = ()  # extra topics for the evaluator to record (e.g. /diagnostics)
    stats_dir: str = ""  # each estimator writes <stats_dir>/<method>.json at shutdown ('' = no)
    estimator_params: tuple[str, ...] = ()  # name=value parameters of every estimator node (e.g. max_delay=0.05)
    realtime_priority: int = 0  # SCHED_FIFO priority of every node process (nodes/realtime.py); 0 = normal
    python: str = sys.executable


def queue_depth(cfg: PipelineConfig) -> int:
    """Every queue holds the whole run (up to MAX_DEPTH messages): a node that falls behind catches
    up later instead of losing messages (reliable, KEEP_LAST; transient_local publishers keep this
    many messages in memory)."""
    return int(min(MAX_DEPTH, max(10_000, cfg.trajectories * (cfg.horizon or 10_000) + 100)))


def live_nodes(cfg: PipelineConfig, bag: str) -> list[NodeSpec]:
    """The live comparison: evaluator, one estimator per method (``estimator_<method>``), simulator
    (waiting for ``len(methods) + 1`` observation subscribers), in start order."""
    depth = queue_depth(cfg)
    ckpt = dict(c.split("=", 1) for c in cfg.checkpoints)
    opts: dict[str, list[str]] = {}
    for item in cfg.options:
        key, _, value = item.partition("=")
        method, _, name = key.partition(".")
        opts.setdefault(method, []).append(f"{name}={value}")
    nodes = [
        NodeSpec(
            "evaluator",
            EVALUATOR,
            {
                "output": str(bag),
                "overwrite": True,
                "methods": list(cfg.methods),
                "completion_timeout": 60.0,
                "topics": list(cfg.record_topics),
                "queue_depth": depth,
                "starts": [
                    f"{m}={cfg.init}" for m in cfg.methods if table.has(m, takes_init=True) and cfg.init != "prior"
                ],
            },
            required=True,
        )
    ]
    for m in cfg.methods:
        nodes.append(
            NodeSpec(
                f"estimator_{m}",
                ESTIMATOR,
                {
                    "method": m,
                    "scenario": cfg.scenario,
                    "set": list(cfg.set),
                    "preset": cfg.preset,
                    "plugins": list(cfg.plugins),
                    "checkpoint": ckpt.get(m, ""),
                    "device": cfg.device,
                    "seed": cfg.seed,
                    **({"init": cfg.init} if table.has(m, takes_init=True) else {}),  # a start mode (--init)
                    "options": opts.get(m, []),
                    "publish_covariance": cfg.publish_covariance,
                    "stats_file": str(Path(cfg.stats_dir) / f"{m}.json") if cfg.stats_dir else "",
                    "queue_depth": depth,
                    "history_depth": depth,
                    **_assignments(cfg.estimator_params),
                },
            )
        )
    nodes.append(
        NodeSpec(
            "simulator",
            SIMULATOR,
            {
                "scenario": cfg.scenario,
                "set": list(cfg.set),
                "preset": cfg.preset,
                "plugins": list(cfg.plugins),
                "noise_scale": float(cfg.noise_scale),
                "seed": cfg.seed,
                "trajectories": cfg.trajectories,
                "horizon": cfg.horizon,
                "rate_hz": float(cfg.rate_hz),
                "wait_for_subscribers": len(cfg.methods) + 1,
                "wait_timeout": 120.0,
                "start_delay": 1.0,
                "history_depth": depth,
                "linger": 120.0,
                "stay_after_run": 0.0,
            },
        )
    )
    return nodes


# ---- launch arguments ----------------------------------------------------------------------------------
def params_file(node: str) -> str:
    """The installed ``share/neural_estimator/params/<node>.yaml`` (the source tree's beside a checkout)."""
    try:
        from ament_index_python.packages import PackageNotFoundError, get_package_share_directory

        try:
            path = Path(get_package_share_directory(PACKAGE)) / "params" / f"{node}.yaml"
            if path.exists():
                return str(path)
        except (PackageNotFoundError, OSError):  # OSError: no AMENT_PREFIX_PATH (a pip environment)
            pass
    except ImportError:
        pass
    return str(Path(__file__).resolve().parents[2] / "params" / f"{node}.yaml")


def _methods(text: str) -> tuple[str, ...]:
    methods = tuple(m.strip() for m in text.split(",") if m.strip())
    if not methods:
        raise GraphError("launch argument methods is empty: give e.g. methods:=ekf,ukf")
    return methods


def _number(args: Mapping[str, str], name: str, kind: type) -> Any:
    try:
        return kind(args[name])
    except ValueError:
        raise GraphError(f"launch argument {name} must be a {kind.__name__}, got {args[name]!r}") from None


def _bool(args: Mapping[str, str], name: str) -> bool:
    value = str(args[name]).strip().lower()
    if value in ("true", "1", "yes", "on"):
        return True
    if value in ("false", "0", "no", "off"):
        return False
    raise GraphError(f"launch argument {name} must be true or false, got {args[name]!r}")


def _init(value: str) -> str:
    if value not in ("prior", "observation"):
        raise GraphError(f"launch argument init must be prior or observation, got {value!r}")
    return value


def _live(args: Mapping[str, str]) -> list[NodeSpec]:
    cfg = PipelineConfig(
        scenario=args["scenario"],
        methods=_methods(args["methods"]),
        trajectories=_number(args, "trajectories", int),
        horizon=_number(args, "horizon", int),
        rate_hz=_number(args, "rate_hz", float),
        seed=_number(args, "seed", int),
        init=_init(args["init"]),
        preset=args["preset"],
    )
    return live_nodes(cfg, args["output"] or f"runs/{cfg.scenario}-live.mcap")


def _estimator(args: Mapping[str, str]) -> list[NodeSpec]:
    params: dict[str, Any] = {"use_sim_time": _bool(args, "use_sim_time")}
    for name in ("method", "scenario"):
        if args[name]:
            params[name] = args[name]
    name = args["node_name"] or (f"estimator_{args['method']}" if args["method"] else "estimator")
    return [NodeSpec(name, ESTIMATOR, params, params_files=(args["params_file"] or params_file("estimator"),))]


def _robot(args: Mapping[str, str]) -> list[NodeSpec]:
    if not args["checkpoint"]:
        raise GraphError("launch argument checkpoint is required: a model trained with neural-estimator train --data")
    sim_time = _bool(args, "use_sim_time") or bool(args["bag"])  # a played bag's clock is the clock
    nodes = []
    if args["bag"] and args["spec"]:
        nodes.append(
            NodeSpec(
                "evaluator",
                EVALUATOR,
                {
                    "output": args["output"] or "runs/robot-replay.mcap",
                    "overwrite": True,
                    "spec": args["spec"],
                    "spec_length": _number(args, "spec_length", int),
                    "topics": ["/clock"] + _truth_topics(args["spec"]),
                    "idle_timeout": 3.0,
                    "use_sim_time": True,
                },
                required=True,
            )
        )
    nodes.append(
        NodeSpec(
            "robot_estimator",
            ROBOT_ESTIMATOR,
            {"checkpoint": args["checkpoint"], "use_sim_time": sim_time},
            params_files=(args["params_file"] or params_file("robot_estimator"),),
        )
    )
    if args["bag"]:
        rate = _number(args, "rate", float)
        nodes.append(
            NodeSpec(
                "player",
                PLAYER,
                {
                    "bag": args["bag"],
                    "rate": rate,
                    "publish_clock": True,
                    "wait_for_subscribers": 1,
                    "wait_topic": args["wait_topic"],
                    "start_delay": 1.0,
                },
                required=not args["spec"],
            )
        )
    return nodes


def _truth_topics(spec_path: str) -> list[str]:
    """The topics of a spec's ground truth (what the evaluator must record to score it)."""
    from neural_estimator.robot import SpecError, load_spec

    try:
        spec = load_spec(spec_path)
    except SpecError as exc:
        raise GraphError(f"launch argument spec: {exc}") from None
    return sorted({f.topic for f in spec.vectors["state"]})


def _replay(args: Mapping[str, str]) -> list[NodeSpec]:
    if not args["bag"]:
        raise GraphError("launch argument bag is required: a .mcap file or rosbag2 directory")
    methods = _methods(args["methods"])
    nodes = [
        NodeSpec(
            "evaluator",
            EVALUATOR,
            {"output": args["output"] or "runs/replay.mcap", "overwrite": True, "methods": list(methods)},
            required=True,
        )
    ]
    for m in methods:
        params: dict[str, Any] = {"method": m}
        if args["scenario"]:
            params["scenario"] = args["scenario"]
        nodes.append(NodeSpec(f"estimator_{m}", ESTIMATOR, params))
    nodes.append(
        NodeSpec(
            "player",
            PLAYER,
            {
                "bag": args["bag"],
                "rate": _number(args, "rate", float),
                "wait_for_subscribers": len(methods) + 1,
                "start_delay": 1.0,
            },
        )
    )
    return nodes


@dataclasses.dataclass(frozen=True)
class Graph:
    """A launch file's arguments {name: (default, help)} and its builder."""

    arguments: dict[str, tuple[str, str]]
    build: Callable[[Mapping[str, str]], list[NodeSpec]]
    doc: str


GRAPHS: dict[str, Graph] = {
    "live": Graph(
        {
            "scenario": ("lorenz96", "scenario name"),
            "methods": ("ekf,ukf", "comma-separated methods, one estimator node each"),
            "rate_hz": ("0.0", "observations per second (0 = real time, 1 / dt)"),
            "trajectories": ("2", "trajectories simulated"),
            "horizon": ("0", "steps per trajectory (0 = the scenario's)"),
            "seed": ("0", "simulation and filter seed"),
            "init": ("prior", "how the classical filters start: prior (the paper's) or observation"),
            "preset": ("", "named scenario constants (e.g. v3); empty = the defaults"),
            "output": ("", "bag the evaluator writes (default runs/<scenario>-live.mcap)"),
        },
        _live,
        "simulator -> one estimator per method -> evaluator (ends when the run is scored)",
    ),
    "estimator": Graph(
        {
            "params_file": ("", "params file (default: the installed params/estimator.yaml)"),
            "method": ("", "overrides the params file's method"),
            "scenario": ("", "overrides the params file's scenario"),
            "node_name": ("", "node name (default estimator_<method>, or estimator when method is empty)"),
            "use_sim_time": ("false", "run on /clock"),
        },
        _estimator,
        "one estimator node with its params file (robot_localization's ekf.launch.py)",
    ),
    "robot_estimator": Graph(
        {
            "checkpoint": ("", "model trained with neural-estimator train --data (its card holds the spec)"),
            "params_file": ("", "params file (default: the installed params/robot_estimator.yaml)"),
            "use_sim_time": ("false", "run on /clock (always on when bag is given)"),
            "bag": ("", "a recording to play with /clock (empty: the robot's live topics)"),
            "rate": ("1.0", "playback speed factor of bag"),
            "wait_topic": ("/imu", "recorded topic whose subscriber the player waits for"),
            "spec": ("", "with bag: score the run through this spec (evaluator records and scores)"),
            "spec_length": ("20", "steps per scored trajectory"),
            "output": ("", "bag the evaluator writes (default runs/robot-replay.mcap)"),
        },
        _robot,
        "the robot estimator on its spec's topics; with bag: player on /clock (+ evaluator with spec)",
    ),
    "replay": Graph(
        {
            "bag": ("", "bag to play (.mcap or rosbag2 directory) with an observation stream"),
            "methods": ("ekf,ukf", "comma-separated methods, one estimator node each"),
            "scenario": ("", "scenario of a bag without a scenario topic"),
            "rate": ("1.0", "playback speed factor"),
            "output": ("", "bag the evaluator writes (default runs/replay.mcap)"),
        },
        _replay,
        "player -> one estimator per method -> evaluator",
    ),
}


def build(graph: str, overrides: Mapping[str, str] | None = None) -> list[NodeSpec]:
    """The NodeSpecs of ``graph`` with its arguments' defaults replaced by ``overrides``."""
    if graph not in GRAPHS:
        raise GraphError(f"unknown graph {graph!r}; one of {', '.join(GRAPHS)}")
    g = GRAPHS[graph]
    unknown = set(overrides or {}) - set(g.arguments)
    if unknown:
        raise GraphError(f"{graph}: unknown launch argument(s) {', '.join(sorted(unknown))}")
    args = {k: d for k, (d, _) in g.arguments.items()}
    args.update({k: str(v) for k, v in (overrides or {}).items()})
    return g.build(args)


def launch_description(graph: str):
    """The ``launch.LaunchDescription`` of ``graph`` (what the files in ``launch/`` return): one
    ``DeclareLaunchArgument`` per argument, and the nodes built when the launch runs."""
    from launch import LaunchDescription
    from launch.actions import DeclareLaunchArgument, OpaqueFunction, Shutdown
    from launch.substitutions import LaunchConfiguration
    from launch_ros.actions import Node

    g = GRAPHS[graph]

    def nodes(context, *args, **kwargs):
        values = {k: LaunchConfiguration(k).perform(context) for k in g.arguments}
        return [
            Node(
                package=PACKAGE,
                executable=spec.executable,
                name=spec.name,
                parameters=[*spec.params_files, spec.ros_params()],
                output="screen",
                on_exit=[Shutdown(reason=f"{spec.name} exited")] if spec.required else None,
            )
            for spec in g.build(values)
        ]

    declared = [DeclareLaunchArgument(k, default_value=d, description=h) for k, (d, h) in g.arguments.items()]
    return LaunchDescription([*declared, OpaqueFunction(function=nodes)])


class _RawArg(str):
    """A parameter value passed through as written (``-p name:=value``)."""


def _assignments(items: tuple[str, ...]) -> dict[str, Any]:
    """``name=value`` strings as parameters (values parsed as YAML scalars by the node)."""
    out: dict[str, Any] = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name:
            raise GraphError(f"estimator parameter must be name=value, got {item!r}")
        out[name.strip()] = _RawArg(value.strip())
    return out


def ros_arg(value: Any) -> str:
    """A parameter value as ``--ros-args -p name:=VALUE`` parses it (YAML)."""
    if isinstance(value, _RawArg):
        return str(value)
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, (list, tuple)):
        return json.dumps([str(v) for v in value]) if value else "[]"
    return json.dumps(str(value))  # a quoted YAML string: "123" stays a string


def command(python: str, spec: NodeSpec) -> list[str]:
    """The pip path's command of a NodeSpec: ``python -m module --ros-args -r __node:=name
    [--params-file f] -p k:=v ...`` (the same parameters ``launch_ros`` passes)."""
    cmd = [python, "-m", spec.module, "--ros-args", "-r", f"__node:={spec.name}"]
    for f in spec.params_files:
        cmd += ["--params-file", os.fspath(f)]
    for k, v in spec.ros_params().items():
        cmd += ["-p", f"{k}:={ros_arg(v)}"]
    return cmd


def main(argv: list[str] | None = None) -> int:
    """``python -m neural_estimator.nodes.graph GRAPH [name:=value ...]``: print the pip path's command
    of every node of a graph (what its launch file starts), one per line, in start order."""
    import shlex

    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help"):
        print("usage: python -m neural_estimator.nodes.graph GRAPH [name:=value ...]\ngraphs:")
        for name, g in GRAPHS.items():
            print(
                f"  {name}: {g.doc}; arguments: "
                + ", ".join(f"{k} ({d or 'empty'})" for k, (d, _) in g.arguments.items())
            )
        return 0 if argv else 2
    overrides = {}
    for item in argv[1:]:
        key, sep, value = item.partition(":=")
        if not sep:
            print(f"graph: error: expected name:=value, got {item!r}", file=sys.stderr)
            return 2
        overrides[key] = value
    try:
        specs = build(argv[0], overrides)
    except GraphError as exc:
        print(f"graph: error: {exc}", file=sys.stderr)
        return 2
    for spec in specs:
        print(shlex.join(command(sys.executable, spec)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
