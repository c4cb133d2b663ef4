"""The metrics of :func:`~neural_estimator.metrics.compute_metrics`, fed a few trajectories at a time.

:class:`BlockScorer` takes a run's trajectories block by block and keeps only what the paper's
metrics need per trajectory (O(N) values: the per-component MSE ``Md[n, d]``, the sum of ``|e|``,
the NEES sums and coverage counts, the every-step ``M_n``) and per step (nothing: the RMSE-time
curve is summed from disk). The outlier rule needs every ``M_n`` before it can say which
trajectories are kept, so what a metric needs per cell goes to disk
(:class:`~neural_estimator.metrics.spill.RowSpill`): per trajectory, sum_d e_{n,t,d}^2 at every
step (the RMSE-time curve), |e_{n,t,d}| (MedAE) and eps_{n,t} (the NEES medians). At the end those
are read back restricted to the kept trajectories, and the medians selected exactly
(:func:`~neural_estimator.metrics.spill.exact_median`). Resident memory is one block plus O(N + T):
it does not grow with the cells of the run.

Every figure equals compute_metrics' on the whole arrays, up to the order of floating-point sums
(sums by trajectory here, pairwise over the array there: a relative difference of order 1e-15;
test_streaming_metrics.py holds them to 1e-12). The spread s_d is combined from each block's mean
and sum of squared deviations (Chan et al.'s pairwise update):
n = n_a + n_b, delta = mean_b - mean_a, mean = mean_a + delta n_b / n,
M2 = M2_a + M2_b + delta^2 n_a n_b / n, s_d = sqrt(M2 / n).
"""

from __future__ import annotations

import math
import tempfile
from collections.abc import Sequence

import numpy as np

from neural_estimator.metrics import definitions as D
from neural_estimator.metrics.checks import MetricsError, check_pair
from neural_estimator.metrics.outliers import OUTLIER_Z, outlier_mask
from neural_estimator.metrics.paired import TrajectoryErrors
from neural_estimator.metrics.spill import RowSpill, exact_median

BLOCK_CELLS = 1 << 16  # (trajectory, step) cells per block: bounds the per-block temporaries


