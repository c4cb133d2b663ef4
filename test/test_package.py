"""The package is a real ament_python package: colcon sees it as such and installs the executables
where `ros2 run` looks for them (lib/neural_estimator)."""

import re
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

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


@pytest.mark.skipif(not COLCON.exists(), reason="colcon is not installed in this environment")
def test_colcon_lists_and_builds_the_package(tmp_path):
    src = tmp_path / "ws" / "src"
    src.mkdir(parents=True)
    # copy only what a source checkout has (no venv, no caches)
    shutil.copytree(ROOT, src / "neural_estimator", ignore=shutil.ignore_patterns(
        ".venv", ".git", "__pycache__", "*.egg-info", "build", "install", "log", ".cache", "runs", "out"))
    ws = tmp_path / "ws"
    listed = subprocess.run([str(COLCON), "list"], cwd=ws, capture_output=True, text=True, check=True).stdout
    assert re.search(r"^neural_estimator\s+src/neural_estimator\s+\(ros\.ament_python\)$", listed, re.M), listed
    build = subprocess.run([str(COLCON), "build"], cwd=ws, capture_output=True, text=True)
    assert build.returncode == 0, build.stdout + build.stderr
    lib = ws / "install" / "neural_estimator" / "lib" / "neural_estimator"
    for exe in ("neural-estimator", "simulator", "estimator", "evaluator", "player"):
        assert (lib / exe).exists(), exe  # where `ros2 run neural_estimator <exe>` looks
    params = ws / "install" / "neural_estimator" / "share" / "neural_estimator" / "params"
    assert {p.name for p in params.glob("*.yaml")} == {"simulator.yaml", "estimator.yaml", "evaluator.yaml", "player.yaml"}
    share = ws / "install" / "neural_estimator" / "share"
    assert (share / "ament_index" / "resource_index" / "packages" / "neural_estimator").exists()
    assert (share / "neural_estimator" / "package.xml").exists()
