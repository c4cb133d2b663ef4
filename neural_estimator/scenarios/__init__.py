"""The five systems of the paper and a registry for user-defined ones.

>>> from neural_estimator.scenarios import make_scenario
>>> s = make_scenario("lorenz96", obs_noise_std=0.5)

A user registers a system of their own with :func:`register_scenario` (see docs/scenarios.md, "Your own
scenario" section); every tool (simulate, evaluate, train, the nodes) then accepts its name.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.util
import inspect
import sys
from pathlib import Path
from typing import Any

from neural_estimator.scenarios.base import (
    EVALUATION_CONSTANTS,
    Scenario,
    ScenarioError,
    complex_step_jacobian,
    parse_assignments,
    psd_sqrt,
)
from neural_estimator.core.options import did_you_mean

# name -> "module:Class" for the built-ins (imported on first use) or a Scenario subclass.
_REGISTRY: dict[str, Any] = {
    "ballistic": "neural_estimator.scenarios.ballistic:Ballistic",
    "bearings": "neural_estimator.scenarios.bearings:Bearings",
    "lorenz96": "neural_estimator.scenarios.lorenz96:Lorenz96",
    "nlink": "neural_estimator.scenarios.nlink:NLinkPendulum",
    "quadrotor": "neural_estimator.scenarios.quadrotor:PlanarQuadrotor",
}

BUILTIN_SCENARIOS = tuple(_REGISTRY)


def register_scenario(cls: type[Scenario], name: str | None = None, *, replace: bool = False) -> type[Scenario]:
    """Register a :class:`Scenario` subclass under ``name`` (default ``cls.name``).

    Usable as a decorator. Re-registering a name is an error unless ``replace=True``.
    """
    key = name or cls.name
    if not (isinstance(cls, type) and issubclass(cls, Scenario)):
        raise ScenarioError(f"register_scenario expects a Scenario subclass, got {cls!r}")
    if key in _REGISTRY and not replace and not _same_definition(_REGISTRY[key], cls):
        raise ScenarioError(f"a scenario named {key!r} is already registered")
    _REGISTRY[key] = cls
    return cls


def _same_definition(a: Any, b: type) -> bool:
    """True when ``a`` is ``b`` or the same class defined in the same file (a plugin loaded twice)."""
    if a is b:
        return True
    try:
        return isinstance(a, type) and a.__qualname__ == b.__qualname__ and inspect.getfile(a) == inspect.getfile(b)
    except TypeError:
        return False


def load_plugins(paths) -> None:
    """Import user Python files that call :func:`register_scenario` (``--plugin``, the nodes' ``plugins``).

    Loading a plugin runs its code: it is the user's own file, named explicitly.
    """
    for p in paths or ():
        path = Path(p)
        if not path.is_file():
            raise ScenarioError(f"plugin {p}: no such file")
        spec = importlib.util.spec_from_file_location(f"neural_estimator_plugin_{path.stem}", path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = module  # the class's source file must be known (see _same_definition)
        try:
            spec.loader.exec_module(module)
        except Exception as exc:  # a user's file: report any failure as a bad input
            raise ScenarioError(f"plugin {p} failed to import: {exc}") from None


def scenario_names() -> list[str]:
    """Names of every registered scenario."""
    return list(_REGISTRY)


def scenario_class(name: str) -> type[Scenario]:
    """The class registered as ``name``; an unknown name is an error listing the valid ones."""
    try:
        entry = _REGISTRY[name]
    except KeyError:
        raise ScenarioError(
            f"unknown scenario {name!r}{did_you_mean(name, _REGISTRY)}; choose one of: {', '.join(_REGISTRY)}"
        ) from None
    if isinstance(entry, str):
        module, _, attr = entry.partition(":")
        entry = getattr(importlib.import_module(module), attr)
        _REGISTRY[name] = entry
    return entry


def make_scenario(name: str, preset: str | None = None, **overrides: Any) -> Scenario:
    """An instance of the scenario ``name``: its ``preset`` (None: the Config defaults, for a
    built-in the preset :func:`default_preset` names), then constants ``overrides`` applied."""
    cls = scenario_class(name)
    if preset is None or preset == "":
        return cls(**overrides)
    return cls(preset=preset, **overrides)


def default_preset(name: str) -> str | None:
    """The preset that the scenario ``name``'s Config defaults are, the constants every
    ``make_scenario(name)`` gets (for a built-in: ``v4``; N-link and bearings ``v5``); None for a
    scenario without presets."""
    cls = scenario_class(name)
    return cls.preset_of(cls.Config())


def preset_names(name: str) -> list[str]:
    """The presets of the scenario ``name``, newest first (empty for a scenario without any)."""
    return list(scenario_class(name).presets)


def code_digest(scenario: Scenario | type[Scenario]) -> str | None:
    """SHA-256 (16 hex) of the source file that defines a user scenario's class; None for a built-in.

    Cached results and data sets are keyed by a scenario's constants (:meth:`Scenario.describe`);
    a built-in's code is covered by the package version and the simulation revision, a plugin's is
    not, so its file's digest joins those keys: editing a plugin invalidates what it computed.
    """
    cls = scenario if isinstance(scenario, type) else type(scenario)
    if cls.__module__.startswith("neural_estimator.scenarios."):
        return None
    try:
        source = Path(inspect.getfile(cls)).read_bytes()
    except (TypeError, OSError):  # defined interactively: no file to hash
        return None
    return hashlib.sha256(source).hexdigest()[:16]


def scenario_from_description(desc: dict[str, Any]) -> Scenario:
    """Rebuild a scenario from :meth:`Scenario.describe` output (as stored in files)."""
    return make_scenario(desc["scenario"], **desc.get("config", {}))


__all__ = [
    "BUILTIN_SCENARIOS",
    "EVALUATION_CONSTANTS",
    "Scenario",
    "ScenarioError",
    "code_digest",
    "complex_step_jacobian",
    "default_preset",
    "load_plugins",
    "make_scenario",
    "parse_assignments",
    "preset_names",
    "psd_sqrt",
    "register_scenario",
    "scenario_class",
    "scenario_from_description",
    "scenario_names",
]
