"""neural_estimator: model-free neural state estimators beside model-based nonlinear filters.

Reproduces and extends Liu, Walker & Jain, "Model-Free Neural Filtering: A Comparison with
Classical Filters in Nonlinear Systems". Layers (imports point downwards only):

1. ``scenarios``: the five nonlinear systems (pure numpy).
2. ``data``, ``metrics``, ``bags``: simulation and datasets, the paper's metrics, MCAP I/O.
3. ``filters`` (EKF, UKF, EnKF, PF) and ``models`` (GRU, LSTM, GPT-2, Filterformer, Mamba, Mamba-2).
4. ``estimators``: one interface and a registry over all ten methods.
5. Front ends: ``cli`` and the ROS 2 nodes (``nodes``, ``sim_nodes``); only the nodes import rclpy.
"""

__version__ = "0.1.0"
