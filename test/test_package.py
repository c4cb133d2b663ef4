"""The package is a real ament_python package: colcon sees it as such and installs the executables
where `ros2 run` looks for them (lib/neural_estimator)."""

import re
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
from conftest import top_level_imports

ROOT = Path(__file__).resolve().parents[1]
COLCON = Path(sys.executable).with_name("colcon")


def test_package_xml_is_format3_ament_python_with_valid_maintainer():
    root = ET.parse(ROOT / "package.xml").getroot()
    assert root.get("format") == "3"
    assert root.findtext("name") == "neural_estimator"
    assert root.find("export/build_type").text == "ament_python"
    email = root.find("maintainer").get("email")
    assert re.fullmatch(r"[^@\s]+@[^@\s]+\.[a-z]{2,}", email), email
    deps = {e.text for e in root.findall("exec_depend")}
    assert {"rclpy", "sensor_msgs", "std_msgs", "diagnostic_msgs", "std_srvs"} <= deps


@pytest.mark.colcon
@pytest.mark.skipif(not COLCON.exists(), reason="colcon is not installed in this environment")
def test_colcon_lists_and_builds_the_package(tmp_path):
    src = tmp_path / "ws" / "src"
    src.mkdir(parents=True)
    # copy only what a source checkout has (no venv, no caches)
    shutil.copytree(
        ROOT,
        src / "neural_estimator",
        ignore=shutil.ignore_patterns(
            ".venv", ".git", "__pycache__", "*.egg-info", "build", "install", "log", ".cache", "runs", "out"
        ),
    )
    ws = tmp_path / "ws"
    listed = subprocess.run([str(COLCON), "list"], cwd=ws, capture_output=True, text=True, check=True).stdout
    assert re.search(r"^neural_estimator\s+src/neural_estimator\s+\(ros\.ament_python\)$", listed, re.M), listed
    build = subprocess.run([str(COLCON), "build"], cwd=ws, capture_output=True, text=True)
    assert build.returncode == 0, build.stdout + build.stderr
    lib = ws / "install" / "neural_estimator" / "lib" / "neural_estimator"
    for exe in ("neural-estimator", "simulator", "estimator", "evaluator", "player", "robot_estimator"):
        assert (lib / exe).exists(), exe  # where `ros2 run neural_estimator <exe>` looks
    launch = ws / "install" / "neural_estimator" / "share" / "neural_estimator" / "launch"
    assert {p.name for p in launch.glob("*.launch.py")} == {
        "live.launch.py",
        "estimator.launch.py",
        "robot_estimator.launch.py",
        "replay.launch.py",
    }
    params = ws / "install" / "neural_estimator" / "share" / "neural_estimator" / "params"
    assert {p.name for p in params.glob("*.yaml")} == {
        "simulator.yaml",
        "estimator.yaml",
        "evaluator.yaml",
        "player.yaml",
        "robot_estimator.yaml",
    }
    share = ws / "install" / "neural_estimator" / "share"
    assert (share / "ament_index" / "resource_index" / "packages" / "neural_estimator").exists()
    assert (share / "neural_estimator" / "package.xml").exists()


# Imports guarded by `except ImportError` (optional speed-ups or GPU kernels), not dependencies.
OPTIONAL_IMPORTS = {"mamba_ssm", "lz4"}
# The ROS 2 interfaces come with the ROS install (package.xml) or the "ros" extra's wheels.
ROS_PACKAGES = {
    "rclpy",
    "rcl_interfaces",
    "std_msgs",
    "sensor_msgs",
    "nav_msgs",
    "diagnostic_msgs",
    "std_srvs",
    "rosgraph_msgs",
    "builtin_interfaces",
    "geometry_msgs",
    "lifecycle_msgs",
    "tf2_msgs",  # publish_tf (no wheel: a ROS install's)
    "ament_index_python",
    "launch",  # the launch files (a ROS install's; not on PyPI)
    "launch_ros",
}


def _declared_requirements() -> tuple[set[str], dict[str, set[str]]]:
    import ast

    tree = ast.parse((ROOT / "setup.py").read_text())
    call = next(n for n in ast.walk(tree) if isinstance(n, ast.Call) and getattr(n.func, "id", "") == "setup")
    kw = {k.arg: ast.literal_eval(k.value) for k in call.keywords if k.arg in ("install_requires", "extras_require")}

    def name(req: str) -> str:
        return re.split(r"[\[<>=!~ ]", req, maxsplit=1)[0].lower().replace("_", "-")

    return (
        {name(r) for r in kw["install_requires"]},
        {extra: {name(r) for r in reqs} for extra, reqs in kw["extras_require"].items()},
    )


@pytest.mark.slow
def test_every_third_party_import_is_a_declared_dependency():
    """`pip install .` must give a package that imports: each distribution the package imports is in
    install_requires, or in the extra of the feature that imports it (ROS nodes, reproduce, references)."""
    import importlib.metadata as md

    core, extras = _declared_requirements()
    declared = core | set().union(*extras.values())
    providers = md.packages_distributions()
    missing = {}
    for path in (ROOT / "neural_estimator").rglob("*.py"):
        for top in sorted(top_level_imports(path)):
            if top in sys.stdlib_module_names or top == "neural_estimator" or top in OPTIONAL_IMPORTS:
                continue
            if top in ROS_PACKAGES:
                assert "ros-jazzy-rclpy" in extras["ros"]
                continue
            dists = {d.lower().replace("_", "-") for d in providers.get(top, [top])}
            if not dists & declared:
                missing.setdefault(top, []).append(path.name)
    assert not missing, f"imported but not declared in setup.py: {missing}"
    assert {"numpy", "torch", "safetensors", "rosbags", "mcap", "pyyaml"} <= core  # what every verb needs
