"""The smallest ``ros2 run``: lets the documented commands work the same in a pip virtual environment.

pip installs of ROS 2 (the ros-jazzy-* wheels) have no ``ros2`` command line. This module is
reached as ``neural-estimator ros2 ...`` (or ``python -m neural_estimator.cli.ros2_shim``; pip puts no
generic ``ros2`` into ``bin/``) and understands

    ros2 run <package> <executable> [args ...]      (e.g. --ros-args -p method:=mamba)
    ros2 pkg executables [<package>]
    ros2 launch neural_estimator <graph>.launch.py [name:=value ...] [--show-args]

``ros2 launch`` starts the nodes of the package's launch files from their description
(:mod:`neural_estimator.nodes.graph`) as processes, without the ``launch`` package (not on PyPI).
Whenever a real ``ros2`` is on PATH (a ROS 2 install has been sourced), every call is handed to it
unchanged, so on a real Jazzy install nothing here is used. Executables are looked up in the
package's install prefix (``<prefix>/lib/<package>/<executable>``, found through
AMENT_PREFIX_PATH, as colcon installs them); this package's nodes are otherwise run as
``python -m neural_estimator.nodes.entry <name>`` with this interpreter.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

USAGE = (
    "usage: neural-estimator ros2 run <package> <executable> [args ...]\n"
    "       neural-estimator ros2 pkg executables [<package>]\n"
    "       neural-estimator ros2 launch neural_estimator <graph>.launch.py [name:=value ...] [--show-args]\n"
    "(this is neural_estimator's minimal ros2 for pip environments; source a ROS 2 install for the full CLI)"
)


def _real_ros2() -> str | None:
    """A ``ros2`` on PATH that is not a copy of this shim (older installs put one into ``bin/``)."""
    for d in os.environ.get("PATH", "").split(os.pathsep):
        cand = Path(d) / "ros2"
        if cand.is_file() and os.access(cand, os.X_OK):
            try:
                head = cand.read_bytes()[:4096]
            except OSError:
                continue
            if b"ros2_shim" not in head:  # this module, now or in its top-level home of older installs
                return str(cand)
    return None


def _package_executables(package: str) -> dict[str, list[str]]:
    """{executable name: command} of ``package`` from ament prefixes, then this package's own."""
    found: dict[str, list[str]] = {}
    for prefix in filter(None, os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep)):
        lib = Path(prefix) / "lib" / package
        if lib.is_dir():
            for f in sorted(lib.iterdir()):
                if f.is_file() and os.access(f, os.X_OK):
                    found.setdefault(f.name, [str(f)])
    if package == "neural_estimator":
        from neural_estimator.nodes.entry import NODES

        for name in NODES:
            found.setdefault(name, [sys.executable, "-m", "neural_estimator.nodes.entry", name])
        found.setdefault("neural-estimator", [sys.executable, "-m", "neural_estimator.cli"])
    return found


def _launch(package: str, file: str, rest: list[str]) -> int:
    """``ros2 launch neural_estimator <graph>.launch.py [name:=value ...]`` from the graph description."""
    from neural_estimator.nodes.graph import GRAPHS, GraphError, build
    from neural_estimator.nodes.launch import run_graph

    graph = Path(file).name.removesuffix(".launch.py")
    if package != "neural_estimator" or graph not in GRAPHS:
        files = ", ".join(f"{g}.launch.py" for g in GRAPHS)
        print(f"ros2 launch: no launch file {file!r} in package {package!r} (launch files: {files})", file=sys.stderr)
        return 1
    if "--show-args" in rest or "-s" in rest:
        print("Arguments (pass arguments as '<name>:=<value>'):")
        for name, (default, help_) in GRAPHS[graph].arguments.items():
            print(f"\n    '{name}':\n        {help_}\n        (default: '{default}')")
        return 0
    overrides = {}
    for item in rest:
        key, sep, value = item.partition(":=")
        if not sep:
            print(f"ros2 launch: expected <name>:=<value>, got {item!r}", file=sys.stderr)
            return 2
        overrides[key] = value
    try:
        specs = build(graph, overrides)
    except GraphError as exc:
        print(f"ros2 launch: {exc}", file=sys.stderr)
        return 2
    return run_graph(specs)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    real = _real_ros2()
    if real:
        os.execv(real, [real, *argv])
    if len(argv) >= 3 and argv[0] == "run":
        package, exe, rest = argv[1], argv[2], argv[3:]
        exes = _package_executables(package)
        if exe not in exes:
            known = ", ".join(sorted(exes)) or "none found"
            print(f"ros2 run: no executable {exe!r} in package {package!r} (executables: {known})", file=sys.stderr)
            return 1
        cmd = exes[exe]
        os.execv(cmd[0], [*cmd, *rest])
    if len(argv) >= 3 and argv[0] == "launch":
        return _launch(argv[1], argv[2], argv[3:])
    if len(argv) >= 2 and argv[:2] == ["pkg", "executables"]:
        for package in argv[2:] or ["neural_estimator"]:
            for name in sorted(_package_executables(package)):
                print(f"{package} {name}")
        return 0
    print(USAGE, file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
