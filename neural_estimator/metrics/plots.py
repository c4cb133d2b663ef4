"""Figures: the RMSE-over-time curves of the paper's appendix (median with an IQR band)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np


def new_figure(figsize: tuple[float, float] = (8, 4.5)):
    """A figure and its axes on matplotlib's file-only backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt.subplots(figsize=figsize, dpi=120)


def save_figure(fig, path: str | Path) -> Path:
    """Lay out, write ``path`` (PNG; its folder made) and free the figure."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


def plot_rmse_over_time(
    curves: Mapping[str, Sequence[np.ndarray]],
    path: str | Path,
    title: str = "",
    dt: float | None = None,
    logy: bool = True,
    first_step: int = 0,
) -> Path:
    """Write a PNG of RMSE_t per method: the median over runs, with the interquartile range shaded.

    Args:
        curves: {method: [rmse_t (T,) for each run]} (one run gives a plain line).
        path: output PNG.
        title: figure title (e.g. the scenario).
        dt: sampling period; when given the x axis is time in seconds instead of steps.
        logy: logarithmic RMSE axis (methods differ by orders of magnitude in some scenarios).
        first_step: the step of each curve's first value (the unscored warm-up before it).
    """
    fig, ax = new_figure((8, 4.5))
    for method, runs in curves.items():
        R = np.asarray([np.asarray(r, dtype=float) for r in runs])  # (runs, T)
        if R.size == 0:
            continue
        t = (first_step + np.arange(R.shape[1])) * (dt if dt else 1.0)
        with np.errstate(invalid="ignore"):
            med = np.nanmedian(R, axis=0)
            lo, hi = np.nanpercentile(R, 25, axis=0), np.nanpercentile(R, 75, axis=0)
        (line,) = ax.plot(t, med, label=method, lw=1.4)
        if R.shape[0] > 1:
            ax.fill_between(t, lo, hi, color=line.get_color(), alpha=0.2, lw=0)
    ax.set_xlabel("time [s]" if dt else "step")
    ax.set_ylabel("RMSE")
    if logy:
        ax.set_yscale("log")
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    ax.legend(ncol=2, fontsize=8)
    return save_figure(fig, path)


def plot_reliability(
    curves: Mapping[str, np.ndarray], levels: Sequence[float], path: str | Path, title: str = ""
) -> Path:
    """Write a PNG reliability diagram: for each method, the fraction of (trajectory, step) errors
    inside its covariance's chi-square region of level q, against q. A consistent covariance lies on
    the diagonal; below it the method is over-confident, above it too wide.

    Args:
        curves: {method: coverage at each of ``levels`` (the median over runs)}.
        levels: the nominal levels q (``neural_estimator.metrics.consistency.RELIABILITY_LEVELS``).
        path: output PNG.
        title: figure title (e.g. the scenario).
    """
    q = np.asarray(levels, dtype=float)
    fig, ax = new_figure((5.5, 5))
    ax.plot([0, 1], [0, 1], color="0.6", lw=1, ls="--", label="consistent")
    for method, cov in curves.items():
        ax.plot(q, np.asarray(cov, dtype=float), marker="o", ms=3, lw=1.2, label=method)
    ax.set(xlim=(0, 1), ylim=(0, 1), xlabel="nominal level q", ylabel="coverage", title=title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", ncol=2)
    return save_figure(fig, path)
