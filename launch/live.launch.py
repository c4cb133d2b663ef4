"""The live graph (neural_estimator.nodes.graph.GRAPHS["live"]: arguments and nodes).

    ros2 launch neural_estimator live.launch.py scenario:=bearings methods:=ekf,ukf,gru rate_hz:=50.0 output:=runs/b.mcap
    ros2 launch neural_estimator live.launch.py --show-args
"""

from neural_estimator.nodes.graph import launch_description


def generate_launch_description():
    return launch_description("live")
