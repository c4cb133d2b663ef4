"""The robot estimator graph (neural_estimator.nodes.graph.GRAPHS["robot_estimator"]).

    ros2 launch neural_estimator robot_estimator.launch.py checkpoint:=runs/robot-gru
    ros2 launch neural_estimator robot_estimator.launch.py checkpoint:=runs/robot-gru bag:=runs/robot_bag
        rate:=4.0 spec:=examples/robot_spec.yaml    # replayed on /clock, recorded and scored
    ros2 launch neural_estimator robot_estimator.launch.py --show-args
"""

from neural_estimator.nodes.graph import launch_description


def generate_launch_description():
    return launch_description("robot_estimator")