class BlockScorer:
    """One method's metrics over a run given in blocks of whole trajectories (module docstring).

    Args:
        horizon: steps per trajectory (T_total), warm-up included.
        dx: state components.
        angle_states: components that are angles (errors wrapped to (-pi, pi]).
        warmup: leading steps not scored, 0 <= warmup < horizon (as compute_metrics).
        covariance: True when every block comes with its covariances (NEES and coverage).
        spread: the NRMSE normaliser; default the spread of the scored ground truth.
        threshold: the outlier z-score threshold.
        spill_dir: where the temporary files go (default: the system's temporary directory).
    """

    def __init__(
        self,
        horizon: int,
        dx: int,
        angle_states: Sequence[int] = (),
        *,
        warmup: int = 0,
        covariance: bool = False,
        spread: np.ndarray | float | None = None,
        threshold: float = OUTLIER_Z,
        spill_dir: str | None = None,
    ) -> None:
        if isinstance(warmup, bool) or int(warmup) != warmup or not 0 <= int(warmup) < horizon:
            raise MetricsError(f"warmup must be an integer in [0, {horizon}) for {horizon} timesteps, got {warmup!r}")
        self.horizon, self.dx, self.warmup = int(horizon), int(dx), int(warmup)
        self.steps = self.horizon - self.warmup  # scored steps T
        self.angles, self.covariance, self.threshold = tuple(angle_states), covariance, threshold
        self.spread = spread
        self._md: list[np.ndarray] = []  # (B, dx) per-trajectory, per-component MSE
        self._div: list[np.ndarray] = []  # (B,) diverged (non-finite M_n, or flagged)
        self._given: list[np.ndarray] = []  # (B,) the caller's divergence flags (for the every-step RMSE)
        self._every: list[np.ndarray] = []  # (B,) M_n over every step (warm-up > 0 only)
        self._abs_sum: list[np.ndarray] = []  # (B,) sum_{t, d} |e|
        self._nees: list[np.ndarray] = []  # (B, 3 + levels) usable count, finite sum, 95 % count, level counts
        self._count, self._mean, self._m2 = 0, np.zeros(self.dx), np.zeros(self.dx)
        self._sq = RowSpill(self.steps, spill_dir)  # sum_d e^2 per step
        self._abs = RowSpill(self.steps * self.dx, spill_dir)  # |e|
        self._eps = RowSpill(self.steps, spill_dir) if covariance else None  # NEES
        self._bounds: np.ndarray | None = None

    def add(
        self,
        x_true: np.ndarray,
        x_hat: np.ndarray,
        P_hat: np.ndarray | None = None,
        diverged: np.ndarray | None = None,
    ) -> None:
        """Score a block: ``x_true``, ``x_hat`` (B, horizon, dx), ``P_hat`` (B, horizon, dx, dx)
        when the scorer takes covariances, ``diverged`` (B,) extra divergence flags."""
        x_true, x_hat = check_pair(x_true, x_hat)
        b, t, dx = x_true.shape
        if (t, dx) != (self.horizon, self.dx):
            raise MetricsError(f"a block must be (B, {self.horizon}, {self.dx}), got {x_true.shape}")
        if (P_hat is not None) != self.covariance:
            raise MetricsError("every block must come with covariances" if self.covariance else "no covariances here")
        given = np.zeros(b, dtype=bool) if diverged is None else np.asarray(diverged, dtype=bool)
        if given.shape != (b,):
            raise MetricsError(f"diverged must be ({b},), got {given.shape}")
        flags = given
        if self.warmup:
            self._every.append(_trajectory_mse(D.errors(x_true, x_hat, self.angles)))
            flags = given | D.diverged_mask(x_hat[:, : self.warmup])  # diverged in the warm-up stays diverged
            x_true, x_hat = x_true[:, self.warmup :], x_hat[:, self.warmup :]
        if not np.isfinite(x_true).all():
            raise MetricsError("x_true holds non-finite values; ground truth must be finite")
        self._add_spread(x_true)
        e = D.errors(x_true, x_hat, self.angles)  # (B, T, dx)
        with np.errstate(over="ignore", invalid="ignore"):
            sq = e * e
            md = sq.mean(axis=1)  # (B, dx)
            self._sq.append(sq.sum(axis=2))
            abs_e = np.abs(e)
            self._abs_sum.append(abs_e.sum(axis=(1, 2)))
        self._abs.append(abs_e.reshape(b, -1))
        self._md.append(md)
        self._div.append(D.diverged_mask(x_hat) | ~np.isfinite(md.mean(axis=1)) | flags)
        self._given.append(given)
        if self.covariance:
            P_hat = np.asarray(P_hat, dtype=np.float64)
            if P_hat.shape != (b, self.horizon, dx, dx):
                raise MetricsError(f"P_hat must be {(b, self.horizon, dx, dx)}, got {P_hat.shape}")
            eps = D.nees(e, P_hat[:, self.warmup :])  # (B, T)
            self._eps.append(eps)
            self._nees.append(self._nees_counts(eps))

    def _add_spread(self, x: np.ndarray) -> None:
        """Merge the block's per-component mean and sum of squared deviations (module docstring)."""
        n_b = x.shape[0] * x.shape[1]
        mean_b = x.mean(axis=(0, 1))
        m2_b = ((x - mean_b) ** 2).sum(axis=(0, 1))
        n = self._count + n_b
        delta = mean_b - self._mean
        self._m2 = self._m2 + m2_b + delta * delta * (self._count * n_b / n)
        self._mean = self._mean + delta * (n_b / n)
        self._count = n

    def _nees_counts(self, eps: np.ndarray) -> np.ndarray:
        """(B, 3 + levels) per trajectory: usable steps, the sum of their NEES, steps within the
        95 % bound, steps within each reliability level's bound (NaN: not covered)."""
        from scipy.special import chdtri

        from neural_estimator.metrics.consistency import RELIABILITY_LEVELS, chi2_quantile

        if self._bounds is None:
            self._bounds = np.concatenate(
                [[chdtri(self.dx, 1.0 - D.COVERAGE_LEVEL)], chi2_quantile(self.dx, np.asarray(RELIABILITY_LEVELS))]
            )
        usable = np.isfinite(eps)
        with np.errstate(invalid="ignore"):
            within = [(eps <= bound).sum(axis=1) for bound in self._bounds]
        return np.column_stack([usable.sum(axis=1), np.where(usable, eps, 0.0).sum(axis=1), *within])

    def report(self) -> D.MetricReport:
        """The :class:`~neural_estimator.metrics.MetricReport` of every block added."""
        if not self._md:
            raise MetricsError("no trajectory to score")
        n, t, dx = sum(len(m) for m in self._md), self.steps, self.dx
        md = np.concatenate(self._md)  # (N, dx)
        m = md.mean(axis=1)  # (N,) the paper's M_n
        div = np.concatenate(self._div)
        s = self._resolved_spread()
        out = outlier_mask(np.where(div, np.inf, m), self.threshold)
        kept = ~out
        self.kept = kept
        every_step = self._every_step_rmse() if self.warmup else None
        common = D.report_fields(m, md, s, div, out, self.warmup, every_step)
        if not kept.any():
            return D.all_diverged_report(t, dx, bool(self.covariance), common)
        k = int(kept.sum())
        msd = md[kept].mean(axis=0)  # (dx,)
        rmse_t = np.sqrt(self._sq.sum_rows(kept) / (k * dx))  # (T,)
        cov = dict.fromkeys(D.COVARIANCE_METRICS) if not self.covariance else self._covariance(kept, n * t, k * t)
        return D.MetricReport(
            rmse=float(np.sqrt(msd.mean())),
            nrmse_spread=float(np.sqrt(np.mean(msd / s**2))),
            mae=float(np.concatenate(self._abs_sum)[kept].sum() / (k * t * dx)),
            medae=exact_median(self._abs, kept),
            auc=D.auc(rmse_t),
            drift_ratio=D.drift_ratio(rmse_t),
            outlier_ratio=int(out.sum()) / n,
            rmse_t=rmse_t,
            rmse_components=tuple(float(v) for v in np.sqrt(msd)),
            **cov,
            **common,
        )

    def _covariance(self, kept: np.ndarray, cells_all: int, cells_kept: int) -> dict:
        counts = np.concatenate(self._nees)  # (N, 3 + levels)
        ck = counts[kept].sum(axis=0)
        call = counts.sum(axis=0)
        return dict(
            nees_median=exact_median(self._eps, kept),
            nees=float(ck[1] / ck[0]) if ck[0] else math.inf,
            coverage95=float(ck[2] / cells_kept),
            cov_degenerate=float(1.0 - ck[0] / cells_kept),
            coverage_curve=tuple(float(c / cells_kept) for c in ck[3:]),
            coverage_curve_all=tuple(float(c / cells_all) for c in call[3:]),
            nees_median_all=exact_median(self._eps, None, nan_as_inf=True),
        )

    def _every_step_rmse(self) -> float:
        """compute_metrics' ``rmse_every_step``: :func:`~neural_estimator.metrics.kept_rmse` of
        the errors over every step, from the stored every-step M_n."""
        m = np.concatenate(self._every)
        div = ~np.isfinite(m) | np.concatenate(self._given)
        kept = ~outlier_mask(np.where(div, np.inf, m), self.threshold)
        return float(np.sqrt(m[kept].mean())) if kept.any() else math.inf

    def _resolved_spread(self) -> np.ndarray:
        if self.spread is not None:
            return D._resolve_spread(np.zeros((1, 1, self.dx)), self.spread)
        s = np.sqrt(self._m2 / self._count)
        bad = ~(np.isfinite(s) & (s > 0))
        if bad.any():
            raise MetricsError(
                "NRMSE spread must be positive and finite; components "
                f"{np.flatnonzero(bad).tolist()} of the true state (pass spread= explicitly)"
            )
        return s

    def trajectory_errors(self) -> TrajectoryErrors:
        """The per-trajectory errors of the paired statistics (as
        :func:`~neural_estimator.metrics.paired.trajectory_errors`), after :meth:`report`."""
        return TrajectoryErrors(np.concatenate(self._md), self.kept.copy())

    def close(self) -> None:
        for spill in (self._sq, self._abs, self._eps):
            if spill is not None:
                spill.close()

    def __enter__(self) -> "BlockScorer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _trajectory_mse(e: np.ndarray) -> np.ndarray:
    with np.errstate(over="ignore", invalid="ignore"):
        return np.mean(e * e, axis=(1, 2))


