"""filterpy run one trajectory at a time: the independent references of the batched filters.

The tests hold the batched EKF and UKF equal to these (to 1e-6 relative) and the EnKF and PF equal
in distribution; ``benchmarks/bench_filters.py`` times them as the one-trajectory-at-a-time
baseline. Each function filters one trajectory under the project's timing convention (y_0 updates
the prior; for k >= 1 predict with u_{k-1}, then update with y_k) and returns the posterior means
(T, dx) (and covariances (T, dx, dx) for the EKF and UKF).

filterpy (https://github.com/rlabbe/filterpy) is imported on first use.
"""

from __future__ import annotations

import numpy as np

from neural_estimator.methods.interface import previous_controls
from neural_estimator.scenarios import Scenario, psd_sqrt


def filterpy_ekf(s: Scenario, y: np.ndarray, u: np.ndarray):
    """filterpy.kalman.ExtendedKalmanFilter with f, jac_f, h, jac_h, angle-wrapped innovations."""
    from filterpy.kalman import ExtendedKalmanFilter as FpEKF

    m0, P0 = s.prior()
    ekf = FpEKF(dim_x=s.dx, dim_z=s.dy)
    ekf.x, ekf.P, ekf.Q, ekf.R = m0.copy(), P0.copy(), s.process_cov(), s.obs_cov()
    up = previous_controls(u[None])[0]
    xs, Ps = [], []
    for k in range(len(y)):
        if k:
            # filterpy's EKF predicts x with F x; the nonlinear f replaces that, F linearises at x.
            ekf.F = s.jac_f(ekf.x, up[k])
            x_new = s.normalize_state(s.f(ekf.x, up[k]))
            ekf.predict()
            ekf.x = x_new
        ekf.update(y[k], HJacobian=s.jac_h, Hx=s.h, residual=s.obs_residual)
        ekf.x = s.normalize_state(ekf.x)
        xs.append(ekf.x.copy())
        Ps.append(ekf.P.copy())
    return np.array(xs), np.array(Ps)


def filterpy_ukf(s: Scenario, y: np.ndarray, u: np.ndarray):
    """filterpy.kalman.UnscentedKalmanFilter, MerweScaledSigmaPoints(alpha=1e-3, beta=2, kappa=0).

    For angles: residual_x / residual_z / x_mean_fn / z_mean_fn / state_add from the scenario
    (filterpy's sigma-point mean is a plain weighted sum unless x_mean_fn is given).
    """
    from filterpy.kalman import MerweScaledSigmaPoints
    from filterpy.kalman import UnscentedKalmanFilter as FpUKF

    m0, P0 = s.prior()
    angles_x, angles_z = bool(s.angle_states), bool(s.angle_obs)
    pts = MerweScaledSigmaPoints(s.dx, alpha=1e-3, beta=2.0, kappa=0.0, subtract=s.state_residual if angles_x else None)
    ukf = FpUKF(
        dim_x=s.dx,
        dim_z=s.dy,
        dt=s.dt,
        hx=s.h,
        fx=lambda x, dt, u: s.f(x, u),
        points=pts,
        x_mean_fn=s.state_mean if angles_x else None,
        z_mean_fn=s.obs_mean if angles_z else None,
        residual_x=s.state_residual if angles_x else None,
        residual_z=s.obs_residual if angles_z else None,
        state_add=(lambda a, b: s.normalize_state(a + b)) if angles_x else None,
    )
    ukf.x, ukf.P, ukf.Q, ukf.R = m0.copy(), P0.copy(), s.process_cov(), s.obs_cov()
    up = previous_controls(u[None])[0]
    xs, Ps = [], []
    for k in range(len(y)):
        if k:
            ukf.predict(u=up[k])
        else:  # the timing convention: y_0 updates the prior, so draw its sigma points
            ukf.sigmas_f = pts.sigma_points(ukf.x, ukf.P)
        ukf.update(y[k])
        xs.append(ukf.x.copy())
        Ps.append(ukf.P.copy())
    return np.array(xs), np.array(Ps)


def filterpy_enkf(s: Scenario, y: np.ndarray, u: np.ndarray, N: int = 50, seed: int = 0):
    """filterpy.kalman.EnsembleKalmanFilter (stochastic, perturbed observations) with N members."""
    from filterpy.kalman import EnsembleKalmanFilter as FpEnKF

    np.random.seed(seed)  # filterpy draws from numpy's global generator
    m0, P0 = s.prior()
    up = previous_controls(u[None])[0]
    enkf = FpEnKF(x=m0.copy(), P=P0.copy(), dim_z=s.dy, dt=s.dt, N=N, hx=s.h, fx=lambda x, dt: x)
    enkf.Q, enkf.R = s.process_cov(), s.obs_cov()
    xs = []
    for k in range(len(y)):
        if k:
            enkf.fx = lambda x, dt, uk=up[k]: s.f(x, uk)
            enkf.predict()
        # filterpy's EnKF subtracts observations plainly; unwrapping each member's predicted angle
        # next to y_k (h_k(x) = y_k + wrap(h(x) - y_k)) makes those differences the wrapped ones.
        enkf.hx = lambda x, yk=y[k]: yk + s.obs_residual(s.h(x), yk)
        enkf.update(y[k])
        xs.append(enkf.x.copy())
    return np.array(xs)


