"""A toy method for test_toy_method.py, all its definitions in this one file: the estimate is the
prior mean at every step (a "mean of the prior"), a classical method with no start modes.

Registering it is one more :class:`~neural_estimator.methods.table.MethodSpec`; the tests put it in
a temporary table (``monkeypatch``), so nothing of it is left behind.
"""

from __future__ import annotations

import numpy as np

from neural_estimator.methods.interface import Estimator
from neural_estimator.methods.table import MethodSpec

NAME = "toymean"


class MeanOfPrior(Estimator):
    """x_hat_k = m0 for every k: the prior mean, whatever is observed."""

    method = NAME

    def __init__(self, scenario, seed: int = 0) -> None:
        super().__init__(scenario)
        self.seed = seed

    def reset(self, batch: int = 1) -> None:
        self.batch = int(batch)
        self._m0 = np.asarray(self.scenario.prior()[0], dtype=np.float64)
        self.diverged = np.zeros(self.batch, dtype=bool)
        self.skipped = np.zeros(self.batch, dtype=bool)

    def step(self, y, u_prev=None) -> np.ndarray:
        y, u_prev = self.check_step(y, u_prev)
        self.start_streams_if_none(y.shape[0])
        return np.broadcast_to(self._m0, (self.batch, self.scenario.dx)).copy()


SPEC = MethodSpec(
    NAME,
    "Toy mean",
    "classical",
    f"{__name__}:MeanOfPrior",
    needs_model=True,
    trainable=False,
    takes_init=False,
    uses_torch=False,
    seeded=False,
)
