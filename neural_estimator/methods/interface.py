"""The estimator interface shared by the ten methods (the bottom of the estimator layers).

The classical filters (:mod:`neural_estimator.filters`) and the neural models
(:mod:`neural_estimator.models`) implement :class:`Estimator`; the table of methods
(:mod:`neural_estimator.methods.table`) names each of them and where its factory is, and
:mod:`neural_estimator.methods.registry` builds any of them by name from the table.

Contract (every method, classical or neural):

- ``reset(batch)``: start ``batch`` independent streams (filters from the prior (m0, P0); neural
  models from their initial hidden state / empty cache). A ``step`` before any ``reset`` starts
  as many streams as its observation has rows (both families alike, tested).
- ``step(y, u_prev) -> x_hat``: one time step for B streams. ``y`` is (B, dy), ``u_prev`` is
  (B, du) = u_{k-1} (zeros at k = 0), ``x_hat`` is (B, dx). After a step, ``covariance`` holds
  (B, dx, dx) where the method has one (else None) and ``diverged`` (B,) flags streams whose
  estimate or covariance went non-finite (they stay flagged until ``reset``).
- ``run(Y, U) -> Estimates``: whole sequences, ``Y`` (B, T, dy) and ``U`` (B, T, du) with
  ``U[:, k] = u_k`` as stored in datasets (the estimator itself shifts to u_{k-1}). Filters loop over
  time vectorised over B; neural models use their parallel form. Invariant, tested for every
  method: ``run`` equals a loop of ``step``.

Timing (see :mod:`neural_estimator.scenarios.base`): at step k the estimator receives
z_k = (y_k, u_{k-1}) and returns x_hat_k from y_0..y_k and u_0..u_{k-1}.

Observations that are non-finite are not used: filters predict only and neural models see the
training mean in their place; the step is reported through ``skipped`` (B,) for that step.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, ClassVar, NamedTuple

import numpy as np

from neural_estimator.methods import table
from neural_estimator.core.options import did_you_mean
from neural_estimator.scenarios import Scenario


class EstimatorError(ValueError):
    """Bad input to an estimator or an unknown method; the message names the problem."""


class Estimates(NamedTuple):
    """Output of :meth:`Estimator.run`."""

    x: np.ndarray  # (B, T, dx) state estimates
    cov: np.ndarray | None  # (B, T, dx, dx) covariance where the method has one
    diverged: np.ndarray  # (B,) True where the stream went non-finite at any step


# The names of the table (neural_estimator.methods.table) when this module was imported, for scripts
# and tests; the package itself asks the table (table.names(), table.has()) when it needs to know.
CLASSICAL_METHODS = table.names(family="classical")
NEURAL_METHODS = table.names(family="neural")
METHODS = table.names()


def previous_controls(U: np.ndarray) -> np.ndarray:
    """u_{k-1} for every k: (B, T, du) with zeros at k = 0 (the timing convention's u_{-1} = 0)."""
    prev = np.zeros_like(U)
    prev[:, 1:] = U[:, :-1]
    return prev


class Estimator(ABC):
    """Base class of the ten methods (see the module docstring for the contract)."""

    method: ClassVar[str]
    has_covariance: ClassVar[bool] = False

    def __init__(self, scenario: Scenario) -> None:
        self.scenario = scenario
        self.covariance: np.ndarray | None = None
        self.diverged = np.zeros(0, dtype=bool)
        self.skipped = np.zeros(0, dtype=bool)
        self.batch = 0

    @abstractmethod
    def reset(self, batch: int = 1) -> None:
        """Start ``batch`` independent streams."""

    @abstractmethod
    def step(self, y: np.ndarray, u_prev: np.ndarray | None = None) -> np.ndarray:
        """Consume z_k = (y_k, u_{k-1}) for B streams and return x_hat_k (B, dx)."""

    def start_streams_if_none(self, batch: int) -> None:
        """What ``step`` does with no streams started: ``reset(batch)`` (see the module docstring)."""
        if not self.batch:
            self.reset(batch)

    def run(self, Y: np.ndarray, U: np.ndarray | None = None) -> Estimates:
        """Estimate whole sequences: Y (B, T, dy), U (B, T, du) -> :class:`Estimates`.

        The default loops :meth:`step`; subclasses override with a faster form that must agree.
        """
        Y, U = self.check_sequences(Y, U)
        B, T, _ = Y.shape
        self.reset(B)
        Uprev = previous_controls(U)
        xs = np.empty((B, T, self.scenario.dx))
        covs = np.empty((B, T, self.scenario.dx, self.scenario.dx)) if self.has_covariance else None
        for k in range(T):
            xs[:, k] = self.step(Y[:, k], Uprev[:, k])
            if covs is not None:
                covs[:, k] = self.covariance
        return Estimates(xs, covs, self.diverged.copy())

    # ---- input checks shared by every method --------------------------------------------------
    def check_step(self, y: Any, u_prev: Any) -> tuple[np.ndarray, np.ndarray]:
        """Validate one step's inputs; returns float64 (B, dy) and (B, du)."""
        s = self.scenario
        y = np.asarray(y, dtype=np.float64)
        if y.ndim == 1:
            y = y[None]
        if y.ndim != 2 or y.shape[1] != s.dy:
            raise EstimatorError(
                f"{self.method}: observation must be (B, {s.dy}) for scenario {s.name!r} "
                f"({', '.join(s.obs_names)}), got shape {y.shape}"
            )
        if self.batch and y.shape[0] != self.batch:
            raise EstimatorError(f"{self.method}: batch of {y.shape[0]} observations, but reset for {self.batch}")
        if u_prev is None:
            u_prev = np.zeros((y.shape[0], s.du))
        u_prev = np.asarray(u_prev, dtype=np.float64)
        if u_prev.ndim == 1:
            u_prev = u_prev[None]
        if u_prev.shape != (y.shape[0], s.du):
            raise EstimatorError(f"{self.method}: control must be ({y.shape[0]}, {s.du}), got shape {u_prev.shape}")
        if not np.all(np.isfinite(u_prev)):
            raise EstimatorError(f"{self.method}: control contains NaN or inf")
        return y, u_prev

    def check_sequences(self, Y: Any, U: Any) -> tuple[np.ndarray, np.ndarray]:
        """Validate whole sequences; returns float64 (B, T, dy) and (B, T, du)."""
        s = self.scenario
        Y = np.asarray(Y, dtype=np.float64)
        if Y.ndim != 3 or Y.shape[2] != s.dy:
            raise EstimatorError(
                f"{self.method}: observations must be (B, T, {s.dy}) for scenario {s.name!r}, got shape {Y.shape}"
            )
        if U is None:
            U = np.zeros(Y.shape[:2] + (s.du,))
        U = np.asarray(U, dtype=np.float64)
        if U.shape != Y.shape[:2] + (s.du,):
            raise EstimatorError(f"{self.method}: controls must be {Y.shape[:2] + (s.du,)}, got shape {U.shape}")
        if not np.all(np.isfinite(U)):
            raise EstimatorError(f"{self.method}: controls contain NaN or inf")
        return Y, U


def check_method(method: str) -> str:
    """Return ``method`` lower-cased if the table has it (a method compared, not a baseline);
    otherwise an error listing the valid names."""
    m = str(method).strip().lower().replace("-", "")
    valid = table.names()
    if m not in valid:
        raise EstimatorError(
            f"unknown method {method!r}{did_you_mean(method, valid)}; choose one of: {', '.join(valid)}"
        )
    return m
