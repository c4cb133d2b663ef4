"""The scenario contract: a discrete-time nonlinear state-space system with Gaussian noise.

A scenario is the paper's Eq. (1),

    x_{k+1} = f(x_k, u_k) + w_k,   w_k ~ N(0, Q)
    y_k     = h(x_k) + v_k,        v_k ~ N(0, R),   R = noise_scale^2 * R_0

with a prior x_0 ~ N(m0, P0) and, where the system has controls, an open-loop control policy.

Timing convention (used by the simulator, every estimator, the nodes and the bags):
    x_k is the state at step k, u_k the control applied from k to k+1, y_k = h(x_k) + v_k.
    At step k an estimator receives z_k = (y_k, u_{k-1}) with u_{-1} = 0, and returns
    x_hat_k computed from y_0..y_k and u_0..u_{k-1}. Filters update the prior with y_0 at k = 0;
    for k >= 1 they predict with u_{k-1}, then update with y_k. Neural models read [y_k, u_{k-1}].

Every method here is batched over any leading axes: ``x`` is (..., dx), ``u`` is (..., du),
``y`` is (..., dy); Jacobians are (..., rows, cols). Everything is float64.

Constants live in one frozen dataclass per scenario (its ``Config``). Every constant can be
overridden (``make_scenario("lorenz96", obs_noise_std=1.0)`` or ``--set obs_noise_std=1.0``) and is
recorded, through :meth:`Scenario.describe`, in every file the tools write.

Presets: a scenario's ``presets`` names whole sets of constants (overrides of its ``Config``
defaults), so that every earlier operating point stays one flag away: ``make_scenario("ballistic",
preset="v3")``, ``--preset v3`` on the command line, the nodes' ``preset`` parameter. The built-in
scenarios have ``v3`` (the constants calibrated to the paper's RMSE rows only) and ``v4`` (the
defaults of ballistic, Lorenz 96 and quadrotor: calibrated to the RMSE rows and the spread of the
true states, see docs/scenarios.md); N-link and bearings also have ``v5``, their defaults, the
operating point that fits both jointly (their ``v4`` equals ``v3``). A preset need not be the
defaults to be the newest: a new operating point can be named while its networks are trained.
``--set`` applies on top of the preset. :meth:`Scenario.describe` records the preset the constants
match (``"preset"``; ``"custom"`` when they match none), computed from the constants themselves, so
a file written before presets existed is labelled too.
"""

from __future__ import annotations

import dataclasses
import json
import math
from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

import numpy as np

from neural_estimator.core.angles import weighted_mean, wrap_components
from neural_estimator.core.options import OptionError, did_you_mean, parse_value

# The largest state, observation or control dimension a scenario may have. A filter holds dx x dx
# matrices (8 MiB each at 1024) and a scenario description can arrive from the ROS graph, so the
# bound is checked before anything of that size is allocated (see Scenario.dimension_fields).
MAX_DIMENSION = 1024


# The bound of every numeric constant (each element of a tuple too) that a scenario does not bound
# itself in ``constant_bounds``: the built-ins' constants are all within 1e4 of zero, and within 1e6
# squares (covariances: 1e12) and products of two constants stay far from float64's 1.8e308, so a
# constant beyond it is a typo or an attack, not a system. A scenario with larger constants (an
# orbit's GM = 3.986e14) declares their bounds. Non-finite values (NaN, inf) are always refused.
MAX_CONSTANT = 1e6

# Constants that set the work of one simulated step (integration substeps) or of the set-up (Lorenz
# 96's spin-up) are bounded so that a step costs at most 100x its default and a scenario starts in
# seconds: 10^9 substeps would run for hours before anything could be said about them.
WORK_BOUNDS = {"substeps": (1, 100), "spinup_steps": (0, 100_000)}


# Constants that describe an evaluation rather than the system: they may differ between a model's
# training and its use, and do not change which preset a set of constants is.
EVALUATION_CONSTANTS = ("noise_scale", "horizon")


