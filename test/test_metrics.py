"""Metrics against hand-computed answers on tiny crafted inputs (paper, "Evaluation Metrics")."""

import csv
import io
import json
import math
import warnings

import numpy as np
import pytest

from neural_estimator import metrics as M
from neural_estimator.metrics import (
    MAD_SCALE,
    MEANAD_SCALE,
    MetricReport,
    MetricsError,
    Stat,
    auc,
    compute_metrics,
    diverged_mask,
    drift_ratio,
    errors,
    format_table,
    median_iqr,
    nees,
    outlier_mask,
    rmse_over_time,
    robust_zscores,
    state_spread,
    summarize,
    to_json,
    trajectory_mse,
)

TOL = dict(rtol=1e-12, atol=1e-12)  # exact arithmetic up to round-off


def _from_errors(e, offset=0.0):
    """(x_true, x_hat) with x_hat - x_true = e exactly (offset keeps x_true non-constant)."""
    e = np.asarray(e, dtype=np.float64)
    x_true = offset + np.arange(e.size, dtype=np.float64).reshape(e.shape) % 4.0  # small integers
    return x_true, x_true + e


# The main crafted set: N=3, T=4, dx=1. Trajectory MSEs M = [1, 2, 11/4]; no outliers
# (u = [0, ln 2, ln 2.75], median ln 2, MAD = ln 1.375, largest z = ln 2 / (1.4826 ln 1.375) = 1.47).
E3 = np.array([[1.0, 1.0, 1.0, 1.0], [2.0, 0.0, -2.0, 0.0], [0.0, 1.0, 3.0, -1.0]])[..., None]  # (3, 4, 1)


# ---- errors, curves, per-trajectory quantities --------------------------------------------------------


def test_errors_wrap_angle_components_only():
    x_true = np.zeros((1, 3, 2))
    x_hat = np.array([[[2 * np.pi - 0.1, 2 * np.pi - 0.1], [np.pi, np.pi], [-np.pi, 3.0]]])
    e = errors(x_true, x_hat, angle_states=(0,))
    np.testing.assert_allclose(e[0, 0], [-0.1, 2 * np.pi - 0.1], **TOL)  # 2 pi - 0.1 counts as -0.1
    assert e[0, 1, 0] == pytest.approx(np.pi) and e[0, 2, 0] == pytest.approx(np.pi)  # (-pi, pi]
    assert e[0, 2, 1] == 3.0


def test_rmse_over_time_and_trajectory_mse_by_hand():
    e = np.array([[[1, 1], [2, 0], [0, 0]], [[1, 1], [0, 2], [3, 1]]], dtype=float)  # (2, 3, 2)
    # t0: (1+1+1+1)/4 = 1, t1: (4+0+0+4)/4 = 2, t2: (0+0+9+1)/4 = 2.5
    np.testing.assert_allclose(rmse_over_time(e), np.sqrt([1.0, 2.0, 2.5]), **TOL)
    np.testing.assert_allclose(rmse_over_time(e, mask=np.array([True, False])), [1.0, np.sqrt(2.0), 0.0], **TOL)
    assert np.isnan(rmse_over_time(e, mask=np.array([False, False]))).all()
    np.testing.assert_allclose(trajectory_mse(e), [6 / 6, 16 / 6], **TOL)


def test_diverged_mask():
    x = np.zeros((4, 3, 2))
    x[1, 2, 0] = np.nan
    x[3, 0, 1] = -np.inf
    np.testing.assert_array_equal(diverged_mask(x), [False, True, False, True])


def test_auc_trapezoid_unit_step():
    assert auc(np.array([1.0, 2.0, 3.0, 4.0])) == pytest.approx(1.5 + 2.5 + 3.5)
    assert auc(np.array([2.0, 0.0])) == pytest.approx(1.0)
    assert auc(np.array([5.0])) == 0.0  # a single point has no area


def test_drift_ratio_quarters():
    # T = 8: q = 2, (7 + 8)/2 / ((1 + 2)/2) = 5
    assert drift_ratio(np.arange(1.0, 9.0)) == pytest.approx(5.0)
    # T = 3: floor(3/4) = 0, so q = max(1, 0) = 1: last / first = 6 / 2
    assert drift_ratio(np.array([2.0, 5.0, 6.0])) == pytest.approx(3.0)
    # T = 9: q = 2 (the middle point is in neither quarter): (8 + 9)/(1 + 2)
    assert drift_ratio(np.arange(1.0, 10.0)) == pytest.approx(17 / 3)
    assert drift_ratio(np.array([4.0])) == 1.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert drift_ratio(np.array([0.0, 1.0])) == math.inf
        assert math.isnan(drift_ratio(np.array([0.0, 0.0])))


