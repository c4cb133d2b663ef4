"""The live comparison: simulator, one estimator per method, evaluator.

    ros2 launch neural_estimator live.launch.py scenario:=bearings methods:=ekf,ukf,gru rate_hz:=50.0
    ros2 launch neural_estimator live.launch.py --show-args

Arguments and nodes: ``GRAPHS["live"]`` of :mod:`neural_estimator.nodes.graph`, the description
``neural-estimator live`` and the pip environment's ``ros2 launch`` start too.
"""

from neural_estimator.nodes.graph import launch_description


def generate_launch_description():
    return launch_description("live")
