"""Covariance localisation for the EnKF: Gaspari-Cohn tapers on declared component distances.

A scenario declares how far apart its state and observation components are by defining

    localization_distances() -> (d_xy (dx, dy), d_yy (dy, dy))

(non-negative, in any unit; the radius is given in the same unit). Lorenz 96 declares the cyclic
index distance on its ring (``Lorenz96.localization_distances``).
"""

from __future__ import annotations

import numpy as np

from neural_estimator.methods.interface import EstimatorError
from neural_estimator.scenarios import Scenario


def gaspari_cohn(z: np.ndarray) -> np.ndarray:
    r"""Gaspari & Cohn (1999), eq. (4.10): the compactly supported fifth-order taper of z = d / c.

        rho(z) = -z^5/4 + z^4/2 + 5 z^3/8 - 5 z^2/3 + 1                     0 <= z <= 1
        rho(z) = z^5/12 - z^4/2 + 5 z^3/8 + 5 z^2/3 - 5 z + 4 - 2 / (3 z)    1 <  z <= 2
        rho(z) = 0                                                           z > 2

    rho(0) = 1, rho(1) = 5/24 ... 0.208, rho vanishes from z = 2 on (support 2c); as a function
    of distance it is a correlation function, so the Schur product keeps covariances PSD.
    """
    z = np.abs(np.asarray(z, dtype=np.float64))
    out = np.zeros_like(z)
    a = z <= 1.0
    za = z[a]
    out[a] = (((-0.25 * za + 0.5) * za + 0.625) * za - 5.0 / 3.0) * za**2 + 1.0
    b = (z > 1.0) & (z < 2.0)
    zb = z[b]
    out[b] = ((((zb / 12.0 - 0.5) * zb + 0.625) * zb + 5.0 / 3.0) * zb - 5.0) * zb + 4.0 - 2.0 / (3.0 * zb)
    return out


def component_distances(s: Scenario, method: str = "enkf") -> tuple[np.ndarray, np.ndarray]:
    """(d_xy (dx, dy), d_yy (dy, dy)) of scenario ``s``, checked; EstimatorError if undeclared."""
    declared = getattr(s, "localization_distances", None)
    if callable(declared):
        d_xy, d_yy = declared()
    else:
        raise EstimatorError(
            f"{method}: localization needs distances between the components of scenario {s.name!r}; "
            "it declares none (define localization_distances() -> (d_xy (dx, dy), d_yy (dy, dy)))"
        )
    d_xy, d_yy = np.asarray(d_xy, dtype=np.float64), np.asarray(d_yy, dtype=np.float64)
    if d_xy.shape != (s.dx, s.dy) or d_yy.shape != (s.dy, s.dy):
        raise EstimatorError(
            f"{method}: localization distances of {s.name!r} must be ({s.dx}, {s.dy}) and ({s.dy}, {s.dy}), "
            f"got {d_xy.shape} and {d_yy.shape}"
        )
    if not (np.all(np.isfinite(d_xy)) and np.all(np.isfinite(d_yy)) and d_xy.min() >= 0 and d_yy.min() >= 0):
        raise EstimatorError(f"{method}: localization distances of {s.name!r} must be finite and >= 0")
    return d_xy, d_yy


def localization_tapers(s: Scenario, radius: float, method: str = "enkf") -> tuple[np.ndarray, np.ndarray]:
    """Gaspari-Cohn tapers (rho_xy, rho_yy) for half-support ``radius`` (taper 0 beyond 2 radius)."""
    d_xy, d_yy = component_distances(s, method)
    return gaspari_cohn(d_xy / radius), gaspari_cohn(d_yy / radius)