# ---- outlier rule -------------------------------------------------------------------------------------

# u sorted: -1 -1 0 0 0 1 1 A B; median 0; deviations 1 1 0 0 0 1 1 A B -> MAD = 1.
U_OUT = np.array([-1.0, -1.0, 0.0, 0.0, 0.0, 1.0, 1.0, 6.01 * MAD_SCALE, 5.99 * MAD_SCALE])


def test_outlier_rule_one_above_one_just_below_six():
    M = np.exp(U_OUT)
    z = robust_zscores(M)
    np.testing.assert_allclose(z, np.abs(U_OUT) / MAD_SCALE, rtol=1e-9)
    assert z[7] == pytest.approx(6.01) and z[8] == pytest.approx(5.99)
    np.testing.assert_array_equal(np.flatnonzero(outlier_mask(M)), [7])
    np.testing.assert_array_equal(np.flatnonzero(outlier_mask(M, threshold=5.9)), [7, 8])


def test_outlier_rule_through_compute_metrics():
    M = np.exp(U_OUT)  # trajectories with constant error sqrt(M_n) have trajectory MSE M_n
    e = np.broadcast_to(np.sqrt(M)[:, None, None], (9, 5, 2))
    r = compute_metrics(*_from_errors(e), spread=1.0)
    np.testing.assert_array_equal(r.outlier_idx, [7])
    assert r.n_outliers == 1 and r.outlier_ratio == pytest.approx(1 / 9) and r.n_diverged == 0
    kept = np.delete(M, 7)
    assert r.rmse == pytest.approx(np.sqrt(kept.mean()))
    assert r.full_rmse == pytest.approx(np.sqrt(M.mean()))
    assert r.full_rmse > r.rmse


def test_outlier_rule_mad_zero_falls_back_to_mean_absolute_deviation():
    # N = 10, nine equal u and one at a: MAD = 0, MeanAD = |a|/10, z = 10 / 1.253314 = 7.98 > 6
    u = np.r_[np.zeros(9), 2.0]
    z = robust_zscores(np.exp(u))
    assert z[-1] == pytest.approx(10 / MEANAD_SCALE) and np.all(z[:-1] == 0.0)
    np.testing.assert_array_equal(np.flatnonzero(outlier_mask(np.exp(u))), [9])
    # N = 6: z = 6 / 1.253314 = 4.79 <= 6, too few trajectories to call one extreme
    u6 = np.r_[np.zeros(5), 2.0]
    assert robust_zscores(np.exp(u6))[-1] == pytest.approx(6 / MEANAD_SCALE)
    assert not outlier_mask(np.exp(u6)).any()
    # all equal: no spread, nothing outlying
    assert not outlier_mask(np.full(5, 3.0)).any()


def test_outlier_rule_nonfinite_always_flagged_and_left_out_of_median():
    M = np.exp(U_OUT[:7])  # median 0, MAD 1 among the finite ones
    M_div = np.r_[M, np.inf, np.nan]
    z = robust_zscores(M_div)
    np.testing.assert_allclose(z[:7], np.abs(U_OUT[:7]) / MAD_SCALE, rtol=1e-9)  # unchanged by inf/NaN
    assert np.all(np.isinf(z[7:]))
    np.testing.assert_array_equal(np.flatnonzero(outlier_mask(M_div)), [7, 8])
    assert outlier_mask(np.array([np.nan, np.inf])).all()


# ---- compute_metrics ----------------------------------------------------------------------------------


def test_compute_metrics_by_hand():
    r = compute_metrics(*_from_errors(E3), spread=2.0)
    # squared errors per t: t0 (1,4,0), t1 (1,0,1), t2 (1,4,9), t3 (1,0,1)
    curve = np.sqrt([5 / 3, 2 / 3, 14 / 3, 2 / 3])
    np.testing.assert_allclose(r.rmse_t, curve, **TOL)
    assert r.rmse == pytest.approx(np.sqrt(23 / 12))  # (4 + 8 + 11) / 12
    assert r.full_rmse == pytest.approx(np.sqrt(23 / 12))
    # per-trajectory MSE 4/4, 8/4, 11/4: NRMSE is the mean of their roots over the spread 2
    assert r.nrmse == pytest.approx(np.mean(np.sqrt([1.0, 2.0, 2.75])) / 2.0)
    assert r.nrmse_spread == pytest.approx(np.sqrt(23 / 12) / 2.0)
    assert r.mae == pytest.approx(13 / 12)  # |e| sums 4 + 4 + 5
    assert r.medae == pytest.approx(1.0)  # sorted |e|: 0 0 0 1 1 1 | 1 1 1 2 2 3
    assert r.auc == pytest.approx(0.5 * curve[0] + curve[1] + curve[2] + 0.5 * curve[3])
    assert r.drift_ratio == pytest.approx(np.sqrt(2 / 5))  # T = 4, q = 1: RMSE_4 / RMSE_1
    assert r.outlier_ratio == 0.0 and r.diverged_ratio == 0.0 and not r.all_diverged
    assert r.n_trajectories == 3 and r.outlier_idx.size == 0 and r.diverged_idx.size == 0
    assert r.nees is None and r.coverage95 is None and not r.has_covariance
    scalars = r.scalars()
    assert tuple(scalars) == M.SCALAR_METRICS  # every key, always
    assert all(scalars[k] is None for k in M.COVARIANCE_METRICS)


