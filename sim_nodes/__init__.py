"""Simulator nodes of neural_estimator (they import rclpy; the simulation itself is neural_estimator.data)."""