def reference_pf(s: Scenario, y: np.ndarray, u: np.ndarray, N: int = 1024, init_std: float = 1.0, seed: int = 0):
    """A bootstrap PF for one trajectory built on filterpy.monte_carlo.systematic_resample.

    Vectorised over its N particles (as any sensible one-trajectory PF is), log-space weights,
    resampling when ESS < N / 2, estimate = weighted mean before resampling.
    """
    from filterpy.monte_carlo import systematic_resample as fp_systematic_resample
    from scipy.special import logsumexp

    np.random.seed(seed)  # filterpy's systematic_resample draws from numpy's global generator
    rng = np.random.default_rng(seed + 1)
    m0, _ = s.prior()
    LQ, Rinv = psd_sqrt(s.process_cov()), np.linalg.inv(s.obs_cov())
    up = previous_controls(u[None])[0]
    X = s.normalize_state(m0 + init_std * rng.standard_normal((N, s.dx)))
    logw = np.full(N, -np.log(N))
    xs = []
    for k in range(len(y)):
        if k:
            X = s.normalize_state(s.f(X, np.broadcast_to(up[k], (N, s.du))) + rng.standard_normal((N, s.dx)) @ LQ.T)
        r = s.obs_residual(y[k], s.h(X))
        logw = logw - 0.5 * np.einsum("ni,ij,nj->n", r, Rinv, r, optimize=True)
        logw -= logsumexp(logw)
        w = np.exp(logw)
        xs.append(s.state_mean(X, w))
        if 1.0 / np.sum(w**2) < N / 2:
            X = X[fp_systematic_resample(w)]
            logw = np.full(N, -np.log(N))
    return np.array(xs)


# ---- DAPPER (https://github.com/nansencenter/DAPPER), the data-assimilation reference ---------------
def dapper_filter(s: Scenario, x: np.ndarray, y: np.ndarray, method: str, seed: int, **settings) -> np.ndarray:
    """Analysis means (T, dx) of one DAPPER filter on one trajectory of ``s`` (no controls, h = H x).

    ``method``: ``"ExtKF"`` (settings: ``infl``), ``"EnKF"`` (``upd_a``, ``N``, ``infl``) or
    ``"PartFilt"`` (``N``, ``NER``, ``reg``, ``qroot``). DAPPER is given the scenario's own f, H, Q,
    R and prior, so the two implementations see the same model and data.

    Timing. DAPPER observes from its step 1 on; ours updates the prior with y_0. So DAPPER's step 1
    is an identity "transition" (its process noise, Q, is still added once: a 1e-5 relative change
    of P0 here), and its observation ko is our y_ko: the returned row k is the analysis after y_k,
    as ours. DAPPER's noise is per unit time (it adds dt C), so C = Q / dt. DAPPER 1.7's ExtKF
    evaluates ``Dyn.linear`` at the forecast mean f(m) (after the step); ``linear`` here returns
    df/dx at m, the state the step started from, so its ExtKF is the textbook EKF (with F at f(m)
    it tracked Lorenz 96 at 0.066 RMSE where the textbook EKF has 0.047, same data).
    """
    import dapper.da_methods as da
    import dapper.mods as modelling
    from dapper.tools.seeding import set_seed

    H = s.obs_matrix()
    if H is None or s.du:
        raise ValueError(f"dapper_filter: {s.name} needs a linear observation and no controls")
    T, n = x.shape
    dt = s.dt
    m0, P0 = s.prior()
    u0 = np.zeros((0,))

    last_input: list[np.ndarray] = []

    def step(E: np.ndarray, t: float, dt_: float) -> np.ndarray:
        last_input[:] = [np.array(E)]
        return E if t < 0.5 * dt else s.f(E, u0)

    def linear(xk: np.ndarray, t: float, dt_: float) -> np.ndarray:
        # DAPPER's ExtKF asks for F after stepping the mean, with the forecast: the Jacobian is
        # taken at the state the step started from (the textbook EKF, filterpy's, ours).
        return np.eye(n) if t < 0.5 * dt else s.jac_f(last_input[0], u0)

    tseq = modelling.Chronology(dt, dko=1, K=T, BurnIn=0)
    Dyn = {"M": n, "model": step, "linear": linear, "noise": modelling.GaussRV(C=s.process_cov() / dt, M=n)}
    Obs = {
        "M": H.shape[0],
        "model": lambda E: E @ H.T,
        "linear": lambda xk: H,
        "noise": modelling.GaussRV(C=s.obs_cov(), M=H.shape[0]),
    }
    HMM = modelling.HiddenMarkovModel(Dyn, Obs, tseq, modelling.GaussRV(mu=m0, C=P0))
    xp = getattr(da, method)(**settings)
    set_seed(int(seed) + 1)  # DAPPER refuses seed 0
    xx = np.concatenate([x[:1], x], axis=0)
    xp.assimilate(HMM, xx, y, liveplots=False)
    return np.asarray(xp.stats.mu.a)
