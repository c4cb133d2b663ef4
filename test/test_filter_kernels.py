"""The filters' compiled kernels follow the scenario through a lookup (filters/kernels/__init__.py),
never through a test of the scenario's type; a scenario without kernels gets the numpy paths."""

from __future__ import annotations

import ast
import importlib
import pkgutil
from pathlib import Path

import numpy as np
import pytest

import neural_estimator.filters as filters_package
from neural_estimator.filters import kernels
from neural_estimator.filters.kernels import KERNELS, CompiledModel, compiled_model, scenario_key
from neural_estimator.scenarios import BUILTIN_SCENARIOS, Scenario, make_scenario

FILTERS = Path(filters_package.__file__).parent


def scenario_classes() -> set[str]:
    """The names of every concrete scenario class the package defines (the built-ins' classes and
    any other Scenario subclass in neural_estimator.scenarios' modules)."""
    names = {type(make_scenario(name)).__name__ for name in BUILTIN_SCENARIOS}
    import neural_estimator.scenarios as scenarios

    for info in pkgutil.iter_modules(scenarios.__path__):
        module = importlib.import_module(f"{scenarios.__name__}.{info.name}")
        for value in vars(module).values():
            if isinstance(value, type) and issubclass(value, Scenario) and value is not Scenario:
                names.add(value.__name__)
    return names


def scenario_type_tests(source: str, classes: set[str]) -> list[str]:
    """Where ``source`` tests a scenario's type: a concrete scenario class named in the code (an
    ``isinstance``/``issubclass`` argument, an ``is``/``==``/``in`` operand, a ``match`` pattern),
    a ``type(...)`` compared with ``is``/``==``/``in``, or an import of a concrete scenario's module."""
    found = []
    for node in ast.walk(ast.parse(source)):
        line = getattr(node, "lineno", 0)
        if isinstance(node, ast.Name) and node.id in classes:
            found.append(f"line {line}: the scenario class {node.id}")
        elif isinstance(node, ast.Attribute) and node.attr in classes:
            found.append(f"line {line}: the scenario class {node.attr}")
        elif isinstance(node, ast.alias) and node.name in classes:
            found.append(f"line {line}: imports the scenario class {node.name}")
        elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith("neural_estimator.scenarios."):
            if node.module.rsplit(".", 1)[1] not in {"base", "_integrate"}:
                found.append(f"line {line}: imports {node.module}")
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("neural_estimator.scenarios.") and a.name.rsplit(".", 1)[1] != "base":
                    found.append(f"line {line}: imports {a.name}")
        elif isinstance(node, ast.Compare):
            typed = [
                o
                for o in [node.left, *node.comparators]
                if isinstance(o, ast.Call) and isinstance(o.func, ast.Name) and o.func.id == "type"
            ]
            kinds = (ast.Is, ast.IsNot, ast.Eq, ast.NotEq, ast.In, ast.NotIn)
            if typed and any(isinstance(op, kinds) for op in node.ops):
                found.append(f"line {line}: compares type(...)")
    return found


def test_no_scenario_type_test_in_the_filters():
    classes = scenario_classes()
    assert {"Lorenz96", "NLinkPendulum", "Ballistic", "Bearings", "PlanarQuadrotor"} <= classes
    found = {}
    for path in sorted(FILTERS.rglob("*.py")):
        hits = scenario_type_tests(path.read_text(), classes)
        if hits:
            found[str(path.relative_to(FILTERS.parent))] = hits
    assert not found, f"filters/ tests the scenario's type (use the kernels' lookup): {found}"


@pytest.mark.parametrize(
    "source",
    [
        "from neural_estimator.scenarios.lorenz96 import Lorenz96\n",
        "import neural_estimator.scenarios.nlink\n",
        "def f(s):\n    return type(s) is not Lorenz96\n",
        "def f(s, m):\n    return isinstance(s, m.NLinkPendulum)\n",
        "def f(s, C):\n    return type(s) == C\n",
        "def f(s):\n    return s.__class__ in (Ballistic, Bearings)\n",
        "def f(s):\n    match s:\n        case PlanarQuadrotor():\n            return 1\n",
    ],
)
def test_the_type_test_finder_finds_them(source):
    """The check above is not vacuous: each way of testing a scenario's type is caught."""
    assert scenario_type_tests(source, scenario_classes())


