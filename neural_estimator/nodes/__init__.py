"""The ROS 2 nodes (estimator, evaluator, player) and the process launcher.

Only modules of this package (and ``sim_nodes``) import rclpy. Importing the package itself does
not: :mod:`neural_estimator.nodes.launch` starts the nodes as processes and runs without rclpy.
"""
