"""One estimator node with its params file (as robot_localization's ekf.launch.py).

    ros2 launch neural_estimator estimator.launch.py params_file:=my_estimator.yaml method:=ukf
    ros2 launch neural_estimator estimator.launch.py --show-args

Arguments and nodes: ``GRAPHS["estimator"]`` of :mod:`neural_estimator.nodes.graph`, the description
``neural-estimator live`` and the pip environment's ``ros2 launch`` start too.
"""

from neural_estimator.nodes.graph import launch_description


def generate_launch_description():
    return launch_description("estimator")
