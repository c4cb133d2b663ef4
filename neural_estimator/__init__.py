"""neural_estimator: model-free neural state estimators beside model-based nonlinear filters.

Reproduces and extends Liu, Walker & Jain, "Model-Free Neural Filtering: A Comparison with
Classical Filters in Nonlinear Systems".

Layers, bottom first. A module imports only from its own layer or those below it, at module level
or inside a function alike, and module-level imports form no cycle (``test/test_layers.py`` walks
every import of the package against this list):

1. ``core`` (angle arithmetic, files written whole or not at all, bounded YAML, the grammar of option
   values, ROS interface checks, the allocator), ``metrics`` (the paper's metrics, the covariances'
   consistency, figures), ``paper`` (the published numbers, the paper's five scenarios, the expected
   failures)
2. ``scenarios``: the five nonlinear systems (numpy; their f and h in torch on request, imported lazily)
3. ``data``: simulation, the paper's protocol of data sets, the dataset files
4. ``methods``: the table of methods (a ``MethodSpec`` each), the interface of the methods
   (``Estimator``, ``Estimates``, errors) and the registry (``make_estimator()``)
5. ``filters`` (EKF, UKF, EnKF, PF, and the open-loop and observation-only reference rows), ``models``
   (the six architectures: GRU, LSTM, GPT-2, Filterformer, Mamba, Mamba-2)
6. ``serving``: a trained model as an estimator (checkpoint, card, normalisation, context, the zoo;
   ``serving.uncertainty``: covariance heads on the served models' trunks, their fit and calibration)
7. ``stream``: the live message format and the per-message estimator (no ROS)
8. ``training``, ``bags``, ``evaluation``, ``robot``, ``paper.departures``: the training run, bag
   storage (MCAP, rosbag2 directories), the evaluation protocol with bag scoring and replay, recorded
   robot data, the marks of departures from the paper's protocol
9. ``paper.reproduce``: the paper's experiments on Ray
10. front ends: ``cli`` (with the minimal ros2 of pip environments), ``nodes``; only nodes import rclpy

The table of methods (``methods.table``) sits below the filters, models and serving that build the
methods: each spec names its factory as ``"module:attribute"`` text, resolved with importlib when the
method is built (``methods.registry.make_estimator``), as Python entry points are, so no import runs
upwards.
"""

__version__ = "0.1.0"
