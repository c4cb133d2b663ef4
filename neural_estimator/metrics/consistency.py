"""Consistency of an estimator's covariance: NEES, coverage at any level, and the calibration scale.

An estimator that reports x_hat_t with covariance P_t claims e_t = x_hat_t - x_t ~ N(0, P_t). Then
the normalised estimation error squared

    eps_t = e_t^T P_t^{-1} e_t   ~   chi^2(dx)                    (NEES; E eps = dx)

and the region {x : (x_hat - x)^T P^-1 (x_hat - x) <= chi2_dx^{-1}(q)} holds the truth with probability
q for every nominal level q. Measured on (n, t) pairs:

    coverage(q)   = share of pairs with eps <= chi2_dx^{-1}(q)     (degenerate P: not covered)
    reliability   = the curve q -> coverage(q) at :data:`RELIABILITY_LEVELS` (the diagonal when consistent)
    cal. error    = mean_q |coverage(q) - q|                        (0 when consistent)
    mean NEES/dx  = 1 when consistent; > 1 over-confident (P too small), < 1 too wide (P too large)

A covariance scaled by s (P -> s P) divides every eps by s, so one scale factor fitted on validation
data moves the coverage to its nominal level (:func:`fit_scale`):

    s_cov  = quantile_{0.95}(eps) / chi2_dx^{-1}(0.95)     (95 % coverage exactly 0.95 on the data)
    s_mean = mean(eps) / dx                                 (mean NEES exactly dx on the data)
    s_band = argmin { cal. error(eps / s) : coverage_95(eps / s) in FIT_BAND }

The last is for heavy-tailed errors, where no Gaussian is right everywhere: a scale that puts 95 %
inside the 95 % region makes the bulk of the errors look far too small (median NEES << dx). s_band
minimises the error over the whole reliability curve among the scales whose 95 % coverage stays in
FIT_BAND = [0.92, 0.97], the done-when band [0.90, 0.98] with a margin for fresh data (the interval
quantile_0.92(eps) / chi2(0.95) .. quantile_0.97(eps) / chi2(0.95), searched on 400 log-spaced
points); for Gaussian errors it is close to s_cov.

The NEES itself (with the degenerate-covariance rule) is :func:`neural_estimator.metrics.nees`;
references: Bar-Shalom, Li, Kirubarajan (2001), "Estimation with Applications to Tracking and
Navigation", Sec. 5.4; Kuleshov, Fenner, Ermon (2018), "Accurate Uncertainties for Deep Learning
Using Calibrated Regression", https://arxiv.org/abs/1807.00263 (reliability curves, recalibration).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

RELIABILITY_LEVELS = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.95, 0.99)
# The done-when band of a calibrated estimator: 95 % coverage and mean NEES / dx.
COVERAGE_BAND = (0.90, 0.98)
NEES_BAND = (0.7, 1.5)
SCALE_TARGETS = ("coverage", "mean", "band")
# A reliability curve whose mean distance from the diagonal exceeds this is not called consistent,
# whatever its 95 % coverage and mean NEES.
CALIBRATION_ERROR_MAX = 0.1
# The 95 % coverage band the "band" scale is chosen in: inside COVERAGE_BAND with a margin, so that
# a scale fitted on one validation set stays in the band on fresh data.
FIT_BAND = (0.92, 0.97)


class ConsistencyError(ValueError):
    """Inputs the consistency figures cannot be computed from; the message names the problem."""


def chi2_quantile(dx: int, level: float | np.ndarray) -> np.ndarray:
    """chi2_dx^{-1}(level): the NEES bound of the nominal ``level`` region."""
    from scipy.special import chdtri  # chi2.ppf(q, k) = chdtri(k, 1 - q)

    return chdtri(int(dx), 1.0 - np.asarray(level, dtype=np.float64))


def coverage_curve(eps: np.ndarray, dx: int, levels: Sequence[float] = RELIABILITY_LEVELS) -> np.ndarray:
    """coverage(q) for every q of ``levels``: the share of ``eps`` (any shape, inf = degenerate) within
    chi2_dx^{-1}(q). NaN values count as not covered."""
    eps = np.asarray(eps, dtype=np.float64).ravel()
    if eps.size == 0:
        raise ConsistencyError("no NEES values to measure a coverage from")
    if any(not 0.0 < q < 1.0 for q in levels):
        raise ConsistencyError(f"levels must lie in (0, 1), got {list(levels)}")
    bounds = chi2_quantile(dx, np.asarray(levels))
    with np.errstate(invalid="ignore"):
        return np.array([float(np.mean(eps <= b)) for b in bounds])


def calibration_error(curve: Sequence[float], levels: Sequence[float] = RELIABILITY_LEVELS) -> float:
    """mean_q |coverage(q) - q| of a reliability curve."""
    curve, levels = np.asarray(curve, dtype=np.float64), np.asarray(levels, dtype=np.float64)
    if curve.shape != levels.shape:
        raise ConsistencyError(f"a curve of {curve.size} coverages for {levels.size} levels")
    return float(np.mean(np.abs(curve - levels)))


def fit_scale(eps: np.ndarray, dx: int, target: str = "coverage") -> float:
    """The covariance scale s (P -> s P) that makes ``eps`` consistent (module docstring).

    Args:
        eps: NEES values of validation (n, t) pairs; degenerate (inf) ones are left out of ``mean``
            and count as large in ``coverage``.
        dx: state dimension.
        target: ``coverage`` (95 % coverage exactly 0.95), ``mean`` (mean NEES exactly dx) or
            ``band`` (the smallest calibration error with the 95 % coverage in its band).
    """
    eps = np.asarray(eps, dtype=np.float64).ravel()
    eps = eps[~np.isnan(eps)]
    if target not in SCALE_TARGETS:
        raise ConsistencyError(f"target must be one of {', '.join(SCALE_TARGETS)}, got {target!r}")
    if target == "band":
        return _band_scale(eps, dx)
    if target == "mean":
        finite = eps[np.isfinite(eps)]
        if finite.size == 0:
            raise ConsistencyError("no usable covariance to fit a scale on")
        s = float(finite.mean() / dx)
    else:
        if eps.size == 0:
            raise ConsistencyError("no NEES values to fit a scale on")
        s = float(np.quantile(eps, 0.95) / chi2_quantile(dx, 0.95))
    if not (math.isfinite(s) and s > 0):
        raise ConsistencyError(f"the fitted scale is {s}: most covariances are degenerate or the errors are zero")
    return s


def _band_scale(eps: np.ndarray, dx: int, points: int = 400) -> float:
    """s_band of the module docstring."""
    if eps.size == 0:
        raise ConsistencyError("no NEES values to fit a scale on")
    q95 = float(chi2_quantile(dx, 0.95))
    lo, hi = (float(np.quantile(eps, c)) / q95 for c in FIT_BAND)
    if not (math.isfinite(lo) and math.isfinite(hi) and lo > 0):
        raise ConsistencyError("most covariances are degenerate or the errors are zero: no scale fits")
    srt = np.sort(eps)
    bounds = chi2_quantile(dx, np.asarray(RELIABILITY_LEVELS))  # (L,)
    scales = np.geomspace(lo, hi, points) if hi > lo else np.array([lo])
    cover = np.searchsorted(srt, scales[:, None] * bounds[None, :], side="right") / srt.size  # (S, L)
    err = np.abs(cover - np.asarray(RELIABILITY_LEVELS)).mean(axis=1)
    c95 = cover[:, RELIABILITY_LEVELS.index(0.95)]
    in_band = (c95 >= FIT_BAND[0] - 1e-12) & (c95 <= FIT_BAND[1] + 1e-12)
    err = np.where(in_band, err, np.inf)
    return float(scales[int(np.argmin(err))]) if np.isfinite(err).any() else float(np.quantile(eps, 0.95) / q95)


def verdict(nees_mean_per_dim: float | None, coverage95: float | None, calibration_error: float | None = None) -> str:
    """``consistent`` (both in the done-when bands :data:`COVERAGE_BAND`, :data:`NEES_BAND`),
    ``over-confident`` (coverage below its band or NEES above), ``too wide`` (coverage above or NEES
    below), ``mixed`` (one says each), ``mis-shaped`` (both in their bands but the reliability curve
    far from the diagonal: calibration error above :data:`CALIBRATION_ERROR_MAX`, e.g. most errors
    far inside the region and a few far out), ``—`` without a covariance."""
    if nees_mean_per_dim is None or coverage95 is None:
        return "—"
    c, r = float(coverage95), float(nees_mean_per_dim)
    if math.isnan(c) or math.isnan(r):
        return "N/A"
    over = c < COVERAGE_BAND[0] or r > NEES_BAND[1]  # the truth falls outside more often than claimed
    wide = c > COVERAGE_BAND[1] or r < NEES_BAND[0]
    if over and wide:  # e.g. heavy tails: most errors well inside, a few far out
        return "mixed"
    if over or wide:
        return "over-confident" if over else "too wide"
    if calibration_error is not None and calibration_error > CALIBRATION_ERROR_MAX:
        return "mis-shaped"
    return "consistent"


def consistency_row(
    summary: Mapping[str, Any],
    dx: int,
    curve: Sequence[float] | None = None,
    curve_all: Sequence[float] | None = None,
) -> dict[str, Any]:
    """The consistency figures of one method from its metric summary (``nees_median``, ``nees``,
    ``coverage95``: numbers, (median, iqr) pairs or Stats) and optionally its reliability curve
    (kept trajectories: ``coverage50``, ``coverage90``, ``coverage99`` are read off it) and the curve
    over every trajectory (``curve_all``: ``coverage95_all``, the coverage a user gets)."""

    def med(key: str) -> float | None:
        v = summary.get(key)
        if v is None:
            return None
        if hasattr(v, "median"):
            return None if not getattr(v, "applies", True) else float(v.median)
        if isinstance(v, (tuple, list)):
            return float(v[0])
        return float(v)

    nm, nmean, c95 = med("nees_median"), med("nees"), med("coverage95")
    row = {
        "nees_median_per_dim": None if nm is None else nm / dx,
        "nees_mean_per_dim": None if nmean is None else nmean / dx,
        "coverage95": c95,
        "calibration_error": None if curve is None else calibration_error(curve),
    }
    if curve is not None:
        for level in (0.5, 0.9, 0.99):
            row[f"coverage{round(level * 100)}"] = float(curve[RELIABILITY_LEVELS.index(level)])
    if curve_all is not None:
        row["coverage95_all"] = float(curve_all[RELIABILITY_LEVELS.index(0.95)])
        every = med("nees_median_all")
        row["nees_median_all_per_dim"] = None if every is None else every / dx
    row["verdict"] = verdict(row["nees_mean_per_dim"], c95, row["calibration_error"])
    return row


def format_consistency_table(rows: Mapping[str, Mapping[str, Any]], fmt: str = "markdown") -> str:
    """The consistency table beside the accuracy table: NEES med./dx, NEES mean/dx, 95 % coverage,
    calibration error (mean |coverage(q) - q| over :data:`RELIABILITY_LEVELS`), where the rows have
    them the 50/90/99 % coverage and the 95 % coverage over every trajectory, and the verdict, one
    row per method of ``rows`` ({method: :func:`consistency_row`})."""
    header = ["Method", "NEES med./dx", "NEES mean/dx", "95% cov.", "Cal. err.", "Verdict"]
    levels = any("coverage50" in r for r in rows.values())  # the 50/90/99 % coverage, when curves are known
    every = any("coverage95_all" in r for r in rows.values())  # 95 % over every trajectory, outliers included

    def num(v: float | None, dec: int) -> str:
        if v is None:
            return "—"
        if math.isnan(v):
            return "N/A"
        if math.isinf(v):
            return "inf"
        return f"{v:.{dec}g}" if (abs(v) >= 1e4 or (v != 0 and abs(v) < 1e-2)) else f"{v:.{dec}f}"

    body = [
        [
            m,
            num(r.get("nees_median_per_dim"), 2),
            num(r.get("nees_mean_per_dim"), 2),
            num(r.get("coverage95"), 3),
            num(r.get("calibration_error"), 3),
            str(r.get("verdict", "—")),
        ]
        for m, r in rows.items()
    ]
    if levels:
        header.insert(-1, "50/90/99% cov.")
        for b, r in zip(body, rows.values()):
            known = r.get("coverage50") is not None
            b.insert(-1, "/".join(num(r.get(f"coverage{q}"), 3) for q in (50, 90, 99)) if known else "—")
    if every:
        header[-1:-1] = ["NEES med./dx (all)", "95% cov. (all)"]
        for b, r in zip(body, rows.values()):
            b[-1:-1] = [num(r.get("nees_median_all_per_dim"), 2), num(r.get("coverage95_all"), 3)]
    last = len(header) - 1
    if fmt == "markdown":
        lines = ["| " + " | ".join(header) + " |", "|---|" + "---:|" * (last - 1) + "---|"]
        return "\n".join(lines + ["| " + " | ".join(b) + " |" for b in body]) + "\n"
    if fmt != "text":
        raise ConsistencyError(f"fmt must be 'markdown' or 'text', got {fmt!r}")
    widths = [max(len(r[i]) for r in [header] + body) for i in range(len(header))]
    return (
        "\n".join(
            "  ".join(c.ljust(w) if i in (0, last) else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths))).rstrip()
            for r in [header] + body
        )
        + "\n"
    )