def block_trajectories(horizon: int, dx: int) -> int:
    """Trajectories per block so that a block holds about :data:`BLOCK_CELLS` cells."""
    return max(1, BLOCK_CELLS // max(1, horizon))


def score_in_blocks(
    x_true: np.ndarray,
    x_hat: np.ndarray,
    angle_states: Sequence[int] = (),
    P_hat: np.ndarray | None = None,
    warmup: int = 0,
    spill_dir: str | None = None,
) -> tuple[D.MetricReport, TrajectoryErrors]:
    """(report, per-trajectory errors) of arrays held in memory (or memory-mapped), scored block by
    block: compute_metrics' figures without its (N, T, dx) temporaries."""
    x_true, x_hat = np.asarray(x_true), np.asarray(x_hat)
    if x_true.ndim != 3:
        raise MetricsError(f"x_true must be (N, T, dx), got shape {x_true.shape}")
    n, t, dx = x_true.shape
    step = block_trajectories(t, dx)
    try:
        with BlockScorer(t, dx, angle_states, warmup=warmup, covariance=P_hat is not None, spill_dir=spill_dir) as sc:
            for a in range(0, n, step):
                sc.add(x_true[a : a + step], x_hat[a : a + step], None if P_hat is None else P_hat[a : a + step])
            return sc.report(), sc.trajectory_errors()
    except OSError as exc:  # no room for the temporary files: one line
        where = spill_dir or tempfile.gettempdir()
        raise MetricsError(
            f"scoring needs temporary files in {where} (set TMPDIR to another directory): {exc.strerror or exc}"
        ) from None
