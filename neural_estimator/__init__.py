"""neural_estimator: model-free neural state estimators beside model-based nonlinear filters.

Reproduces and extends Liu, Walker & Jain, "Model-Free Neural Filtering: A Comparison with
Classical Filters in Nonlinear Systems".

Layers, bottom first. A module imports only from its own layer or those below it, at module level
or inside a function alike, and module-level imports form no cycle (``test/test_layers.py`` walks
every import of the package against this list):

1. ``core`` (angle arithmetic, files written whole or not at all, bounded YAML, the grammar of option
   values, ROS interface checks, the allocator), ``metrics`` (the paper's metrics, the covariances'
   consistency, figures), ``expected_failures``, ``paper``
2. ``scenarios``: the five nonlinear systems (pure numpy)
3. ``data``: simulation, the paper's protocol of data sets, the dataset files
4. ``estimator``: the interface of the ten methods (``Estimator``, ``Estimates``, errors, method names)
5. ``filters`` (EKF, UKF, EnKF, PF), ``models`` (the six architectures: GRU, LSTM, GPT-2, Filterformer,
   Mamba, Mamba-2), ``baselines`` (the open-loop and observation-only reference rows)
6. ``serving``: a trained model as an estimator (checkpoint, card, normalisation, context, the zoo;
   ``serving.uncertainty``: covariance heads on the served models' trunks, their fit and calibration)
7. ``registry``: every method by name (``make_estimator()``); ``stream``: the live message format and
   the per-message estimator (no ROS)
8. ``training``, ``bags``, ``evaluation``, ``robot``, ``departures``: the training run, bag storage
   (MCAP, rosbag2 directories), the evaluation protocol with bag scoring and replay, recorded robot
   data, the marks of departures from the paper's protocol
9. ``reproduce``: the paper's experiments on Ray
10. front ends: ``cli`` (with the minimal ros2 of pip environments), ``nodes``; only nodes import rclpy
"""

__version__ = "0.1.0"
