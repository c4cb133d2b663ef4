"""How the classical filters start in the offline protocol (``init``): the three modes, their check,
and the start a method really gets on a scenario."""

from __future__ import annotations

from neural_estimator.methods import table
from neural_estimator.scenarios import Scenario

INIT_MODES = ("prior", "truth", "observation")
"""How the classical filters start in the offline protocol (``init``):

- ``"prior"`` (default; the live node's only choice, it never knows the truth): every filter
  starts from the scenario prior, mean m0 and covariance P0; the PF's particles are
  N(m0, init_std^2 I) (paper: x_0 std = 1.0).
- ``"truth"``: each trajectory's filters start at its true initial state x_0 (the mean only:
  covariance P0 and the PF's init_std spread unchanged), i.e. the PF's particles are
  N(x_0, init_std^2 I). This is the reading of the paper's "x_0 std = 1.0" under which a PF with a
  fixed unit spread can lock on in every scenario (see docs/fidelity.md).
- ``"observation"``: the start the live pipeline offers a practitioner (the filters' ``init``
  option, :data:`neural_estimator.filters.base.FILTER_INITS`): at step 0 each stream's mean is
  the state its first observation determines where h is invertible on the observed components
  (Lorenz 96: x = y_0), the prior mean elsewhere; P0 and init_std unchanged. Needs no truth, so
  the live node, replay and ``neural-estimator live`` use it too.

Neural methods read observations only; the option does not concern them.
"""


def effective_init(scenario: Scenario, method: str, init: str) -> str:
    """The start ``method`` really gets on ``scenario`` under the protocol's ``init``: ``"observation"``
    is the prior where one observation determines no state component (bearings, ballistic, quadrotor:
    the same computation, so the same cached result), and neural methods always read ``"prior"``."""
    check_init(init)
    if not table.has(method, takes_init=True):
        return "prior"
    if init == "observation":
        from neural_estimator.filters.base import observation_determines_state

        return init if observation_determines_state(scenario) else "prior"
    return init


def check_init(init: str) -> str:
    """``init`` if it is one of :data:`INIT_MODES`, else a one-line ValueError naming the choices."""
    if init not in INIT_MODES:
        raise ValueError(f"init must be one of {', '.join(INIT_MODES)}; got {init!r}")
    return init
