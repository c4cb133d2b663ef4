"""ament_python package; also installs with pip (``pip install -e .``) and exposes ``neural-estimator``."""

import sys
from glob import glob

from setuptools import find_packages, setup

package_name = "neural_estimator"

# The node executables go where `ros2 run neural_estimator <name>` finds them: lib/neural_estimator
# (setup.cfg), which is what colcon's `setup.py install|develop` makes of console scripts. A wheel
# (pip) would put them into bin/ under generic names, so pip gets only `neural-estimator`; there
# the nodes run as `neural-estimator ros2 run neural_estimator <name>` (neural_estimator/cli/ros2_shim.py).
_NODES = [
    "simulator = neural_estimator.nodes.entry:simulator",
    "estimator = neural_estimator.nodes.entry:estimator",
    "evaluator = neural_estimator.nodes.entry:evaluator",
    "player = neural_estimator.nodes.entry:player",
    "robot_estimator = neural_estimator.nodes.entry:robot_estimator",
    "lifecycle_estimator = neural_estimator.nodes.entry:lifecycle_estimator",
]
_WHEEL = any(cmd in sys.argv for cmd in ("bdist_wheel", "editable_wheel", "dist_info"))

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(include=["neural_estimator", "neural_estimator.*"]),
    package_data={
        "neural_estimator": [
            "serving/zoo/*/*.safetensors",
            "serving/zoo/*/*.json",
            "serving/zoo/*/*.onnx",
            "serving/zoo/instances/*/*/*.safetensors",
            "serving/zoo/instances/*/*/*.json",
            "serving/zoo/instances/*/*/*.onnx",
            "serving/zoo/variants/*/*/*.safetensors",  # e.g. variants/observations/<pair>/: trained without states
            "serving/zoo/variants/*/*/*.json",
            "serving/zoo/variants/*/*/*.onnx",
            "paper/paper_results.json",
            "nodes/*.xml",
            "serving/uncertainty/calibrated_filters.json",
        ]
    },
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{package_name}"]),
        (f"share/{package_name}", ["package.xml"]),
        (f"share/{package_name}/params", glob("params/*.yaml")),
        (f"share/{package_name}/launch", glob("launch/*.launch.py")),
        (f"share/{package_name}/bags", glob("bags/*.mcap")),
    ],
    # What `pip install .` needs for every verb but `reproduce` and the nodes (the "ros" extra). The
    # main job's install (scripts/requirements.txt) pins torch to the CPU build; here a range, so
    # that an existing torch (CPU or CUDA) is kept. test/test_package.py checks every import is declared.
    install_requires=[
        "numpy>=1.26",
        "scipy>=1.11",
        "torch>=2.1",
        "numba>=0.60",
        "safetensors>=0.4",
        "matplotlib>=3.8",
        "tqdm>=4.66",
        "rosbags>=0.10",
        "mcap>=1.2",
        "PyYAML>=6",
        "zstandard>=0.21",
        # the per-message serving backend (step.onnx beside the card, no torch) and its export at `train`
        "onnxruntime>=1.20",
        "onnx>=1.16",
    ],
    extras_require={
        # the nodes: from the ROS 2 install on a ROS machine, or these wheels in a plain venv
        # (tf2_msgs, launch and launch_ros have no wheel: publish_tf and `ros2 launch` need a ROS install)
        "ros": [
            "ros-jazzy-rclpy[fastrtps]",
            "ros-jazzy-common-interfaces",
            "ros-jazzy-diagnostic-msgs",
            "ros-jazzy-std-srvs",
            "ros-jazzy-nav-msgs",
            "ros-jazzy-rosgraph-msgs",
            "ros-jazzy-lifecycle-msgs",
            "ros-jazzy-ament-index-python",
        ],
        "reproduce": ["ray==2.60.0"],
        "reference": ["filterpy>=2.0.0", "dapper==1.7.1"],  # the filters' independent references
        "docs": ["mkdocs>=1.6", "mkdocs-material>=9.5"],
        "test": [
            "pytest>=8",
            "pytest-xdist>=3.6",
            "atheris==3.0.0",
            "ruff==0.14.14",
            "filterpy>=2.0.0",
            "dapper==1.7.1",
            "mcap-ros2-support>=0.5",
            "ray==2.60.0",
            "mkdocs>=1.6",
            "mkdocs-material>=9.5",
        ],
    },
    zip_safe=False,
    maintainer="neural_estimator maintainers",
    maintainer_email="maintainers@neural-estimator.dev",
    description="Model-free neural state estimators beside model-based nonlinear filters, on ROS 2.",
    license="Apache-2.0",
    python_requires=">=3.10",
    entry_points={
        "console_scripts": ["neural-estimator = neural_estimator.cli:main", *([] if _WHEEL else _NODES)],
    },
)