# Smallest Cholesky pivot^2, relative to the largest variance, taken as positive definite (round-off
# of a singular matrix leaves ~1e-16; the built-in scenarios' smallest is N-link's 8e-6).
CHOLESKY_MIN_PIVOT = 1e-12


class ScenarioError(ValueError):
    """A scenario name, constant or input that cannot be used; the message names the problem."""


def psd_sqrt(cov: np.ndarray) -> np.ndarray:
    """A square root L with L L^T = cov for a symmetric positive semi-definite matrix, the same on
    every CPU (up to round-off).

    * diagonal cov: diag(sqrt(c_ii)), exactly;
    * positive definite: the Cholesky factor (unique: lower triangular, positive diagonal), when
      every pivot^2 exceeds CHOLESKY_MIN_PIVOT of the largest variance;
    * singular (a noise-free velocity, a white-noise-acceleration Q of rank dx/2): the principal,
      symmetric square root V diag(sqrt(lambda)) V^T of the eigen-decomposition cov = V diag(lambda)
      V^T, with eigenvalues below dx * eps * max(lambda) (round-off) set to 0.

    Why not V diag(sqrt(lambda)) itself: where an eigenvalue repeats (the bearings Q has 0.1125 twice,
    one per axis), its eigenvectors are any orthonormal basis of the eigenspace, and LAPACK picks a
    different one on different CPUs (seen between two AVX-512 machines). Every such V sqrt(Lambda) is
    a valid square root, but the noise eps L^T it turns the same standard normals into differs, so
    the same seed simulated different trajectories on different machines. The principal root depends
    only on the eigenspaces' projectors V_k V_k^T, which are unique.
    """
    cov = np.asarray(cov, dtype=np.float64)
    if cov.ndim != 2 or cov.shape[0] != cov.shape[1]:
        raise ScenarioError(f"covariance must be a square matrix, got shape {cov.shape}")
    scale = max(1.0, float(np.abs(cov).max(initial=0.0)))
    diag = np.diag(cov)
    if np.count_nonzero(cov - np.diag(diag)) == 0:
        if diag.size and diag.min() < -1e-9 * scale:
            raise ScenarioError(f"covariance is not positive semi-definite (diagonal entry {diag.min():.3g})")
        return np.diag(np.sqrt(np.clip(diag, 0.0, None)))
    try:
        L = np.linalg.cholesky(cov)
        # A singular matrix can pass Cholesky on round-off (a last pivot of ~1e-8 of the scale);
        # such a factor is as CPU-dependent as the round-off it divides by, so it counts as singular.
        if np.diag(L).min() ** 2 > CHOLESKY_MIN_PIVOT * diag.max():
            return L
    except np.linalg.LinAlgError:
        pass
    vals, vecs = np.linalg.eigh(0.5 * (cov + cov.T))
    if vals.min() < -1e-9 * max(1.0, abs(vals.max())):
        raise ScenarioError(f"covariance is not positive semi-definite (eigenvalue {vals.min():.3g})")
    vals = np.where(vals > cov.shape[0] * np.finfo(np.float64).eps * vals.max(), vals, 0.0)
    return (vecs * np.sqrt(vals)) @ vecs.T


def complex_step_jacobian(fn, x: np.ndarray, *args, h: float = 1e-30) -> np.ndarray:
    """Jacobian of ``fn(x, *args)`` with respect to ``x`` by the complex step.

    d fn / d x_j = Im(fn(x + i h e_j)) / h, exact to machine precision for functions that are real
    analytic and written with complex-safe operations (no abs, min, atan2 on the perturbed path).
    All dx perturbations are evaluated in one batched call.

    Args:
        fn: batched function (..., n) -> (..., m).
        x: (..., n) point.

    Returns:
        (..., m, n) Jacobian.
    """
    x = np.asarray(x, dtype=np.float64)
    n = x.shape[-1]
    xp = np.repeat(x[..., None, :], n, axis=-2).astype(np.complex128)  # (..., n, n): row j perturbs x_j
    xp[..., np.arange(n), np.arange(n)] += 1j * h
    args_b = [np.asarray(a)[..., None, :] if np.ndim(a) else a for a in args]
    out = fn(xp, *args_b)  # (..., n, m)
    return np.swapaxes(out.imag / h, -1, -2)