def test_warmup_scores_the_later_steps_only():
    """compute_metrics(warmup=k) equals compute_metrics of the steps k.. (covariances too); a
    trajectory that diverged during the warm-up stays diverged."""
    rng = np.random.default_rng(4)
    x = rng.normal(size=(6, 30, 3))
    x_hat = x + rng.normal(scale=0.1, size=x.shape)
    x_hat[:, :10] += 5.0  # a large warm-up error, as a model whose loss skipped those steps has
    A = rng.normal(size=(6, 30, 3, 3))
    P = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(3)
    r = compute_metrics(x, x_hat, P_hat=P, warmup=10)
    ref = compute_metrics(x[:, 10:], x_hat[:, 10:], P_hat=P[:, 10:])
    for k in M.SCALAR_METRICS:
        assert getattr(r, k) == pytest.approx(getattr(ref, k)), k
    np.testing.assert_allclose(r.rmse_t, ref.rmse_t)
    assert r.warmup == 10 and ref.warmup == 0 and r.rmse_t.shape == (20,)
    assert compute_metrics(x, x_hat).rmse > 10 * r.rmse  # every step: the warm-up dominates
    x_hat[2, 3] = np.nan  # diverged in the warm-up: still diverged, left out
    d = compute_metrics(x, x_hat, warmup=10)
    assert d.n_diverged == 1 and list(d.diverged_idx) == [2] and d.full_rmse == math.inf
    for bad in (-1, 30, 2.5, True):
        with pytest.raises(MetricsError, match="warmup must be an integer in \\[0, 30\\)"):
            compute_metrics(x, x_hat, warmup=bad)


def test_evaluation_warmup_is_the_training_warmup():
    from neural_estimator.data.protocol import WARMUP_STEPS

    assert M.EVALUATION_WARMUP == WARMUP_STEPS == 10  # the paper: "The first 10 timesteps are ignored"


def test_compute_metrics_drift_on_growing_curve_t8():
    t = np.arange(1.0, 9.0)
    e = np.broadcast_to(t[None, :, None], (4, 8, 1))  # every trajectory has RMSE_t = t
    r = compute_metrics(*_from_errors(e), spread=1.0)
    np.testing.assert_allclose(r.rmse_t, t, **TOL)
    assert r.drift_ratio == pytest.approx(5.0)  # q = 2
    assert r.auc == pytest.approx(0.5 * 1 + (2 + 3 + 4 + 5 + 6 + 7) + 0.5 * 8)
    assert r.n_outliers == 0  # equal M_n: MAD = MeanAD = 0, nothing flagged


def test_angle_wrapping_in_metrics():
    x_true = np.zeros((3, 4, 2))
    x_true[..., 1] = np.arange(12.0).reshape(3, 4)
    x_hat = x_true.copy()
    x_hat[..., 0] += 2 * np.pi - 0.1  # angle error 2 pi - 0.1 is really -0.1
    wrapped = compute_metrics(x_true, x_hat, angle_states=(0,), spread=1.0)
    raw = compute_metrics(x_true, x_hat, spread=1.0)
    assert wrapped.rmse == pytest.approx(0.1 / np.sqrt(2))  # errors (-0.1, 0) in every step
    assert wrapped.mae == pytest.approx(0.05)
    assert raw.rmse == pytest.approx((2 * np.pi - 0.1) / np.sqrt(2))


