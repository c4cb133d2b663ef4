"""neural_estimator: model-free neural state estimators beside model-based nonlinear filters.

Reproduces and extends Liu, Walker & Jain, "Model-Free Neural Filtering: A Comparison with
Classical Filters in Nonlinear Systems".

Layers, bottom first. A module imports only from its own layer or those below it, at module level
or inside a function alike, and module-level imports form no cycle (``test/test_layers.py`` walks
every import of the package against this list):

1. ``angles``, ``options``, ``interfaces``, ``runtime``, ``metrics``, ``consistency``, ``plots``,
   ``expected_failures``, ``paper``
2. ``scenarios``: the five nonlinear systems (pure numpy)
3. ``data``: simulation, the paper's protocol of data sets, the dataset files
4. ``estimator``: the interface of the ten methods (``Estimator``, ``Estimates``, errors, method names)
5. ``filters`` (EKF, UKF, EnKF, PF), ``models`` (GRU, LSTM, GPT-2, Filterformer, Mamba, Mamba-2), ``uncertainty``
6. ``estimators``: the registry (``make_estimator``)
7. ``bags``, ``evaluation``, ``replay``, ``robot``, ``departures``: MCAP I/O, the evaluation protocol, bag
   replay, recorded robot data, the marks of departures from the paper's protocol
8. ``reproduce``: the paper's experiments on Ray
9. front ends: ``cli``, ``nodes``, ``ros2_shim``; only the nodes import rclpy
"""

__version__ = "0.1.0"