def test_the_type_test_finder_leaves_method_override_checks_alone():
    """What filters/ does legitimately: ask whether a scenario overrides a base-class method."""
    source = "def f(s, Scenario):\n    cls = type(s)\n    return cls.state_mean is Scenario.state_mean\n"
    assert scenario_type_tests(source, scenario_classes()) == []


@pytest.mark.parametrize("name", BUILTIN_SCENARIOS)
def test_every_built_in_scenario_has_its_kernels(name):
    """The lookup's keys follow the scenario classes: a renamed or moved class would silently lose
    its kernels (the numpy path: right, but slow) without this."""
    s = make_scenario(name)
    assert KERNELS[scenario_key(s)] == f"{kernels.__name__}.{name}"
    model = compiled_model(s)
    assert model.predict is not None
    # the compiled EKF and EnKF hold Lorenz 96's field: only it may hand them its constants
    assert (model.ekf_model is not None) == (model.enkf_model is not None) == (name == "lorenz96")


def test_every_entry_of_the_lookup_names_a_scenario_class_and_a_kernel_module():
    for key, module in KERNELS.items():
        mod, cls = key.rsplit(".", 1)
        assert issubclass(getattr(importlib.import_module(mod), cls), Scenario), key
        assert callable(importlib.import_module(module).bind), module


def _subclass(name: str) -> Scenario:
    base = type(make_scenario(name))
    sub = type(f"My{base.__name__}", (base,), {})  # may redefine f or h: gets no kernels
    return sub(base.Config()) if hasattr(base, "Config") else sub(make_scenario(name).config)


@pytest.mark.parametrize("name", ["lorenz96", "bearings"])
def test_a_scenario_without_kernels_gets_the_numpy_paths(name):
    from neural_estimator.filters import EnsembleKalmanFilter, ExtendedKalmanFilter, ParticleFilter

    s = _subclass(name)
    assert compiled_model(s) == CompiledModel()
    ekf, enkf, pf = ExtendedKalmanFilter(s), EnsembleKalmanFilter(s, n_members=8), ParticleFilter(s, n_particles=8)
    for f in (ekf, enkf, pf):
        f.reset(2)
    assert ekf._compiled is None and enkf._compiled is None
    assert enkf._transition == s.f and pf._ck_predict is None and pf._ck_loglik is None


def test_the_lookup_not_the_type_picks_the_kernels(monkeypatch):
    """A scenario class given an entry (as a plugin would) gets that module's kernels."""
    s = _subclass("bearings")
    monkeypatch.setitem(KERNELS, scenario_key(s), f"{kernels.__name__}.bearings")
    model = compiled_model(s)
    assert model.predict is not None and model.log_likelihood is not None
    X = np.zeros((1, 3, 4))
    X[..., :2] = [1.0, 1.0]
    logw = np.zeros((1, 3))
    model.log_likelihood(X, np.array([[np.pi / 4]]), np.ones(1), logw)
    np.testing.assert_allclose(logw, 0.0, atol=1e-24)


def test_the_numba_cache_files_do_not_collide():
    """Every cached kernel of filters/ has its own cache index (numba names it after the module's
    file stem and the function's qualified name, in a folder per source folder)."""
    from numba.core.registry import CPUDispatcher

    paths = {}
    modules = [f"{kernels.__name__}.{m.name}" for m in pkgutil.iter_modules(kernels.__path__)]
    modules += [f"{filters_package.__name__}.{m.name}" for m in pkgutil.iter_modules(filters_package.__path__)]
    for name in modules:
        for attr, value in vars(importlib.import_module(name)).items():
            cache = getattr(value, "_cache", None) if isinstance(value, CPUDispatcher) else None
            if cache is None or type(cache).__name__ != "FunctionCache" or value.__module__ != name:
                continue
            index = cache._cache_file._index_path
            assert index not in paths, f"{name}.{attr} and {paths[index]} share {index}"
            paths[index] = f"{name}.{attr}"
    assert len(paths) >= 25, sorted(paths.values())
