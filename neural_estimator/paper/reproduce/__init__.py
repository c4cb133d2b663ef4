"""``neural-estimator reproduce``: the paper's experiments as independent jobs on Ray, and a report.

Modules, one job each:

* :mod:`.scales` -- the sizes of the ``smoke``, ``small`` and ``paper`` scales;
* :mod:`.jobs` -- one job (evaluate one method on one evaluation set; time one method's step),
  its cache key, and the code a Ray task runs;
* :mod:`.engine` -- runs the jobs as Ray tasks with one progress bar, reusing cached results and
  reporting failed jobs while the others go on;
* :mod:`.report` -- tables beside the paper's numbers (:mod:`neural_estimator.paper`), PNG figures
  and the markdown report;
* :mod:`.mismatch` -- the model-mismatch experiment beyond the paper (one job per sweep, its cache,
  its report section).
"""

from neural_estimator.paper.reproduce.scales import SCALES, Scale, get_scale

__all__ = ["SCALES", "Scale", "get_scale"]
