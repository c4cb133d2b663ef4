"""Entry points of the ROS 2 node executables (``ros2 run neural_estimator <name>``).

Each checks that rclpy imports before the node module is loaded, so that an install without the
ROS 2 wheels says in one line what to install instead of a ``ModuleNotFoundError`` traceback.
``python -m neural_estimator.nodes.entry <name> [args ...]`` runs a node by name (what
``neural-estimator ros2 run`` does in a pip environment, where no node executable is on PATH).
"""

from __future__ import annotations

import importlib
import sys

# executable name -> module whose main() runs the node
NODES = {
    "simulator": "neural_estimator.nodes.simulator_node",
    "estimator": "neural_estimator.nodes.estimator_node",
    "evaluator": "neural_estimator.nodes.evaluator_node",
    "player": "neural_estimator.nodes.player_node",
    "robot_estimator": "neural_estimator.nodes.robot_estimator_node",
    "lifecycle_estimator": "neural_estimator.nodes.lifecycle_estimator_node",
}

# executable name -> (module, parameter dataclass) of every parameter it declares
_OUTPUTS = ("neural_estimator.nodes.outputs", "OutputParams")
_INPUTS = ("neural_estimator.nodes.diagnostics", "InputDiagnosticsParams")
_ROBOT = (("neural_estimator.nodes.robot_estimator_node", "RobotEstimatorParams"), _OUTPUTS, _INPUTS)
_ESTIMATOR = (("neural_estimator.nodes.estimator_params", "EstimatorParams"), _OUTPUTS, _INPUTS)
PARAMETERS = {
    "simulator": (("neural_estimator.nodes.simulator_node", "SimulatorParams"),),
    "estimator": _ESTIMATOR + _ROBOT[:1],  # the estimator becomes the robot estimator for a `train --data` model
    "evaluator": (("neural_estimator.nodes.evaluator_node", "EvaluatorParams"),),
    "player": (("neural_estimator.nodes.player_node", "PlayerParams"),),
    "robot_estimator": _ROBOT,
    "lifecycle_estimator": _ESTIMATOR,
}
ROS_PARAMETERS = ("use_sim_time", "start_type_description_service")  # rclpy declares these on every node

NO_RCLPY = (
    "{name}: the ROS 2 nodes need rclpy: pip install 'neural_estimator[ros]' "
    "(the ros-jazzy-* wheels), or source a ROS 2 Jazzy install"
)


def rclpy_missing() -> bool:
    try:
        import rclpy  # noqa: F401
    except ImportError:
        return True
    return False


def run(name: str, args: list[str] | None = None) -> int:
    """Run node ``name``'s main(); exit status 1 with one line when rclpy is missing."""
    if rclpy_missing():
        print(NO_RCLPY.format(name=name), file=sys.stderr)
        return 1
    return int(importlib.import_module(NODES[name]).main(args) or 0)


def simulator() -> int:
    return run("simulator")


def estimator() -> int:
    return run("estimator")


def evaluator() -> int:
    return run("evaluator")


def player() -> int:
    return run("player")


def robot_estimator() -> int:
    return run("robot_estimator")


def lifecycle_estimator() -> int:
    return run("lifecycle_estimator")


def parameter_fields(name: str) -> list:
    """The dataclass fields of every parameter node ``name`` declares, in declaration order (each once)."""
    import dataclasses

    out, seen = [], set()
    for module, cls in PARAMETERS[name]:
        for f in dataclasses.fields(getattr(importlib.import_module(module), cls)):
            if f.name not in seen:
                seen.add(f.name)
                out.append(f)
    return out


def wants_help(argv: list[str]) -> bool:
    """``-h`` / ``--help`` before any ``--ros-args``."""
    head = argv[: argv.index("--ros-args")] if "--ros-args" in argv else argv
    return any(a in ("-h", "--help") for a in head)


def help_text(name: str) -> str:
    """The node's usage and every parameter with its type, default and meaning (``--help``)."""
    import typing

    lines = [
        f"usage: ros2 run neural_estimator {name} --ros-args [-p NAME:=VALUE ...] [--params-file FILE]",
        "",
        "parameters (read once at start-up; docs/nodes.md):",
    ]
    hints = {}
    for module, cls in PARAMETERS[name]:
        hints.update(typing.get_type_hints(getattr(importlib.import_module(module), cls)))
    for f in parameter_fields(name):
        default = list(f.default) if isinstance(f.default, tuple) else f.default
        kind = getattr(hints.get(f.name), "__name__", str(hints.get(f.name)))
        lines.append(f"  {f.name} ({kind}, default {default!r}): {f.metadata.get('help', '')}")
    return "\n".join(lines)


def given_parameters(argv: list[str], node_name: str) -> list[str]:
    """Names of the parameters the command line gives the node: ``-p``/``--param NAME:=VALUE`` after
    ``--ros-args``, and the ``ros__parameters`` of ``--params-file`` entries for ``/**`` or this node."""
    names: list[str] = []
    files: list[str] = []
    ros = False
    for i, a in enumerate(argv):
        if a == "--ros-args":
            ros = True
        elif a == "--":
            ros = False
        elif ros and a in ("-p", "--param") and i + 1 < len(argv) and ":=" in argv[i + 1]:
            names.append(argv[i + 1].split(":=", 1)[0].split(":")[-1])
        elif ros and a == "--params-file" and i + 1 < len(argv):
            files.append(argv[i + 1])
        elif ros and a == "-r" and i + 1 < len(argv) and argv[i + 1].startswith("__node:="):
            node_name = argv[i + 1].split(":=", 1)[1]
    for path in files:
        try:
            import yaml

            with open(path) as fh:
                doc = yaml.safe_load(fh) or {}
        except (OSError, ValueError, ImportError, yaml.YAMLError):
            continue  # rclpy reports an unreadable params file itself
        for key, entry in doc.items() if isinstance(doc, dict) else ():
            if (key == "/**" or str(key).rstrip("/").split("/")[-1] == node_name) and isinstance(entry, dict):
                names += list((entry.get("ros__parameters") or {}).keys())
    return names


def unknown_parameters(name: str, argv: list[str], node_name: str | None = None) -> list[str]:
    """One warning line per parameter given to node ``name`` that it does not declare (ignored by
    ROS), with the closest declared name ("did you mean")."""
    import difflib

    known = [f.name for f in parameter_fields(name)] + list(ROS_PARAMETERS)
    out = []
    for given in dict.fromkeys(given_parameters(argv, node_name or name)):
        if given in known:
            continue
        close = difflib.get_close_matches(given, known, n=1)
        out.append(f"unknown parameter '{given}' (ignored)" + (f"; did you mean '{close[0]}'?" if close else ""))
    return out


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] not in NODES:
        print(f"usage: python -m neural_estimator.nodes.entry {{{','.join(NODES)}}} [args ...]", file=sys.stderr)
        return 2
    sys.argv = [argv[0], *argv[1:]]  # rclpy reads --ros-args from sys.argv
    return run(argv[0])


if __name__ == "__main__":
    sys.exit(main())
