"""A team's own robot: recorded bags -> datasets -> neural estimators, with no simulator and no equations.

- :mod:`~neural_estimator.robot.spec`: the YAML spec naming the observation, control and state
  vectors as fields of standard messages on topics, the rate and the alignment.
- :mod:`~neural_estimator.robot.dataset`: bags (any tool's ``.mcap`` or rosbag2 directory) ->
  the project's dataset format, reporting what was dropped.
- :mod:`~neural_estimator.robot.data_scenario`: the data's interface (names, units, angles, rate) as
  a scenario without a model, so training, evaluation and the checkpoint checks apply unchanged; or
  with the model a spec names (``model:``), whose equations it delegates to (filters, a hybrid).
"""

from neural_estimator.robot.data_scenario import DATA_SCENARIO, DataScenario
from neural_estimator.robot.dataset import BagSummary, build_dataset
from neural_estimator.robot.spec import Spec, SpecError, load_spec

__all__ = ["BagSummary", "DATA_SCENARIO", "DataScenario", "Spec", "SpecError", "build_dataset", "load_spec"]
