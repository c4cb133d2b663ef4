"""The estimator graph (neural_estimator.nodes.graph.GRAPHS["estimator"]: arguments and nodes).

    ros2 launch neural_estimator estimator.launch.py params_file:=my_estimator.yaml method:=ukf scenario:=bearings
    ros2 launch neural_estimator estimator.launch.py --show-args
"""

from neural_estimator.nodes.graph import launch_description


def generate_launch_description():
    return launch_description("estimator")