def test_nrmse_with_known_spread():
    base = np.array([[1.0, -1.0], [-1.0, 1.0]])  # mean 0, population std 1
    x_true = np.stack([base, 3.0 * base], axis=-1)  # (2, 2, 2), spreads (1, 3)
    np.testing.assert_allclose(state_spread(x_true), [1.0, 3.0], **TOL)
    x_hat = x_true + np.array([0.5, 1.5])  # normalised errors (0.5, 0.5) everywhere
    r = compute_metrics(x_true, x_hat)
    assert r.nrmse == pytest.approx(0.5) and r.nrmse_spread == pytest.approx(0.5)
    assert r.rmse == pytest.approx(np.sqrt((0.25 + 2.25) / 2))
    np.testing.assert_allclose(r.spread, [1.0, 3.0], **TOL)
    assert compute_metrics(x_true, x_hat, spread=[0.5, 1.5]).nrmse == pytest.approx(1.0)
    with pytest.raises(MetricsError, match="spread"):
        compute_metrics(np.zeros((2, 3, 1)), np.ones((2, 3, 1)))  # constant truth, no spread given
    with pytest.raises(MetricsError, match="spread"):
        compute_metrics(x_true, x_hat, spread=[1.0, 0.0])


def test_diverged_trajectories_reported_excluded_no_crash():
    e = np.ones((5, 4, 2))
    e[2] = 2.0  # M = [1, ., 4, ., 1]
    x_true, x_hat = _from_errors(e)
    x_hat[1, 2, 0] = np.nan
    x_hat[3] = 1e200  # finite estimate whose squared error overflows: diverged too
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no RuntimeWarning from NaN, inf or overflow
        r = compute_metrics(x_true, x_hat, spread=1.0)
    np.testing.assert_array_equal(r.diverged_idx, [1, 3])
    np.testing.assert_array_equal(r.outlier_idx, [1, 3])  # diverged are always flagged
    assert r.n_diverged == 2 and r.diverged_ratio == pytest.approx(0.4) and r.outlier_ratio == pytest.approx(0.4)
    assert r.full_rmse == math.inf and not r.all_diverged
    # kept M = [1, 4, 1]: MAD = 0, z = 3 / 1.253314 < 6, all three kept
    assert r.rmse == pytest.approx(np.sqrt(2.0))
    assert np.isfinite(r.rmse_t).all() and np.isfinite(r.auc) and np.isfinite(r.drift_ratio)


def test_extra_divergence_flags_exclude_trajectory():
    r = compute_metrics(*_from_errors(E3), spread=2.0, diverged=np.array([False, False, True]))
    np.testing.assert_array_equal(r.diverged_idx, [2])
    assert r.rmse == pytest.approx(np.sqrt((4 + 8) / 8)) and r.full_rmse == math.inf


def test_all_diverged_is_explicit():
    x_true = np.arange(24.0).reshape(3, 4, 2)
    x_hat = np.full_like(x_true, np.nan)
    P = np.broadcast_to(np.eye(2), (3, 4, 2, 2))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r = compute_metrics(x_true, x_hat, P_hat=P)
    assert r.all_diverged and r.n_diverged == 3 and r.diverged_ratio == 1.0
    for k in ("rmse", "full_rmse", "nrmse", "nrmse_spread", "mae", "medae", "auc"):
        assert getattr(r, k) == math.inf, k
    for k in ("drift_ratio", "outlier_ratio") + M.COVARIANCE_METRICS:
        assert math.isnan(getattr(r, k)), k
    assert np.isinf(r.rmse_t).all() and r.rmse_t.shape == (4,)
    table = format_table({"EnKF": r.scalars()})
    row = table.splitlines()[2]
    assert row == "| EnKF | inf | inf | inf | inf | inf | inf | N/A | N/A | 1.000 | N/A | N/A | N/A | N/A |"
    payload = json.dumps(to_json(r), allow_nan=False)  # strict JSON
    back = json.loads(payload)
    assert back["rmse"] is None and back["drift_ratio"] is None and back["all_diverged"] is True


