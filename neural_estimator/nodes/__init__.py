"""The ROS 2 nodes (simulator, estimator, evaluator, player) and the process launcher.

Only modules of this package import rclpy. Importing the package itself does not:
:mod:`neural_estimator.nodes.launch` starts the nodes as processes and runs without rclpy.
"""
