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
    "simulator": "sim_nodes.simulator",
    "estimator": "neural_estimator.nodes.estimator_node",
    "evaluator": "neural_estimator.nodes.evaluator_node",
    "player": "neural_estimator.nodes.player_node",
    "robot_estimator": "neural_estimator.nodes.robot_estimator_node",
    "lifecycle_estimator": "neural_estimator.nodes.lifecycle_estimator_node",
}

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


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] not in NODES:
        print(f"usage: python -m neural_estimator.nodes.entry {{{','.join(NODES)}}} [args ...]", file=sys.stderr)
        return 2
    sys.argv = [argv[0], *argv[1:]]  # rclpy reads --ros-args from sys.argv
    return run(argv[0])


if __name__ == "__main__":
    sys.exit(main())
