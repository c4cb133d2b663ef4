"""A bag played into one estimator per method, recorded and scored by the evaluator.

    ros2 launch neural_estimator replay.launch.py bag:=bags/bearings.mcap methods:=ekf,ukf,mamba rate:=20.0
    ros2 launch neural_estimator replay.launch.py --show-args

Arguments and nodes: ``GRAPHS["replay"]`` of :mod:`neural_estimator.nodes.graph`, the description
``neural-estimator live`` and the pip environment's ``ros2 launch`` start too.
"""

from neural_estimator.nodes.graph import launch_description


def generate_launch_description():
    return launch_description("replay")
