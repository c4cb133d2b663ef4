"""The paper's outlier rule: a trajectory is an outlier when the robust z-score of its log MSE is
above 6 (paper: "z_n = |u_n - median| / (1.4826 MAD)", "A trajectory is an outlier if z_n > 6").
Diverged trajectories (non-finite MSE) are always outliers."""

from __future__ import annotations

import numpy as np

from neural_estimator.metrics.checks import MetricsError

OUTLIER_Z = 6.0  # the paper's threshold: "A trajectory is an outlier if z_n > 6."
MAD_SCALE = 1.4826  # paper: z_n = |u_n - median| / (1.4826 MAD); 1/Phi^-1(3/4), MAD -> sigma
MEANAD_SCALE = 1.253314  # sqrt(pi/2): mean absolute deviation -> sigma (fallback when MAD = 0)
LOG_SCALE_FLOOR = 1e-9  # robust scales below this (log space) are round-off, not spread
_TINY = np.finfo(np.float64).tiny  # floor of M_n before the log: log(0) would be -inf


def robust_zscores(M: np.ndarray) -> np.ndarray:
    """The paper's robust z-score of each trajectory's log-MSE.

    Paper, Section "Evaluation Metrics":

        "To prevent rare catastrophic failures from dominating aggregate metrics, we detect
        trajectory-level outliers on log-MSE values using a robust z-score based on the median
        absolute deviation (MAD). Let M_n be the trajectory-level MSE for trajectory n, and define

            u_n = log M_n,
            u~  = median{u_1, ..., u_N},
            MAD = median{|u_1 - u~|, ..., |u_N - u~|}.

        The robust z-score is

            z_n = |u_n - u~| / (1.4826 MAD)."

    Choices where the paper is silent:

    - Non-finite M_n (diverged trajectories) get z_n = inf and are left out of the median and the
      MAD, which are taken over the finite M_n only. A diverged trajectory has no log-MSE to rank,
      and letting it in would move the median (the paper's EnKF rows are "N/A" for this reason).
    - M_n = 0 (an exact estimate) is floored at the smallest positive float before the log, so u_n
      stays finite; under the two-sided rule a perfect trajectory among imperfect ones is an
      outlier on the low side, as the formula says.
    - MAD = 0 (more than half of the u_n equal): the modified z-score's standard fallback
      (Iglewicz & Hoaglin 1993) replaces 1.4826 MAD by 1.253314 MeanAD, with
      MeanAD = mean{|u_n - u~|} and 1.253314 = sqrt(pi / 2) the factor that makes MeanAD estimate
      a normal standard deviation, as 1.4826 does for the MAD. If MeanAD = 0 as well, all finite
      u_n are equal and every finite z_n is 0: there is no spread, so nothing is outlying.
    - The robust scale is floored at LOG_SCALE_FLOOR = 1e-9 in log space (a relative MSE
      difference of one part in 10^9). Without the floor, trajectories whose MSEs agree up to
      floating-point round-off (identical errors computed as (x + e) - x) have a MAD of ~1e-16 and
      round-off alone would be flagged as outliers.

    Args:
        M: (N,) trajectory-level MSE.

    Returns:
        (N,) z_n >= 0, inf for non-finite M_n.
    """
    M = np.asarray(M, dtype=np.float64)
    if M.ndim != 1:
        raise MetricsError(f"M must be (N,), got shape {M.shape}")
    finite = np.isfinite(M)
    z = np.full(M.shape, np.inf)
    if not finite.any():
        return z
    u = np.log(np.maximum(M[finite], _TINY))  # (N_finite,)
    dev = np.abs(u - np.median(u))
    mad = np.median(dev)
    scale = MAD_SCALE * mad if mad > LOG_SCALE_FLOOR else MEANAD_SCALE * dev.mean()
    z[finite] = dev / scale if scale > LOG_SCALE_FLOOR else 0.0
    return z


def outlier_mask(M: np.ndarray, threshold: float = OUTLIER_Z) -> np.ndarray:
    """(N,) True for the paper's trajectory-level outliers.

    Paper: "A trajectory is an outlier if z_n > 6. We report the outlier ratio over all
    trajectories. Main RMSE and NRMSE exclude detected outliers, while full metrics with outlier
    statistics are reported in the Appendix."

    z_n is :func:`robust_zscores` (u_n = log M_n, median, MAD, z_n = |u_n - u~| / (1.4826 MAD)).
    Non-finite M_n (diverged trajectories) are always flagged; see :func:`robust_zscores` for
    MAD = 0.

    Args:
        M: (N,) trajectory-level MSE.
        threshold: the z-score above which a trajectory is an outlier (paper: 6).
    """
    return robust_zscores(M) > threshold


# ---- curve summaries ---------------------------------------------------------------------------------
