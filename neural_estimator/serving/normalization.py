"""Z-score normalisation of a neural estimator's inputs and outputs.

Inputs are the paper's z_t = y_t (no controls) or z_t = [y_t, u_{t-1}] (controls; u_{-1} = 0, see
:func:`neural_estimator.methods.interface.previous_controls`), outputs the state x_t. With statistics
taken over every timestep of the training set (all N trajectories x T steps),

    z_n = (z - mu_z) / sigma_z          (d_in,)   what the network reads
    x_n = (x - mu_x) / sigma_x          (dx,)     what the network is trained to output
    x_hat = mu_x + sigma_x * x_hat_n               what the estimator returns
    P_hat = diag(sigma_x) C_n diag(sigma_x)        a normalised covariance C_n in state units

sigma = max(std, STD_FLOOR * max(1, |mu|)): a component that never varies in the training set (a
control that is always zero, say) maps to 0 instead of dividing by zero.

Angles. Angular state components (``scenario.angle_states``) are predicted directly, in radians,
with mu = 0 and sigma = 1: a z-score of an angle in (-pi, pi] would move the wrap point and a
z-scored mean of angles is not a circular mean. The training loss wraps the error of these
components to (-pi, pi] (:func:`neural_estimator.training.loop.state_error`), exactly as the
evaluation's errors are wrapped (:func:`neural_estimator.metrics.errors`), so an estimate of
pi - 0.01 for a true -pi + 0.01 costs 0.02, not 2 pi - 0.02. The network's raw output for an angle
is any real number; :meth:`Normalizer.denormalize_states` wraps it to (-pi, pi]. Angular
observations (bearings) are read like every other input, z-scored, as the paper feeds y_t.

The statistics are stored in the checkpoint card (:meth:`to_dict`, JSON floats round-trip exactly).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from neural_estimator.core.angles import wrap_components
from neural_estimator.methods.interface import previous_controls

STD_FLOOR = 1e-6  # relative to max(1, |mean|)


class NormalizationError(ValueError):
    """Statistics that cannot be used (wrong shapes, non-finite, non-positive spread)."""


def _floored_std(mean: np.ndarray, std: np.ndarray, floor: float) -> np.ndarray:
    return np.maximum(std, floor * np.maximum(1.0, np.abs(mean)))


@dataclass(frozen=True, eq=False)
class Normalizer:
    """Per-component z-score of inputs [y, u_prev] and of states x.

    Attributes:
        in_mean, in_std: (d_in,) statistics of z = [y, u_prev], d_in = dy + du.
        out_mean, out_std: (dx,) statistics of x (0 and 1 on angular components).
        dy, du: the observation and control widths inside z.
        angle_states: angular state components (wrapped on the way out).
    """

    in_mean: np.ndarray
    in_std: np.ndarray
    out_mean: np.ndarray
    out_std: np.ndarray
    dy: int
    du: int
    angle_states: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        for name in ("in_mean", "in_std", "out_mean", "out_std"):
            object.__setattr__(self, name, np.asarray(getattr(self, name), dtype=np.float64))
        object.__setattr__(self, "angle_states", tuple(int(i) for i in self.angle_states))
        d_in = self.dy + self.du
        if self.in_mean.shape != (d_in,) or self.in_std.shape != (d_in,):
            raise NormalizationError(
                f"input statistics must be ({d_in},) for dy={self.dy}, du={self.du}; "
                f"got {self.in_mean.shape} and {self.in_std.shape}"
            )
        if self.out_mean.ndim != 1 or self.out_std.shape != self.out_mean.shape:
            raise NormalizationError(
                f"state statistics must be (dx,); got {self.out_mean.shape} and {self.out_std.shape}"
            )
        for name in ("in_mean", "in_std", "out_mean", "out_std"):
            if not np.all(np.isfinite(getattr(self, name))):
                raise NormalizationError(f"normalisation statistic {name} holds NaN or inf")
        if np.any(self.in_std <= 0) or np.any(self.out_std <= 0):
            raise NormalizationError("normalisation standard deviations must be positive")
        if any(not 0 <= i < self.dx for i in self.angle_states):
            raise NormalizationError(f"angle_states {self.angle_states} out of range for dx={self.dx}")

    @property
    def d_in(self) -> int:
        return self.dy + self.du

    @property
    def dx(self) -> int:
        return int(self.out_mean.shape[0])

    # ---- fitting -------------------------------------------------------------------------------
    @classmethod
    def fit(
        cls,
        y: np.ndarray,
        u_prev: np.ndarray,
        x: np.ndarray,
        angle_states=(),
        std_floor: float = STD_FLOOR,
        labelled: np.ndarray | None = None,
    ) -> "Normalizer":
        """Statistics over every timestep of a training set.

        Args:
            y: (N, T, dy) observations (finite).
            u_prev: (N, T, du) previous controls u_{t-1} (``previous_controls(U)``); du may be 0.
            x: (N, T, dx) true states.
            angle_states: angular state components (mean 0, std 1: see the module docstring).
            std_floor: relative floor of the standard deviations.
            labelled: (N, T) bool, the steps whose x is ground truth (partial ground truth): the
                state statistics use those only (the inputs' use every step); None: every step.
        """
        y, u_prev, x = (np.asarray(a, dtype=np.float64) for a in (y, u_prev, x))
        if not (np.all(np.isfinite(y)) and np.all(np.isfinite(u_prev)) and np.all(np.isfinite(x))):
            raise NormalizationError("training data hold NaN or inf; statistics need finite data")
        dy, du, dx = y.shape[-1], u_prev.shape[-1], x.shape[-1]
        rows = int(np.prod(y.shape[:-1]))
        z = np.concatenate([y.reshape(rows, dy), u_prev.reshape(rows, du)], axis=1)  # (N T, d_in)
        xs = x.reshape(rows, dx)
        if labelled is not None:  # a placeholder state is no sample of the truth's distribution
            xs = xs[np.asarray(labelled, dtype=bool).reshape(rows)]
        in_mean, in_std = z.mean(0), z.std(0)
        out_mean, out_std = xs.mean(0), xs.std(0)
        idx = list(angle_states)
        out_mean[idx], out_std[idx] = 0.0, 1.0
        return cls(
            in_mean,
            _floored_std(in_mean, in_std, std_floor),
            out_mean,
            _floored_std(out_mean, out_std, std_floor),
            dy,
            du,
            tuple(angle_states),
        )

    @classmethod
    def from_data(cls, scenario, data, std_floor: float = STD_FLOOR) -> "Normalizer":
        """:meth:`fit` on a :class:`~neural_estimator.data.Trajectories` training set of ``scenario``."""
        return cls.fit(
            data.y, previous_controls(data.u), data.x, scenario.angle_states, std_floor, getattr(data, "labelled", None)
        )

    # ---- the maps ------------------------------------------------------------------------------
    def normalize_inputs(self, y: np.ndarray, u_prev: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """z_n = ([y, u_prev] - mu_z) / sigma_z, with unusable observations replaced.

        Args:
            y: (..., dy) observations; a row with any NaN or inf is not used.
            u_prev: (..., du) previous controls (finite).

        Returns:
            z_n (..., d_in) float64, where the y part of a non-finite row is 0 (the training mean);
            skipped (...,) bool, True for those rows.
        """
        y = np.asarray(y, dtype=np.float64)
        u_prev = np.asarray(u_prev, dtype=np.float64)
        skipped = ~np.all(np.isfinite(y), axis=-1)
        z = np.concatenate([y, u_prev], axis=-1)
        z = (z - self.in_mean) / self.in_std
        if skipped.any():
            z[skipped, : self.dy] = 0.0
        return z, skipped

    def normalize_states(self, x: np.ndarray) -> np.ndarray:
        """(x - mu_x) / sigma_x; angular components unchanged (mu 0, sigma 1)."""
        return (np.asarray(x, dtype=np.float64) - self.out_mean) / self.out_std

    def denormalize_states(self, x_n: np.ndarray) -> np.ndarray:
        """mu_x + sigma_x x_n in float64, angular components wrapped to (-pi, pi]."""
        x = np.asarray(x_n, dtype=np.float64) * self.out_std + self.out_mean
        return wrap_components(x, self.angle_states)

    def denormalize_covariance(self, cov_n: np.ndarray) -> np.ndarray:
        """diag(sigma_x) C_n diag(sigma_x) for (..., dx, dx) normalised covariances."""
        s = self.out_std
        return np.asarray(cov_n, dtype=np.float64) * s[:, None] * s[None, :]

    # ---- storage -------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """JSON-ready statistics (stored in the checkpoint card)."""
        return {
            "inputs": "z = [y, u_prev]",
            "in_mean": self.in_mean.tolist(),
            "in_std": self.in_std.tolist(),
            "out_mean": self.out_mean.tolist(),
            "out_std": self.out_std.tolist(),
            "dy": self.dy,
            "du": self.du,
            "angle_states": list(self.angle_states),
            "std_floor": STD_FLOOR,
            "angles": "predicted directly in radians (mean 0, std 1), wrapped-error loss, output wrapped",
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "Normalizer":
        """Inverse of :meth:`to_dict`; a missing or malformed field raises NormalizationError."""
        try:
            return cls(
                np.asarray(d["in_mean"], dtype=np.float64),
                np.asarray(d["in_std"], dtype=np.float64),
                np.asarray(d["out_mean"], dtype=np.float64),
                np.asarray(d["out_std"], dtype=np.float64),
                int(d["dy"]),
                int(d["du"]),
                tuple(d.get("angle_states", ())),
            )
        except (KeyError, TypeError, ValueError) as exc:
            if isinstance(exc, NormalizationError):
                raise
            raise NormalizationError(f"normalisation statistics are malformed: {exc!r}") from None
