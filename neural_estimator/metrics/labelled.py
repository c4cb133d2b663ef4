"""The metrics on the labelled steps only: recorded data whose ground truth has gaps.

A recording's ground truth may cover only part of the time (a robot outside the motion-capture
volume); its dataset's mask m_{n,t} (True where x holds ground truth,
:mod:`neural_estimator.robot.dataset`) says which steps can be scored. With e the errors (angles
wrapped), S_n = {t : m_{n,t}} the scored steps of trajectory n (after the warm-up), |S_n| their
number, and K the kept trajectories (the outlier rule on M_n; diverged ones always flagged):

    M_{n,d}   = (1 / |S_n|) sum_{t in S_n} e_{n,t,d}^2                 (a trajectory's MSE on its labels)
    M_n       = (1 / dx) sum_d M_{n,d}
    RMSE      = sqrt( (1 / |K|) sum_{n in K} M_n )     (the mean trajectory MSE, as for full labels)
    Full RMSE = sqrt( (1 / N) sum_n M_n ); inf if any diverged
    NRMSE     = (1 / N) sum_n sqrt( mean_d M_{n,d} / s_d^2 ),  s_d the spread of the labelled truth
    MAE, MedAE over { |e_{n,t,d}| : n in K, t in S_n }
    RMSE_t    = sqrt( mean { e_{n,t,d}^2 : n in K with m_{n,t}, d } ),  NaN at a step no kept trajectory labels
    AUC       = the trapezoid rule over consecutive steps that both have an RMSE_t
    drift     = mean of the defined RMSE_t in the last quarter / the same in the first quarter

With every step labelled these are :func:`~neural_estimator.metrics.definitions.compute_metrics`'s
definitions; :func:`compute_labelled_metrics` (what every scorer of recorded data calls) only
comes here when some step is unlabelled, so a fully labelled set is scored exactly as before.
:func:`~neural_estimator.metrics.paired.trajectory_errors` with the same mask gives the M_{n,d}
the confidence intervals resample. A trajectory with no labelled step after the warm-up is not
scored (and not counted in N). Divergence is judged on every step, labelled or not: an estimator
that blows up in a gap diverged.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

import neural_estimator.metrics.definitions as D


def compute_labelled_metrics(
    x_true: np.ndarray,
    x_hat: np.ndarray,
    angle_states: Sequence[int] = (),
    labelled: np.ndarray | None = None,
    **kwargs,
) -> D.MetricReport:
    """:func:`~neural_estimator.metrics.definitions.compute_metrics` (its keyword arguments) where
    ``labelled`` (N, T) is None or all True, else :func:`labelled_metrics` (no ``spread`` there)."""
    if labelled is None or bool(np.all(labelled)):
        return D.compute_metrics(x_true, x_hat, angle_states, **kwargs)
    if kwargs.pop("spread", None) is not None:
        raise D.MetricsError("labelled steps: the spread is that of the labelled truth; pass no spread")
    return labelled_metrics(x_true, x_hat, labelled, angle_states, **kwargs)


def labelled_metrics(
    x_true: np.ndarray,
    x_hat: np.ndarray,
    labelled: np.ndarray,
    angle_states: Sequence[int] = (),
    P_hat: np.ndarray | None = None,
    diverged: np.ndarray | None = None,
    threshold: float = D.OUTLIER_Z,
    warmup: int = 0,
    nees_values: np.ndarray | None = None,
) -> D.MetricReport:
    """The :class:`~neural_estimator.metrics.definitions.MetricReport` of the labelled steps (see the
    module docstring); ``scored_steps`` and ``unlabelled_steps`` count the (n, t) after the warm-up.

    Raises:
        MetricsError: shapes that disagree, a warm-up out of range, or no labelled step to score.
    """
    x_true, x_hat = D.check_pair(x_true, x_hat)
    n, t, dx = x_true.shape
    m = np.asarray(labelled, dtype=bool)
    if m.shape != (n, t):
        raise D.MetricsError(f"labelled must be ({n}, {t}), got {m.shape}")
    if isinstance(warmup, bool) or int(warmup) != warmup or not 0 <= int(warmup) < t:
        raise D.MetricsError(f"warmup must be an integer in [0, {t}) for {t} timesteps, got {warmup!r}")
    warmup = int(warmup)
    div = D.diverged_mask(x_hat)  # every step, labelled or not
    if diverged is not None:
        div = div | np.asarray(diverged, dtype=bool)
    e_all = D.errors(x_true, x_hat, angle_states)
    every_step = _kept_rmse(e_all, m, div, threshold)
    e, m = e_all[:, warmup:], m[:, warmup:]
    x_true = x_true[:, warmup:]
    scored = m.any(axis=1)
    if not scored.any():
        raise D.MetricsError("no labelled step after the warm-up: nothing to score")
    if not np.isfinite(x_true[m]).all():
        raise D.MetricsError("x_true holds non-finite values at labelled steps; ground truth must be finite")
    e, m, div, keep_idx = e[scored], m[scored], div[scored], np.flatnonzero(scored)
    s = x_true[scored][m].std(axis=0)  # (dx,) spread of the labelled truth
    if not np.all(s > 0):
        raise D.MetricsError(f"the labelled ground truth has a zero spread in some component ({s.tolist()})")
    count = m.sum(axis=1)  # (N',) |S_n|
    with np.errstate(over="ignore", invalid="ignore"):
        sq = np.where(m[..., None], e * e, 0.0)  # unlabelled steps contribute nothing (not even NaN)
        Md = sq.sum(axis=1) / count[:, None]  # (N', dx)
    M = Md.mean(axis=1)
    div = div | ~np.isfinite(M)
    out = D.outlier_mask(np.where(div, np.inf, M), threshold)
    kept = ~out
    n_s, n_div = int(scored.sum()), int(div.sum())
    common = dict(
        full_rmse=math.inf if n_div else float(np.sqrt(M.mean())),
        nrmse=math.inf if n_div else D.trajectory_mean_nrmse(Md, s),
        diverged_ratio=n_div / n_s,
        n_trajectories=n_s,
        n_outliers=int(out.sum()),
        n_diverged=n_div,
        all_diverged=n_div == n_s,
        spread=s,
        outlier_idx=keep_idx[out],
        diverged_idx=keep_idx[div],
        warmup=warmup,
        rmse_every_step=every_step,
        scored_steps=int(m.sum()),
        unlabelled_steps=int((~m).sum()),
    )
    if not kept.any():
        inf = math.inf
        return D.MetricReport(
            rmse=inf, nrmse_spread=inf, mae=inf, medae=inf, auc=inf, drift_ratio=math.nan,
            outlier_ratio=math.nan, rmse_t=np.full(t - warmup, np.inf), rmse_components=(inf,) * dx, **common,
        )  # fmt: skip
    sq_k, m_k = sq[kept], m[kept]
    msd = Md[kept].mean(axis=0)  # (dx,) MSE per component, the mean over kept trajectories
    abs_e = np.abs(e[kept][m_k])  # (labelled kept steps, dx)
    per_t = m_k.sum(axis=0)  # kept trajectories labelled at each step
    with np.errstate(invalid="ignore", divide="ignore"):
        rmse_t = np.where(per_t > 0, np.sqrt(sq_k.sum(axis=(0, 2)) / (np.maximum(per_t, 1) * dx)), np.nan)
    cov = _labelled_covariance(e_all, P_hat, nees_values, warmup, scored, kept, m_k)
    return D.MetricReport(
        rmse=float(np.sqrt(msd.mean())),
        nrmse_spread=float(np.sqrt(np.mean(msd / s**2))),
        mae=float(abs_e.mean()),
        medae=float(np.median(abs_e)),
        auc=gapped_auc(rmse_t),
        drift_ratio=gapped_drift(rmse_t),
        outlier_ratio=int(out.sum()) / n_s,
        rmse_t=rmse_t,
        rmse_components=tuple(float(v) for v in np.sqrt(msd)),
        **cov,
        **common,
    )


def _labelled_covariance(e_all, P_hat, nees_values, warmup: int, scored, kept, m_k) -> dict:
    """The covariance metrics over the labelled steps of the kept trajectories after the warm-up, from
    ``P_hat`` (N, T, dx, dx) or precomputed ``nees_values`` (N, T); {} without either."""
    n, t, dx = e_all.shape
    if P_hat is not None:
        P = np.asarray(P_hat, dtype=np.float64)
        if P.shape != (n, t, dx, dx):
            raise D.MetricsError(f"P_hat must be {(n, t, dx, dx)}, got {P.shape}")
        nees_values = D.nees(e_all, P)
    if nees_values is None:
        return {}
    eps = np.asarray(nees_values, dtype=np.float64)
    if eps.shape != (n, t):
        raise D.MetricsError(f"nees_values must be {(n, t)}, got {eps.shape}")
    return D.covariance_metrics(eps[:, warmup:][scored][kept][m_k][None, :], dx)  # labelled kept steps


def _kept_rmse(e: np.ndarray, m: np.ndarray, div: np.ndarray, threshold: float) -> float:
    """sqrt of the mean M_n (labelled steps) over the trajectories with a label that the outlier rule
    keeps, every step counted, the warm-up included (``rmse_every_step``); inf when none is kept."""
    count = m.sum(axis=1)
    with np.errstate(over="ignore", invalid="ignore"):
        sq = np.where(m[..., None], e * e, 0.0)
        M = sq.sum(axis=(1, 2)) / np.maximum(count, 1) / e.shape[2]
    M, bad = M[count > 0], (div | ~np.isfinite(M))[count > 0]
    kept = ~D.outlier_mask(np.where(bad, np.inf, M), threshold)
    return float(np.sqrt(M[kept].mean())) if kept.any() else math.inf


def gapped_auc(rmse_t: np.ndarray) -> float:
    """Trapezoid area under an RMSE-time curve with NaN gaps: the pairs of consecutive defined steps."""
    both = np.isfinite(rmse_t[1:]) & np.isfinite(rmse_t[:-1])
    return float(np.sum(0.5 * (rmse_t[1:] + rmse_t[:-1])[both]))


def gapped_drift(rmse_t: np.ndarray) -> float:
    """Mean defined RMSE_t of the last quarter over that of the first (NaN when a quarter has none)."""
    q = max(1, rmse_t.size // 4)
    head, tail = rmse_t[:q], rmse_t[-q:]
    head, tail = head[np.isfinite(head)], tail[np.isfinite(tail)]
    if not head.size or not tail.size:
        return math.nan
    with np.errstate(divide="ignore", invalid="ignore"):
        return float(np.float64(tail.mean()) / np.float64(head.mean()))


def scored_line(reports) -> str:
    """The line under a table of ``reports`` (MetricReports) when the ground truth was partial:
    how many steps were scored and how many had no ground truth; "" when every step was labelled."""
    for r in reports:
        if getattr(r, "scored_steps", None) is not None:
            return (
                f"partial ground truth: {r.scored_steps} labelled steps scored, "
                f"{r.unlabelled_steps} unlabelled steps not scored (no ground truth)"
            )
    return ""
