"""package.xml is what rosdep resolves: every ROS package the code imports is declared, nothing
declared is unused, and every Python dependency of setup.py has its rosdep key or is named pip-only."""

from __future__ import annotations

import ast
import functools
import importlib.metadata as md
import re
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
from conftest import top_level_imports

ROOT = Path(__file__).resolve().parents[1]
SOURCES = [ROOT / "neural_estimator", ROOT / "launch"]
ROS_TOOLS = {"rclpy", "launch", "launch_ros", "ament_index_python", "tf2_ros"}
# setup.py's install_requires -> its rosdep key (rosdistro's rosdep/python.yaml)
ROSDEP_KEYS = {
    "numpy": "python3-numpy",
    "scipy": "python3-scipy",
    "numba": "python3-numba",
    "matplotlib": "python3-matplotlib",
    "tqdm": "python3-tqdm",
    "pyyaml": "python3-yaml",
    "rosbags": "python3-rosbags-pip",
}


def _imports() -> dict[str, set[str]]:
    """{top-level module: files importing it} over the package, the simulator nodes and the launch files."""
    out: dict[str, set[str]] = {}
    for src in SOURCES:
        for path in src.rglob("*.py"):
            for n in top_level_imports(path):
                out.setdefault(n, set()).add(path.relative_to(ROOT).as_posix())
    return out


@functools.cache
def _distributions() -> dict[str, list[str]]:
    """{top-level module: distributions}; read once (it scans every installed distribution's files)."""
    return md.packages_distributions()


def _is_ros(module: str) -> bool:
    if module in ROS_TOOLS or re.search(r"_(msgs|srvs|interfaces)$", module):
        return True
    return any(d.lower().startswith("ros-") for d in _distributions().get(module, []))


def _package_xml():
    root = ET.parse(ROOT / "package.xml").getroot()
    exec_deps = {e.text.strip() for e in root.findall("exec_depend")}
    comments = (ROOT / "package.xml").read_text()
    pip_only = set(re.search(r"<!-- pip-only: ([^\n(]+)", comments).group(1).split())
    return exec_deps, pip_only


def _install_requires() -> set[str]:
    tree = ast.parse((ROOT / "setup.py").read_text())
    call = next(n for n in ast.walk(tree) if isinstance(n, ast.Call) and getattr(n.func, "id", "") == "setup")
    reqs = ast.literal_eval(next(k.value for k in call.keywords if k.arg == "install_requires"))
    return {re.split(r"[\[<>=!~ ]", r, maxsplit=1)[0].lower() for r in reqs}


@pytest.mark.slow
def test_every_imported_ros_package_is_declared_and_every_declared_one_imported():
    imports = _imports()
    ros = {m for m in imports if _is_ros(m) and m not in sys.stdlib_module_names}
    exec_deps, _ = _package_xml()
    missing = {m: sorted(imports[m]) for m in ros - exec_deps}
    assert not missing, f"imported but not in package.xml: {missing}"
    declared_ros = {d for d in exec_deps if not d.startswith("python3-")}
    assert declared_ros - ros == set(), f"declared in package.xml but never imported: {declared_ros - ros}"
    assert {"nav_msgs", "rosgraph_msgs", "geometry_msgs", "tf2_msgs", "launch_ros"} <= ros  # what this checks


def test_every_python_dependency_has_its_rosdep_key_or_is_pip_only():
    exec_deps, pip_only = _package_xml()
    for dist in _install_requires():
        if dist in pip_only:
            assert dist not in ROSDEP_KEYS, f"{dist}: has a rosdep key, declare it instead of pip-only"
            continue
        assert dist in ROSDEP_KEYS, f"{dist}: neither a rosdep key in package.xml nor named pip-only"
        assert ROSDEP_KEYS[dist] in exec_deps, f"{dist}: package.xml lacks <exec_depend>{ROSDEP_KEYS[dist]}"
    python_keys = {d for d in exec_deps if d.startswith("python3-")}
    assert python_keys == {ROSDEP_KEYS[d] for d in _install_requires() if d in ROSDEP_KEYS}
    assert pip_only == {"torch", "safetensors", "mcap", "zstandard", "onnxruntime", "onnx"}


@pytest.mark.slow
def test_a_missing_declaration_is_caught(tmp_path, monkeypatch):
    """The check above fails for a package.xml without nav_msgs (the check can fail)."""
    text = (ROOT / "package.xml").read_text().replace("<exec_depend>nav_msgs</exec_depend>", "")
    root = ET.fromstring(text)
    exec_deps = {e.text.strip() for e in root.findall("exec_depend")}
    ros = {m for m in _imports() if _is_ros(m)}
    assert ros - exec_deps == {"nav_msgs"}
