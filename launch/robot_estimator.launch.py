"""The robot estimator on its spec's topics, or on a bag played on /clock (+ evaluator).

    ros2 launch neural_estimator robot_estimator.launch.py checkpoint:=runs/robot-gru
    ros2 launch neural_estimator robot_estimator.launch.py checkpoint:=runs/robot-gru bag:=runs/robot_bag \\
        rate:=4.0 spec:=examples/robot_spec.yaml
    ros2 launch neural_estimator robot_estimator.launch.py --show-args

Arguments and nodes: ``GRAPHS["robot_estimator"]`` of :mod:`neural_estimator.nodes.graph`, the description
``neural-estimator live`` and the pip environment's ``ros2 launch`` start too.
"""

from neural_estimator.nodes.graph import launch_description


def generate_launch_description():
    return launch_description("robot_estimator")