def test_bad_inputs_raise_own_error():
    with pytest.raises(MetricsError):
        compute_metrics(np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(MetricsError):
        compute_metrics(np.zeros((2, 3, 1)), np.zeros((2, 4, 1)))
    x_true = np.arange(6.0).reshape(2, 3, 1)
    x_true[0, 0, 0] = np.nan
    with pytest.raises(MetricsError, match="ground truth"):
        compute_metrics(x_true, np.zeros((2, 3, 1)))


# ---- NEES and coverage ----------------------------------------------------------------------------------


def test_nees_by_hand():
    e = np.array([[[2.0, 1.0], [1.0, 0.0], [1.0, 1.0]]])  # (1, 3, 2)
    P = np.array([[[[4.0, 0.0], [0.0, 1.0]], [[2.0, 1.0], [1.0, 2.0]], [[1.0, 2.0], [2.0, 1.0]]]])
    eps = nees(e, P)
    # diag(4, 1): 4/4 + 1/1 = 2; [[2,1],[1,2]]^-1 = [[2,-1],[-1,2]]/3: 2/3; indefinite: inf
    np.testing.assert_allclose(eps[0, :2], [2.0, 2.0 / 3.0], **TOL)
    assert eps[0, 2] == math.inf


def test_nees_mean_is_dx_and_coverage_95_for_gaussian_errors():
    rng = np.random.default_rng(0)
    n, t, dx = 200, 50, 3
    A = rng.standard_normal((n, t, dx, dx))
    P = A @ np.swapaxes(A, -1, -2) + 0.5 * np.eye(dx)  # a different SPD covariance at every (n, t)
    e = (np.linalg.cholesky(P) @ rng.standard_normal((n, t, dx, 1)))[..., 0]  # e ~ N(0, P)
    x_true, x_hat = _from_errors(e)
    r = compute_metrics(x_true, x_hat, spread=1.0, P_hat=P)
    assert r.n_outliers == 0  # every sample enters the averages below
    # NEES ~ chi2(3): mean 3, variance 6. Over K = 10,000 independent samples the mean has standard
    # deviation sqrt(6 / K) = 0.0245; 5 sigma = 0.12. Coverage is a binomial share with standard
    # deviation sqrt(0.95 * 0.05 / K) = 0.0022; 5 sigma = 0.011. (The seed is fixed, so this is
    # deterministic; the tolerances say how far a correct implementation can land from the truth.)
    assert abs(r.nees - dx) < 0.12
    assert abs(r.coverage95 - 0.95) < 0.011
    # an estimator that reports 4x too large a covariance is caught: NEES ~ dx / 4
    r_over = compute_metrics(x_true, x_hat, spread=1.0, P_hat=4.0 * P)
    assert abs(r_over.nees - dx / 4) < 0.12 / 4 and r_over.coverage95 > 0.99


# ---- median / IQR, summaries, tables, JSON --------------------------------------------------------------


def test_median_iqr():
    assert median_iqr([1.0, 2.0, 3.0, 4.0]) == pytest.approx((2.5, 1.5))  # q25 1.75, q75 3.25
    v = np.random.default_rng(1).standard_normal(11)
    med, iqr = median_iqr(v)
    assert med == pytest.approx(np.median(v)) and iqr == pytest.approx(np.subtract(*np.percentile(v, [75, 25])))
    assert median_iqr([1.0, 2.0, math.inf]) == (2.0, math.inf)  # q25 = 1.5, q75 = inf
    assert median_iqr([math.inf] * 3) == (math.inf, 0.0)
    assert median_iqr([math.nan, 1.0, 3.0]) == pytest.approx((2.0, 1.0))  # NaN left out
    assert all(math.isnan(x) for x in median_iqr([math.nan]))
    assert median_iqr(["inf", None, 1.0, 2.0]) == (2.0, math.inf)  # JSON spellings read back


def _three_reports():
    reps = []
    for scale in (1.0, 2.0, 4.0):
        reps.append(compute_metrics(*_from_errors(scale * E3), spread=2.0))
    return reps


def test_summarize_median_iqr_across_runs_and_json_round_trip():
    reps = _three_reports()
    s = summarize(reps)
    base = np.sqrt(23 / 12)
    # RMSE scales with the error: values base * (1, 2, 4): median 2 base, IQR 3 base - 1.5 base
    assert s["rmse"].median == pytest.approx(2 * base) and s["rmse"].iqr == pytest.approx(1.5 * base)
    assert s["drift_ratio"].iqr == pytest.approx(0.0)  # scale-free
    assert s["rmse"].n == 3 and s["rmse"].max == pytest.approx(4 * base)
    assert set(s) == set(M.SCALAR_METRICS) and not s["nees"].applies and s["rmse"].applies
    from_json = summarize(json.loads(json.dumps(to_json(r), allow_nan=False)) for r in reps)
    assert repr(from_json) == repr(s)  # NaN != NaN, so compare the spelled-out values


def test_format_table_paper_columns_and_cells():
    good = summarize(_three_reports())
    bad = {
        "rmse": Stat(math.inf, math.nan, 3, math.inf),
        "full_rmse": (math.inf, 0.0),
        "outlier_ratio": math.nan,
        "diverged_ratio": 1.0,
    }
    md = format_table({"UKF": good, "EnKF": bad})
    lines = md.splitlines()
    assert lines[0] == (
        "| Method | RMSE | Full RMSE | NRMSE | MAE | MedAE | AUC | Out. | Drift | Div. "
        "| NEES med. | NEES mean | 95% | Degen. |"
    )
    base = np.sqrt(23 / 12)
    ukf = lines[2].split(" | ")
    assert ukf[1] == f"{2 * base:.3f}±{1.5 * base:.3f}"
    assert ukf[6].count(".") == 2 and len(ukf[6].split("±")[0].split(".")[1]) == 1  # AUC: 1 decimal
    assert ukf[7] == "0.000" and "±" not in ukf[8]  # Out., Drift: median only, as in the paper
    assert lines[3].startswith("| EnKF | inf | inf | — |")  # NRMSE not given: does not apply
    assert lines[2].endswith("| — | — | — | — |")  # no covariance: NEES columns do not apply
    # the same columns whatever the rows hold
    with_p = {"KF": {"rmse": 1.0, "nees_median": (2.9, 0.1), "nees": math.inf, "coverage95": (0.95, 0.01)}}
    assert format_table(with_p).splitlines()[0] == lines[0] == format_table({"UKF": good}).splitlines()[0]
    assert format_table(with_p).splitlines()[2].endswith("| 2.90±0.10 | degen. | 0.950±0.010 | — |")
    text = format_table({"UKF": good}, fmt="text").splitlines()
    assert text[0].split()[:3] == ["Method", "RMSE", "Full"] and text[1].startswith("UKF")
    rows = list(csv.DictReader(io.StringIO(format_table({"UKF": good, "EnKF": bad}, fmt="csv"))))
    assert float(rows[0]["rmse"]) == pytest.approx(2 * base) and rows[1]["rmse"] == "inf"
    assert list(rows[0])[1::2] == list(M.SCALAR_METRICS) and rows[0]["nees"] == ""
    with pytest.raises(MetricsError):
        format_table({"UKF": good}, fmt="latex")


def test_to_json_plain_types():
    r = compute_metrics(*_from_errors(E3), spread=2.0, P_hat=np.broadcast_to(np.eye(1), (3, 4, 1, 1)))
    out = to_json(r)
    assert isinstance(r, MetricReport)
    payload = json.dumps(out, allow_nan=False)
    back = json.loads(payload)
    assert back["rmse_t"] == pytest.approx(list(np.sqrt([5 / 3, 2 / 3, 14 / 3, 2 / 3])))
    assert back["outlier_idx"] == [] and back["spread"] == [2.0]
    assert back["nees"] == pytest.approx(23 / 12)  # P = I: NEES = mean e^2
    assert back["cov_degenerate"] == 0.0 and back["has_covariance"] is True
    assert type(back["n_trajectories"]) is int
    no_p = to_json(compute_metrics(*_from_errors(E3), spread=2.0))
    assert set(no_p) == set(back) and no_p["nees"] is None and no_p["has_covariance"] is False  # same keys
    assert to_json({"a": np.float32(-np.inf), "b": np.array([np.nan, 1.0])}) == {"a": None, "b": [None, 1.0]}


def test_precomputed_nees_values_equal_p_hat_path():
    from neural_estimator import metrics as M

    """Evaluation computes NEES chunk by chunk; passing those values must equal passing P_hat."""
    rng = np.random.default_rng(3)
    x = rng.standard_normal((6, 5, 2))
    xh = x + 0.3 * rng.standard_normal((6, 5, 2))
    P = np.broadcast_to(np.diag([0.09, 0.2]), (6, 5, 2, 2)).copy()
    xh[4] = np.nan  # diverged: must be excluded either way
    from_p = M.compute_metrics(x, xh, P_hat=P)
    vals = M.nees(M.errors(x, xh), P)
    from_vals = M.compute_metrics(x, xh, nees_values=vals)
    assert from_p.nees == from_vals.nees and from_p.coverage95 == from_vals.coverage95
    assert np.isfinite(from_p.nees)
    with pytest.raises(M.MetricsError, match="nees_values must be"):
        M.compute_metrics(x, xh, nees_values=vals[:, :3])


def test_round_off_is_not_an_outlier():
    """Identical errors computed as (x + e) - x differ by round-off; none may be flagged."""
    from neural_estimator import metrics as M

    x = np.random.default_rng(0).standard_normal((50, 8, 2)) * 1e3
    report = M.compute_metrics(x, x + 0.5)
    assert report.n_outliers == 0


# ---- the NRMSE definition against the paper's own tables ---------------------------------------------
# (RMSE, Full RMSE, NRMSE, MAE) medians, paper.tex appendix tables tab:l96_extended and
# tab:nlink_pendulum_extended, printed to 3 decimals.
PAPER_L96 = {
    "EKF": (0.049, 0.049, 0.014, 0.027),
    "UKF": (0.048, 0.048, 0.013, 0.026),
    "EnKF": (0.054, 0.054, 0.015, 0.029),
    "PF": (0.065, 0.065, 0.018, 0.037),
    "GRU": (0.127, 0.127, 0.036, 0.101),
    "LSTM": (0.119, 0.119, 0.034, 0.093),
    "GPT-2": (0.099, 0.099, 0.028, 0.080),
    "Filterformer": (0.732, 0.732, 0.202, 0.493),
    "Mamba": (0.052, 0.052, 0.015, 0.031),
    "Mamba-2": (0.052, 0.052, 0.015, 0.031),
}
PAPER_NLINK = {
    "EKF": (0.080, 0.081, 0.012, 0.063),
    "UKF": (0.081, 0.081, 0.012, 0.065),
    "EnKF": (0.092, 0.092, 0.014, 0.073),
    "PF": (0.086, 4.678, 0.550, 0.618),
    "GRU": (0.399, 0.452, 0.063, 0.242),
    "LSTM": (0.356, 0.421, 0.058, 0.217),
    "GPT-2": (0.233, 0.269, 0.037, 0.153),
    "Filterformer": (1.749, 1.760, 0.219, 0.701),
    "Mamba": (0.093, 0.118, 0.017, 0.076),
    "Mamba-2": (0.092, 0.105, 0.015, 0.073),
}
HALF_ULP = 0.0005  # a printed 3-decimal value v is in [v - 0.0005, v + 0.0005]


def _ratio_interval(num, den):
    """Range of num / den over the values that print as num and den."""
    return (num - HALF_ULP) / (den + HALF_ULP), (num + HALF_ULP) / (den - HALF_ULP)


def test_paper_tables_rule_out_rmse_over_a_constant():
    """The paper's L96 rows contradict NRMSE = RMSE / (a number fixed by the data set).

    All 40 Lorenz 96 components have the same spread s (the system is invariant under cyclic
    shifts), so the old per-component definition, and any RMSE divided by a per-data-set
    normaliser, make RMSE / NRMSE = s for every method on the same evaluation sets. In the paper's
    table the LSTM and Filterformer ratios cannot be equal even allowing for rounding.
    """
    lo_ff, _ = _ratio_interval(PAPER_L96["Filterformer"][0], PAPER_L96["Filterformer"][2])
    _, hi_lstm = _ratio_interval(PAPER_L96["LSTM"][0], PAPER_L96["LSTM"][2])
    assert hi_lstm < 3.58 < 3.61 < lo_ff
    # The same with Full RMSE (identical here): no normaliser of the all-trajectory RMSE either.
    assert (
        _ratio_interval(PAPER_L96["LSTM"][1], PAPER_L96["LSTM"][2])[1]
        < _ratio_interval(*PAPER_L96["Filterformer"][1:3])[0]
    )


def test_paper_tables_nrmse_includes_the_outliers():
    """The N-link PF row only fits an NRMSE over all trajectories.

    Its MAE (0.618) exceeds its RMSE (0.086), impossible on one set of trajectories (MAE <= RMSE
    always): the paper's RMSE is over the kept trajectories, its other columns over all. Over the
    kept trajectories the PF's NRMSE / RMSE would be 6.4 where every other N-link row has 0.12 to
    0.19 (a 34x gap on the same trajectories); against Full RMSE all rows agree within 1.35x.
    """
    pf = PAPER_NLINK["PF"]
    assert pf[3] > pf[0]  # MAE > RMSE
    kept = {m: v[2] / v[0] for m, v in PAPER_NLINK.items()}
    full = {m: v[1] / v[2] for m, v in PAPER_NLINK.items()}
    others = [kept[m] for m in kept if m != "PF"]
    assert kept["PF"] > 30 * max(others)
    assert max(full.values()) / min(full.values()) < 1.35


def test_nrmse_behaves_as_the_paper_tables_require():
    """The two properties above, on our implementation: equal spreads and a different ratio for
    the method whose error varies between trajectories; outliers count in NRMSE, not in RMSE."""
    rng = np.random.default_rng(0)
    x = rng.standard_normal((400, 30, 4)) * 3.6  # equal spreads, as in Lorenz 96
    steady = x + 0.1 * rng.standard_normal(x.shape)  # the same error size in every trajectory
    scale = np.exp(0.8 * rng.standard_normal(400))[:, None, None]  # per-trajectory error size varies
    varied = x + 0.1 * scale * rng.standard_normal(x.shape)
    r_steady, r_varied = compute_metrics(x, steady), compute_metrics(x, varied)
    # the old definition: RMSE / NRMSE = s for both (equal spreads) -- the paper contradicts this
    s = M.state_spread(x).mean()
    assert r_steady.rmse / r_steady.nrmse_spread == pytest.approx(s, rel=0.01)
    assert r_varied.rmse / r_varied.nrmse_spread == pytest.approx(s, rel=0.01)
    # the new one: the steady method has the ratio ~s, the varied one a larger one (the
    # Filterformer's ratio above the LSTM's in the paper's L96 rows)
    assert r_steady.rmse / r_steady.nrmse == pytest.approx(s, rel=0.01)
    assert r_varied.full_rmse / r_varied.nrmse > 1.1 * s

    # outliers: 10 % of trajectories with a 100x error are removed from RMSE, not from NRMSE
    bad = steady.copy()
    bad[:40] = x[:40] + 10.0 * rng.standard_normal((40, 30, 4))
    r_bad = compute_metrics(x, bad)
    assert r_bad.n_outliers == 40
    assert r_bad.rmse == pytest.approx(r_steady.rmse, rel=0.05)  # outliers removed
    assert r_bad.nrmse > 10 * r_steady.nrmse  # outliers counted, like the paper's N-link PF


# ---- degenerate covariances ----------------------------------------------------------------------------


def test_degenerate_covariances_are_marked_not_overflowed():
    """A collapsed particle cloud's covariance (rank deficient, or zero) gives no 1e12 NEES: it is
    counted as degenerate, the median stays meaningful, and the table says so when most are."""
    rng = np.random.default_rng(1)
    n, t, dx = 20, 10, 3
    x = rng.standard_normal((n, t, dx))
    xh = x + rng.standard_normal((n, t, dx))  # errors ~ N(0, I): with P = I, NEES ~ chi2(3)
    P = np.broadcast_to(np.eye(dx), (n, t, dx, dx)).copy()
    v = np.array([1.0, 2.0, -1.0])
    P[:, :3] = np.outer(v, v) * 1e-3 + np.eye(dx) * 1e-19  # rank one up to round-off: Cholesky passes
    P[:, 3] = 0.0  # collapsed to a point: not positive definite
    P[0, 4, 0, 0] = np.inf  # overflowed
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        eps = nees(M.errors(x, xh), P)
        r = compute_metrics(x, xh, P_hat=P)
    assert np.isinf(eps[:, :4]).all() and np.isinf(eps[0, 4]) and np.isfinite(eps[1:, 4:]).all()
    assert r.cov_degenerate == pytest.approx((4 * n + 1) / (n * t))
    assert r.nees == pytest.approx(eps[np.isfinite(eps)].mean())  # mean over the usable ones: ~3
    assert 1.5 < r.nees < 5  # chi2(3) has mean 3
    # 40 % degenerate: the median is finite, the 83rd percentile of the usable values' chi2(3)
    assert r.nees_median == np.median(eps) and 3 < r.nees_median < 8
    assert r.coverage95 == pytest.approx(np.mean(eps <= 7.814727903251178))  # degenerate: not covered
    assert r.coverage95 < 0.6
    # a legitimately ill-scaled but regular covariance (units differing by 1e6) is not degenerate
    P_units = np.broadcast_to(np.diag([1e6, 1.0, 1e-6]), (n, t, dx, dx))
    assert compute_metrics(x, xh, P_hat=P_units).cov_degenerate == 0.0
    # most steps degenerate: the median NEES is inf and the table says "degen.", JSON null
    P[:, :] = 0.0
    r_all = compute_metrics(x, xh, P_hat=P)
    assert r_all.cov_degenerate == 1.0 and r_all.coverage95 == 0.0 and math.isinf(r_all.nees_median)
    row = M.format_reports({"PF": r_all}, fmt="markdown").splitlines()[2]
    assert row.endswith("| degen. | degen. | 0.000 | 1.000 |") and "inf" not in row.split("|")[10]
    back = json.loads(json.dumps(to_json(r_all), allow_nan=False))
    assert back["nees_median"] is None and back["cov_degenerate"] == 1.0


def test_a_single_set_prints_its_value_without_a_fake_spread():
    """One evaluation set has no spread: "2.195", not "2.195±0.000"; several sets keep their IQR, 0 too."""
    from neural_estimator.metrics.summary import Stat

    one = format_table({"gru": {"rmse": Stat(2.195, 0.0, 1, 2.195)}}, fmt="text")
    assert "2.195" in one and "±" not in one
    three = format_table({"gru": {"rmse": Stat(2.195, 0.0, 3, 2.195)}}, fmt="text")
    assert "2.195±0.000" in three
