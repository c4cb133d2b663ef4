"""The replay graph (neural_estimator.nodes.graph.GRAPHS["replay"]: arguments and nodes).

    ros2 launch neural_estimator replay.launch.py bag:=bags/bearings.mcap methods:=ekf,ukf,mamba rate:=2.0
    ros2 launch neural_estimator replay.launch.py --show-args
"""

from neural_estimator.nodes.graph import launch_description


def generate_launch_description():
    return launch_description("replay")
