"""The classical filters' compiled (numba) kernels, and the lookup that gives a scenario its own.

One module per scenario holds the kernels of its f and h (:mod:`.lorenz96`, :mod:`.nlink`,
:mod:`.ballistic`, :mod:`.bearings`, :mod:`.quadrotor`); :mod:`.rng` the random numbers (the PF's
keyed generators, numpy's SFC64 normals for the EnKF); :mod:`.pf` the particle filter's pieces that
know no scenario (linear likelihood, weight normalisation, resampling, weighted moments);
:mod:`.ekf` and :mod:`.enkf` the compiled EKF and EnKF steps; :mod:`.trig` the kernels' angle
wrap, sine and cosine; :mod:`.model` the :class:`CompiledModel` record.

The scenario's kernels (each module's ``bind(scenario) -> CompiledModel``, its constants bound),
done per particle in the same order of operations as the scenario's numpy code (RK4 stages, the
N-link L D L^T solve, the tan half-angle trigonometry), so they agree with it to rounding (tested
against ``scenario.f`` / ``scenario.h``), and release the GIL so the filter's worker threads run
them side by side:

    scenario     predict (f + noise)           log-likelihood of h               EKF / EnKF step
    lorenz96     RK4 ring                       linear (pf.linear_log_likelihood)  ekf, enkf
    nlink        RK4 of Euler-Lagrange, wrap    masses' positions                  -
    ballistic    RK4 of the drag dynamics       range                              -
    bearings     constant velocity              bearing (wrapped innovation)       -
    quadrotor    Euler step of the PVTOL body   linear (pf.linear_log_likelihood)  -

Which scenario has which kernels is the table :data:`KERNELS`, keyed by the scenario's class (its
dotted path): the exact class only, since a subclass may redefine f or h. A scenario without an
entry (a plugin, a toy, a subclass) gets an empty :class:`CompiledModel`, and the filters their
numpy paths (the PF still draws its noise and weighs linear observations with the compiled kernels
of :mod:`.rng` and :mod:`.pf`). A plugin with kernels of its own adds its entry
(``KERNELS["my_package.my_module.MyScenario"] = "my_package.my_kernels"``, a module with a
``bind(scenario)``); the filters never test the scenario's type.
"""

from __future__ import annotations

import importlib

from neural_estimator.filters.kernels.model import CompiledModel

_HERE = __name__

# {scenario class's dotted path: the module of its kernels}
KERNELS: dict[str, str] = {
    "neural_estimator.scenarios.ballistic.Ballistic": f"{_HERE}.ballistic",
    "neural_estimator.scenarios.bearings.Bearings": f"{_HERE}.bearings",
    "neural_estimator.scenarios.lorenz96.Lorenz96": f"{_HERE}.lorenz96",
    "neural_estimator.scenarios.nlink.NLinkPendulum": f"{_HERE}.nlink",
    "neural_estimator.scenarios.quadrotor.PlanarQuadrotor": f"{_HERE}.quadrotor",
}


def scenario_key(scenario) -> str:
    """The key of ``scenario`` in :data:`KERNELS`: its class's dotted path (module and qualified name)."""
    cls = type(scenario)
    return f"{cls.__module__}.{cls.__qualname__}"


def compiled_model(scenario) -> CompiledModel:
    """The compiled kernels of ``scenario``, its constants bound; empty where :data:`KERNELS` has no
    entry for its class."""
    module = KERNELS.get(scenario_key(scenario))
    if module is None:
        return CompiledModel()
    return importlib.import_module(module).bind(scenario)


__all__ = ["KERNELS", "CompiledModel", "compiled_model", "scenario_key"]
