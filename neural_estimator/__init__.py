"""neural_estimator: model-free neural state estimators beside model-based nonlinear filters.

Reproduces and extends Liu, Walker & Jain, "Model-Free Neural Filtering: A Comparison with
Classical Filters in Nonlinear Systems".

Layers, bottom first. A module imports only from its own layer or those below it, at module level
or inside a function alike, and module-level imports form no cycle (``test/test_layers.py`` walks
every import of the package against this list):

1. ``angles``, ``atomic``, ``safe_yaml``, ``options``, ``interfaces``, ``runtime``, ``metrics``, ``consistency``,
   ``plots``, ``expected_failures``, ``paper``
2. ``scenarios``: the five nonlinear systems (numpy; their f and h in torch on request, imported lazily)
3. ``data``: simulation, the paper's protocol of data sets, the dataset files
4. ``estimator``: the interface of the ten methods (``Estimator``, ``Estimates``, errors, method names)
5. ``filters`` (EKF, UKF, EnKF, PF), ``models`` (the six architectures: GRU, LSTM, GPT-2, Filterformer,
   Mamba, Mamba-2), ``baselines`` (the open-loop and observation-only reference rows)
6. ``serving``: a trained model as an estimator (checkpoint, card, normalisation, context, the zoo);
   ``uncertainty``: covariance heads on the served models' trunks, their fit and calibration
7. ``registry``: every method by name (``make_estimator``)
8. ``training``, ``bags``, ``evaluation``, ``online``, ``replay``, ``robot``, ``departures``: the
   training run, MCAP I/O, the evaluation protocol, the per-message estimator, bag replay, recorded
   robot data, the marks of departures from the paper's protocol
9. ``reproduce``: the paper's experiments on Ray
10. front ends: ``cli``, ``nodes``, ``ros2_shim``; only the nodes import rclpy
"""

__version__ = "0.1.0"
