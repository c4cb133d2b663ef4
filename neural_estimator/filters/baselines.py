"""Reference estimators that use no filtering: what a team gets without a filter or a network.

They score a benchmark's rows from below: a method that does not beat them on a state component
does not estimate that component. They are evaluated like the ten methods (``evaluate --methods
openloop,obsonly``) and printed as reference rows, never ranked among the ten.

- ``openloop``: the prior mean propagated by the noise-free model with the known controls and no
  observation, x_hat_0 = m0, x_hat_{k+1} = f(x_hat_k, u_k) (what a model without sensors gives).
- ``obsonly``: the components one observation determines, read from that step's observation
  alone (h's inverse, :meth:`~neural_estimator.scenarios.base.Scenario.state_from_observation`),
  the open-loop estimate elsewhere and at any step whose observation is not finite. Only where h
  is invertible on some components (Lorenz 96: x = y; N-link: the angles from the mass positions);
  elsewhere refused with a one-line error.
"""

from __future__ import annotations

import numpy as np

from neural_estimator.methods import table
from neural_estimator.methods.interface import Estimator, EstimatorError, check_method
from neural_estimator.scenarios import Scenario


class OpenLoop(Estimator):
    """x_hat_0 = m0, x_hat_k = f(x_hat_{k-1}, u_{k-1}): the prior mean under the noise-free model."""

    method = "openloop"

    def reset(self, batch: int = 1) -> None:
        m0 = np.asarray(self.scenario.prior()[0], dtype=np.float64)
        self.batch = int(batch)
        self._x = np.broadcast_to(m0, (self.batch, self.scenario.dx)).copy()
        self._k = 0
        self.diverged = np.zeros(self.batch, dtype=bool)
        self.skipped = np.zeros(self.batch, dtype=bool)

    def step(self, y: np.ndarray, u_prev: np.ndarray | None = None) -> np.ndarray:
        y, u_prev = self.check_step(y, u_prev)
        self.start_streams_if_none(y.shape[0])
        if self._k > 0:  # step 0 is the prior mean; later steps predict with u_{k-1}
            with np.errstate(all="ignore"):
                self._x = self.scenario.normalize_state(self.scenario.f(self._x, u_prev))
        self._k += 1
        self.diverged |= ~np.isfinite(self._x).all(axis=1)
        self.skipped = np.ones(self.batch, dtype=bool)  # no observation is ever used
        return self._x.copy()


class ObservationOnly(OpenLoop):
    """h's inverse on the components one observation determines, the open loop elsewhere."""

    method = "obsonly"

    def __init__(self, scenario: Scenario) -> None:
        super().__init__(scenario)
        m0 = np.asarray(scenario.prior()[0], dtype=np.float64)
        with np.errstate(all="ignore"):
            inverse = scenario.state_from_observation(scenario.h(m0[None]))
        if inverse is None:
            raise EstimatorError(f"obsonly: {scenario.name}'s observation determines no state component; use openloop")
        self.observed = np.asarray(inverse[1], dtype=bool)  # (dx,)

    def step(self, y: np.ndarray, u_prev: np.ndarray | None = None) -> np.ndarray:
        x = super().step(y, u_prev)
        y = np.asarray(y, dtype=np.float64).reshape(x.shape[0], -1)
        finite = np.isfinite(y).all(axis=1)
        if finite.any():
            with np.errstate(all="ignore"):
                inv, _ = self.scenario.state_from_observation(y[finite])
            x[np.ix_(finite, self.observed)] = inv[:, self.observed]
        self.skipped = ~finite
        return self.scenario.normalize_state(x)


def is_baseline(method: str) -> bool:
    """``method`` is a reference row of the table of methods (family ``baseline``)."""
    return table.has(method, family="baseline")


def check_evaluated_method(method: str) -> str:
    """``method`` if it is one of the ten or a baseline, else the registry's one-line error."""
    name = str(method).strip().lower()
    if is_baseline(name):
        return name
    return check_method(method)


def make_baseline(method: str, scenario: Scenario, **options) -> OpenLoop:
    """Build a baseline by name; baselines take no options (a one-line EstimatorError otherwise)."""
    if options:
        raise EstimatorError(f"{method}: a baseline takes no options, got {', '.join(sorted(options))}")
    if not is_baseline(method):
        raise EstimatorError(f"unknown baseline {method!r}; baselines: {', '.join(table.names(family='baseline'))}")
    return table.resolve(table.spec(method).factory)(scenario)