class Scenario(ABC):
    """Base class of the five systems and of user scenarios.

    Subclasses set the class attributes below, define a frozen ``Config`` dataclass (which must
    have ``dt``, ``horizon`` and ``noise_scale`` fields), and implement :meth:`f`, :meth:`h`,
    :meth:`process_cov`, :meth:`obs_cov_nominal`, :meth:`prior`. They may override the Jacobians
    (default: complex step), :meth:`sample_initial` and :meth:`sample_controls`.
    """

    name: ClassVar[str]
    Config: ClassVar[type]
    state_names: ClassVar[tuple[str, ...]]
    state_units: ClassVar[tuple[str, ...]]
    obs_names: ClassVar[tuple[str, ...]]
    obs_units: ClassVar[tuple[str, ...]]
    control_names: ClassVar[tuple[str, ...]] = ()
    control_units: ClassVar[tuple[str, ...]] = ()
    angle_states: ClassVar[tuple[int, ...]] = ()  # wrapped in errors, circular means, filter updates
    angle_obs: ClassVar[tuple[int, ...]] = ()  # wrapped in innovations
    # Which state components are a pose and its rates, for nav_msgs/Odometry output: keys among
    # x, y, z, roll, pitch, yaw (pose) and vx, vy, vz, wx, wy, wz (twist), values state indices.
    pose_states: ClassVar[dict[str, int]] = {}
    # Config fields that set a dimension, with how many dimensions one unit adds (Lorenz 96:
    # {"n_vars": 1}; N-link: {"n_links": 2}). Checked against MAX_DIMENSION before the scenario is
    # built, so a description naming 10^9 variables is refused before any allocation; a scenario
    # with variable dimensions should declare its fields here (dx, dy, du are checked after too).
    dimension_fields: ClassVar[dict[str, int]] = {}
    # Config fields with their own [low, high] (each element of a tuple field); every other numeric
    # field is bounded by +-MAX_CONSTANT, and substeps / spinup_steps by WORK_BOUNDS. Checked when
    # the scenario is built, before anything is simulated.
    constant_bounds: ClassVar[dict[str, tuple[float, float]]] = {}
    # Named sets of constants: preset name -> overrides of the Config defaults (see "Presets").
    # Newest first; the built-ins' "v4" is {} (the defaults); N-link's and bearings' "v5" are newer,
    # not the defaults.
    presets: ClassVar[dict[str, dict[str, Any]]] = {}

    def __init__(self, config: Any = None, preset: str | None = None, **overrides: Any) -> None:
        cfg = config if config is not None else self.Config()
        if preset is not None:
            cfg = replace_config(cfg, self.preset_constants(preset), scenario=self.name)
        if overrides:
            cfg = replace_config(cfg, overrides, scenario=self.name)
        self.config = cfg
        self._check_dimension_fields()
        self._check_constants()
        self._validate()
        self._check_dimensions()

    def _check_dimension_fields(self) -> None:
        for field, per_unit in self.dimension_fields.items():
            value = getattr(self.config, field)
            if isinstance(value, (int, np.integer)) and int(value) * per_unit > MAX_DIMENSION:
                raise ScenarioError(
                    f"scenario {self.name!r}: {field} = {value} gives {int(value) * per_unit} dimensions, "
                    f"more than the {MAX_DIMENSION} this package accepts"
                )

    def _check_constants(self) -> None:
        """Every numeric constant finite and within its bound (see ``constant_bounds``), by name."""
        for field in dataclasses.fields(self.config):
            own = {**WORK_BOUNDS, **self.constant_bounds}.get(field.name)
            lo, hi = own if own is not None else (-MAX_CONSTANT, MAX_CONSTANT)
            for v in _numbers(getattr(self.config, field.name)):
                if not math.isfinite(v):
                    raise ScenarioError(f"scenario {self.name!r}: {field.name} = {v} is not a finite number")
                if not lo <= v <= hi:
                    whose = "its bound" if own is not None else "the bound of every constant (MAX_CONSTANT)"
                    raise ScenarioError(
                        f"scenario {self.name!r}: {field.name} = {v:g} is outside [{lo:g}, {hi:g}], {whose}"
                    )

    def _check_dimensions(self) -> None:
        for what, n in (("state", self.dx), ("observation", self.dy), ("control", self.du)):
            if n > MAX_DIMENSION:
                raise ScenarioError(
                    f"scenario {self.name!r}: {n} {what} dimensions, more than the {MAX_DIMENSION} this package accepts"
                )

    @classmethod
    def preset_constants(cls, preset: str) -> dict[str, Any]:
        """The overrides of the Config defaults that make ``preset``; an unknown name is an error
        listing the valid ones."""
        try:
            return dict(cls.presets[str(preset)])
        except KeyError:
            valid = ", ".join(cls.presets) or "none"
            raise ScenarioError(f"scenario {cls.name!r} has no preset {preset!r}; valid: {valid}") from None

    @classmethod
    def preset_of(cls, config: Mapping[str, Any] | Any) -> str | None:
        """The name of the preset whose constants ``config`` (a Config or its dict) are, ignoring
        :data:`EVALUATION_CONSTANTS`; "custom" when none matches; None for a scenario without
        presets. The newest matching preset wins where two are equal."""
        if not cls.presets:
            return None
        theirs = config if isinstance(config, Mapping) else config_to_dict(config)
        for name, overrides in cls.presets.items():
            try:
                ours = config_to_dict(replace_config(cls.Config(), overrides, scenario=cls.name))
            except ScenarioError:
                continue
            if all(theirs.get(k) == v for k, v in ours.items() if k not in EVALUATION_CONSTANTS) and set(theirs) <= set(
                ours
            ):
                return name
        return "custom"

    # ---- dimensions and timing -------------------------------------------------------------
    @property
    def dx(self) -> int:
        return len(self.state_names)

    @property
    def dy(self) -> int:
        return len(self.obs_names)

    @property
    def du(self) -> int:
        return len(self.control_names)

    @property
    def dt(self) -> float:
        """Sampling period in seconds (or the scenario's time unit)."""
        return float(self.config.dt)

    @property
    def horizon(self) -> int:
        """Default number of steps of a trajectory."""
        return int(self.config.horizon)

    @property
    def longest_training_trajectory(self) -> int | None:
        """The longest training trajectory [steps] that is still informative, or None (no limit:
        the paper's 500-step trajectories). Training caps its trajectories at this length."""
        return None

    # ---- the model -------------------------------------------------------------------------
    @abstractmethod
    def f(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Noise-free transition x_{k+1} = f(x_k, u_k); (..., dx), (..., du) -> (..., dx)."""

    @abstractmethod
    def h(self, x: np.ndarray) -> np.ndarray:
        """Noise-free observation h(x_k); (..., dx) -> (..., dy)."""

    def jac_f(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """d f / d x at (x, u); (..., dx, dx). Default: complex step."""
        return complex_step_jacobian(self.f, x, u)

    def jac_h(self, x: np.ndarray) -> np.ndarray:
        """d h / d x at x; (..., dy, dx). Default: complex step."""
        return complex_step_jacobian(self.h, x)

    def torch_dynamics(self) -> Any:
        """The differentiable form of :meth:`f` and :meth:`h`: an object with ``f(x, u)`` and ``h(x)``
        on batched torch tensors (float64 capable), the same arithmetic as the numpy form, so that a
        method can backpropagate through the system (the five built-ins:
        :mod:`neural_estimator.scenarios.differentiable`, torch imported only when this is called).
        None (the default) where the scenario has none."""
        return None

    def obs_matrix(self) -> np.ndarray | None:
        """H (dy, dx) when the observation is exactly linear, h(x) = H x, else None (the default).

        A declaration, not a requirement: filters may then use closed forms (the UKF's update is
        the Kalman update, which its unscented transform of a linear h equals in exact arithmetic).
        The test suite checks h(x) == H x for every scenario that declares it.
        """
        return None

    def state_from_observation(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """The state components one observation determines, for starting a filter at it.

        Returns ``(x, observed)``: ``x`` (..., dx) holds h's inverse on the components it
        determines and the prior mean m0 elsewhere; ``observed`` (dx,) bool says which are which.
        None where h is invertible on no component (a bearing alone fixes no coordinate).

        Default: an exactly linear h = H x (:meth:`obs_matrix`): the components whose columns of
        H are nonzero, solved by least squares, x_o = H_o^+ (y - H_u m0_u), when those columns have
        full rank (Lorenz 96: H = I, x = y). Scenarios with a nonlinear h that is invertible on
        some components override it.
        """
        H = self.obs_matrix()
        if H is None:
            return None
        H = np.asarray(H, dtype=np.float64)
        observed = np.any(H != 0.0, axis=0)  # (dx,)
        Ho = H[:, observed]
        if not observed.any() or np.linalg.matrix_rank(Ho) < Ho.shape[1]:
            return None
        m0 = np.asarray(self.prior()[0], dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        rhs = y - m0[~observed] @ H[:, ~observed].T  # (..., dy)
        x = np.broadcast_to(m0, y.shape[:-1] + (self.dx,)).copy()
        x[..., observed] = rhs @ np.linalg.pinv(Ho).T
        return x, observed

    @abstractmethod
    def process_cov(self) -> np.ndarray:
        """Q, the (dx, dx) covariance of w_k."""

    @abstractmethod
    def obs_cov_nominal(self) -> np.ndarray:
        """R_0, the (dy, dy) covariance of v_k at noise_scale = 1."""

    def obs_cov(self) -> np.ndarray:
        """R = noise_scale^2 R_0: the observation noise the simulator draws and filters are told."""
        return float(self.config.noise_scale) ** 2 * self.obs_cov_nominal()

    @abstractmethod
    def prior(self) -> tuple[np.ndarray, np.ndarray]:
        """(m0, P0): mean (dx,) and covariance (dx, dx) of x_0, given to the model-based filters."""

    # ---- sampling ----------------------------------------------------------------------------
    def sample_initial(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """n true initial states (n, dx). Default: draws from the prior N(m0, P0)."""
        m0, p0 = self.prior()
        return m0 + rng.standard_normal((n, self.dx)) @ psd_sqrt(p0).T

    def sample_controls(self, rng: np.random.Generator, n: int, horizon: int) -> np.ndarray:
        """Open-loop controls (n, horizon, du); u[:, k] acts from step k to k+1. Default: none."""
        return np.zeros((n, horizon, self.du))

    # ---- residuals and means that respect angles -----------------------------------------------
    def state_residual(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """a - b with angular state components wrapped to (-pi, pi]."""
        return wrap_components(np.asarray(a) - np.asarray(b), self.angle_states)

    def obs_residual(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """a - b with angular observation components wrapped (innovations)."""
        return wrap_components(np.asarray(a) - np.asarray(b), self.angle_obs)

    def state_mean(self, points: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
        """Mean over the member axis (-2) of (..., N, dx) points, circular for angles."""
        return weighted_mean(points, weights, self.angle_states)

    def obs_mean(self, points: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
        """Mean over the member axis (-2) of (..., N, dy) predicted observations."""
        return weighted_mean(points, weights, self.angle_obs)

    def normalize_state(self, x: np.ndarray) -> np.ndarray:
        """Wrap the angular components of a state (after an additive update)."""
        return wrap_components(x, self.angle_states)

    # ---- description ---------------------------------------------------------------------------
    def describe(self) -> dict[str, Any]:
        """Everything that defines this scenario instance, JSON-serialisable (recorded in files)."""
        config = config_to_dict(self.config)
        out = {
            "scenario": self.name,
            "config": config,
            "state_names": list(self.state_names),
            "state_units": list(self.state_units),
            "obs_names": list(self.obs_names),
            "obs_units": list(self.obs_units),
            "control_names": list(self.control_names),
            "control_units": list(self.control_units),
            "angle_states": list(self.angle_states),
            "angle_obs": list(self.angle_obs),
            "dt": self.dt,
        }
        preset = self.preset_of(config)
        if preset is not None:
            out["preset"] = preset
        return out

    def _validate(self) -> None:
        for field in ("dt", "horizon", "noise_scale"):
            if not hasattr(self.config, field):
                raise ScenarioError(f"scenario {self.name!r}: its Config needs a {field!r} field")
        if not float(self.config.dt) > 0:
            raise ScenarioError(f"scenario {self.name!r}: dt must be positive, got {self.config.dt}")
        if int(self.config.horizon) < 1:
            raise ScenarioError(f"scenario {self.name!r}: horizon must be >= 1, got {self.config.horizon}")
        if not float(self.config.noise_scale) >= 0:
            raise ScenarioError(f"scenario {self.name!r}: noise_scale must be >= 0, got {self.config.noise_scale}")
        m0, p0 = self.prior()
        if np.shape(m0) != (self.dx,) or np.shape(p0) != (self.dx, self.dx):
            raise ScenarioError(f"scenario {self.name!r}: prior must be ({self.dx},) and ({self.dx}, {self.dx})")
        for label, cov, n in (("Q", self.process_cov(), self.dx), ("R", self.obs_cov_nominal(), self.dy)):
            if np.shape(cov) != (n, n):
                raise ScenarioError(f"scenario {self.name!r}: {label} must be ({n}, {n}), got {np.shape(cov)}")
        psd_sqrt(p0)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.config})"


# ---- configs ------------------------------------------------------------------------------------
def config_to_dict(cfg: Any) -> dict[str, Any]:
    """A config dataclass as plain JSON types (tuples become lists)."""
    out = {}
    for f in dataclasses.fields(cfg):
        v = getattr(cfg, f.name)
        out[f.name] = json.loads(json.dumps(_jsonable(v)))
    return out


def _numbers(value: Any, depth: int = 0) -> list[float]:
    """The numbers of a constant (a scalar, or the elements of nested tuples, lists or arrays) as
    floats; an integer too large for a float is inf (refused as not finite). Booleans and text are
    not numbers here."""
    if isinstance(value, (bool, np.bool_, str)) or depth > 4:
        return []
    if isinstance(value, (int, np.integer)):
        return [float(value) if abs(int(value)) < 2**1023 else math.inf]
    if isinstance(value, (float, np.floating)):
        return [float(value)]
    if isinstance(value, np.ndarray):
        return [float(v) for v in value.ravel()] if value.dtype.kind in "iuf" else []
    if isinstance(value, (tuple, list)):
        return [v for e in value for v in _numbers(e, depth + 1)]
    return []


def _jsonable(v: Any) -> Any:
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, tuple):
        return [_jsonable(e) for e in v]
    return v


def _coerce(value: Any, default: Any, name: str, scenario: str) -> Any:
    """Convert ``value`` (often a command-line string) to the type of the field's default
    (:func:`neural_estimator.core.options.parse_value`, the package's one grammar)."""
    try:
        return parse_value(value, default, name)
    except OptionError as exc:
        raise ScenarioError(f"scenario {scenario!r}: {exc}") from None


def replace_config(cfg: Any, overrides: Mapping[str, Any], scenario: str = "") -> Any:
    """A copy of ``cfg`` with ``overrides`` applied; unknown names are an error listing valid ones."""
    fields = {f.name: f for f in dataclasses.fields(cfg)}
    changes = {}
    for name, value in overrides.items():
        if name not in fields:
            hint = did_you_mean(name, fields)
            raise ScenarioError(
                f"scenario {scenario!r} has no constant {name!r}{hint}; valid: {', '.join(sorted(fields))}"
            )
        changes[name] = _coerce(value, getattr(cfg, name), name, scenario)
    return dataclasses.replace(cfg, **changes)


def parse_assignments(items: Sequence[str] | None) -> dict[str, str]:
    """Parse ``["name=value", ...]`` (the ``--set`` flag) into a dict of strings."""
    out: dict[str, str] = {}
    for item in items or ():
        name, sep, value = item.partition("=")
        if not sep or not name.strip():
            raise ScenarioError(f"--set expects name=value, got {item!r}")
        out[name.strip()] = value.strip()
    return out
