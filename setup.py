"""ament_python package; also installs with pip (``pip install -e .``) and exposes ``neural-estimator``."""

from glob import glob

from setuptools import find_packages, setup

package_name = "neural_estimator"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(include=["neural_estimator", "neural_estimator.*", "sim_nodes", "sim_nodes.*"]),
    package_data={
        "neural_estimator": ["zoo/*/*.safetensors", "zoo/*/*.json", "paper/paper_results.json", "nodes/*.xml"]
    },
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{package_name}"]),
        (f"share/{package_name}", ["package.xml"]),
        (f"share/{package_name}/params", glob("params/*.yaml")),
        (f"share/{package_name}/bags", glob("bags/*.mcap")),
    ],
    # What `pip install .` needs for every verb but `reproduce` and the nodes. The README's install
    # (scripts/requirements.txt) pins torch to the CPU build on disk; here a range, so that an
    # existing torch (CPU or CUDA) is kept. test/test_package.py checks every import is declared.
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
    ],
    extras_require={
        # the nodes: from the ROS 2 install on a ROS machine, or these wheels in a plain venv
        "ros": ["ros-jazzy-rclpy[fastrtps]", "ros-jazzy-common-interfaces", "ros-jazzy-diagnostic-msgs",
                "ros-jazzy-std-srvs"],
        "reproduce": ["ray==2.60.0"],
        "reference": ["filterpy>=1.4.5", "dapper==1.7.1"],  # the filters' independent references
        "test": ["pytest>=8", "atheris==3.0.0", "ruff==0.14.14", "filterpy>=1.4.5", "dapper==1.7.1"],
    },
    zip_safe=False,
    maintainer="neural_estimator maintainers",
    maintainer_email="maintainers@neural-estimator.dev",
    description="Model-free neural state estimators beside model-based nonlinear filters, on ROS 2.",
    license="Apache-2.0",
    python_requires=">=3.10",
    entry_points={
        "console_scripts": [
            "neural-estimator = neural_estimator.cli:main",
            # the minimal `ros2 run` for pip environments; hands over to a real ros2 when installed
            "ros2 = neural_estimator.ros2_shim:main",
            # ROS 2 nodes (`ros2 run neural_estimator <name>`)
            "simulator = sim_nodes.simulator:main",
            "estimator = neural_estimator.nodes.estimator_node:main",
            "evaluator = neural_estimator.nodes.evaluator_node:main",
            "player = neural_estimator.nodes.player_node:main",
            "robot_estimator = neural_estimator.nodes.robot_estimator_node:main",
        ],
    },
)
