"""The live stream, without ROS: the message format of observations, estimates and ground truth
(:mod:`~neural_estimator.stream.messages`) and the per-message estimator that turns one observation
message into one estimate message (:mod:`~neural_estimator.stream.online`). The nodes, bag replay and
the bags' storage all use this one format."""
