"""Extended Kalman filter, batched over B streams.

Reference: the paper's "standard configuration" EKF (Table hparams); the equations are those of
filterpy's ``ExtendedKalmanFilter`` (Joseph-form covariance update), which the tests use as the
independent implementation. Angular observation components are wrapped in the innovation
(``scenario.obs_residual``) and angular state components after the update
(``scenario.normalize_state``).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import numpy as np

from neural_estimator.filters.base import ClassicalFilter, check_inflation, compiled_applies
from neural_estimator.filters.kernels import compiled_model
from neural_estimator.filters.kernels import ekf as compiled_ekf
from neural_estimator.filters.numerics import ScenarioOps, psd_solve, symmetrize


@dataclass(frozen=True)
class EKFHyperParams:
    """EKF settings. The paper uses the "standard configuration" (these defaults)."""

    joseph_form: bool = True  # P = (I-KH) P (I-KH)^T + K R K^T (filterpy's update); False: P - K S K^T
    inflation: float = 1.0  # not in the paper (1 = none): P^- = inflation^2 F P F^T + q_inflation Q
    q_inflation: float = 1.0  # not in the paper (1 = none): multiplies the process noise covariance Q

    def validate(self) -> None:
        check_inflation(self.inflation, self.q_inflation)
        if not isinstance(self.joseph_form, bool):
            raise ValueError(f"joseph_form must be true or false, got {self.joseph_form!r}")


# ---- the maths: plain functions on arrays of b streams (the class below only schedules them) ----------
def _predict(
    m: np.ndarray, P: np.ndarray, u: np.ndarray, *, ops: ScenarioOps, Q: np.ndarray, inflation: float
) -> tuple[np.ndarray, np.ndarray]:
    """Predict, with F = df/dx at (m, u_{k-1}):

        m^- = f(m, u_{k-1})
        P^- = inflation^2 F P F^T + Q          (Q already multiplied by q_inflation)

    Args: m (b, n), P (b, n, n), u (b, du). Returns m^- (b, n), P^- (b, n, n).
    """
    s = ops.scenario
    F = s.jac_f(m, u)  # (b, n, n)
    m_pred = ops.normalize_state(s.f(m, u))
    FPFt = F @ P @ np.swapaxes(F, -1, -2)
    if inflation != 1.0:
        FPFt *= inflation**2
    return m_pred, symmetrize(FPFt + Q)


def _update(
    m: np.ndarray, P: np.ndarray, y: np.ndarray, *, ops: ScenarioOps, R: np.ndarray, eye: np.ndarray, joseph_form: bool
) -> tuple[np.ndarray, np.ndarray]:
    """Update, with H = dh/dx at m^-:

        r = y_k - h(m^-)                    (angles wrapped)
        S = H P^- H^T + R
        K = P^- H^T S^{-1}                  (solved with S, never inverted)
        m = m^- + K r                       (angles wrapped)
        P = (I - K H) P^- (I - K H)^T + K R K^T     (Joseph form; or P^- - K S K^T)

    Args: m (b, n), P (b, n, n), y (b, dy); eye = I (n, n). Returns m (b, n), P (b, n, n).
    """
    s = ops.scenario
    H = s.jac_h(m)  # (b, dy, n)
    r = ops.obs_residual(y, s.h(m))  # (b, dy)
    PHt = P @ np.swapaxes(H, -1, -2)  # (b, n, dy)
    S = symmetrize(H @ PHt + R)  # (b, dy, dy)
    Kt = psd_solve(S, np.swapaxes(PHt, -1, -2))  # (b, dy, n) = K^T = S^{-1} H P
    m_post = ops.normalize_state(m + np.einsum("bmn,bm->bn", Kt, r))
    if joseph_form:
        K = np.swapaxes(Kt, -1, -2)
        IKH = eye - K @ H
        P_post = IKH @ P @ np.swapaxes(IKH, -1, -2) + K @ R @ Kt
    else:
        P_post = P - PHt @ Kt  # K S K^T = P^- H^T K^T
    return m_post, symmetrize(P_post)


def _no_flags(fn):
    """A maths function as a scheduler kernel: its outputs plus ok = None (the EKF flags no stream
    itself; non-finite results are caught by the base class)."""
    return lambda *arrays: (*fn(*arrays), None)


class ExtendedKalmanFilter(ClassicalFilter):
    r"""Extended Kalman filter.

    Predict (k >= 1), with F = df/dx at (m, u_{k-1}):

        m^- = f(m, u_{k-1})
        P^- = F P F^T + Q

    Update, with H = dh/dx at m^-:

        r = y_k - h(m^-)                    (angles wrapped)
        S = H P^- H^T + R
        K = P^- H^T S^{-1}                  (solved with S, never inverted)
        m = m^- + K r                       (angles wrapped)
        P = (I - K H) P^- (I - K H)^T + K R K^T     (Joseph form; or P^- - K S K^T)

    Every covariance is symmetrised. A stream whose mean or covariance goes non-finite (a singular
    S included) is flagged in ``diverged``. The EKF factors no covariance, so it needs no jitter.

    Covariance inflation (not in the paper; both off by default, the paper's filters):

        P^- = inflation^2 {prediction covariance} + q_inflation Q

    ``inflation`` >= 1 multiplies the spread (standard deviations) of the propagated covariance,
    as the EnKF's ``inflation`` multiplies its anomalies (multiplicative inflation, Anderson &
    Anderson 1999); ``q_inflation`` multiplies the process noise the filter assumes (additive
    inflation). Both compensate for what the linearisation or the model leaves out: on Lorenz 96
    at observation variance 1 the EKF loses track without them. DAPPER's ``ExtKF(infl=a)``
    multiplies F P F^T by a^dt, i.e. ``inflation`` = a^(dt/2).
    """

    method = "ekf"
    HyperParams = EKFHyperParams
    # Larger blocks than the base's: the EKF's per-stream work is a few (n, n) products, and on
    # Lorenz 96 its Jacobian (13 band diagonals of (b, n)) is many small operations whose Python
    # overhead smaller blocks multiply. Measured at B = 2000, 2 threads: 11.9k traj-steps/s with
    # 2^17, 14.9k with 2^19, 10.4k with 2^21.
    block_elements = 2**19
    # Lorenz 96 runs on the compiled kernels (filters/kernels/ekf.py: the same equations, one
    # compiled call per phase and block of streams, the blocks on the filter's threads) at every
    # batch: at B = 1 numpy's per-call cost is most of a batched step, and at B = 1,000 (n = 40, one
    # thread) they are still 1.5x the batched numpy path per trajectory
    # (benchmarks/bench_batch_kernels.py). An int caps the batch they run at; 0 turns them off.
    compiled_max_batch: int | None = None

    def _init_state(self, B: int) -> None:
        n = self.scenario.dx
        self._eye = np.eye(n)
        self._m = np.array(self._init_mean, dtype=np.float64)  # (B, n): m0 or the given initial means
        self._P = self._initial_cov(B)
        self._compiled = self._compiled_kernels(B)
        # the kernels, bound once per reset (not per step: a B = 1 step is ~0.5 ms)
        self._predict_kernel = _no_flags(partial(_predict, ops=self.ops, Q=self.Q, inflation=self.hp.inflation))
        self._update_kernel = _no_flags(
            partial(_update, ops=self.ops, R=self.R, eye=self._eye, joseph_form=self.hp.joseph_form)
        )

    def _compiled_kernels(self, B: int):
        """(predict, update) on the compiled single-stream kernels, or None for the batched path (a
        scenario whose kernels have no ``ekf_model``: all but Lorenz 96)."""
        if not compiled_applies(self.compiled_max_batch, B):
            return None
        model = compiled_model(self.scenario).ekf_model
        if model is None:
            return None
        H = np.ascontiguousarray(self.scenario.obs_matrix(), dtype=np.float64)
        Q, R = np.ascontiguousarray(self.Q), np.ascontiguousarray(self.R)
        inflation2, joseph = float(self.hp.inflation) ** 2, bool(self.hp.joseph_form)
        no_skip = np.zeros(B, dtype=bool)

        def own() -> None:  # the last step's covariance was handed out read-only: write a new one
            if not self._P.flags.writeable or not self._P.flags.c_contiguous:
                self._P = np.array(self._P, dtype=np.float64, order="C")
            if not self._m.flags.writeable or not self._m.flags.c_contiguous:
                self._m = np.array(self._m, dtype=np.float64, order="C")

        def predict() -> None:
            own()
            m, P = self._m, self._P
            self._scheduler.for_each(lambda i, sl: compiled_ekf.predict(m[sl], P[sl], Q, inflation2, *model))

        def update(y: np.ndarray, skip: np.ndarray | None) -> None:
            own()
            m, P, no = self._m, self._P, no_skip if skip is None else skip
            self._scheduler.for_each(lambda i, sl: compiled_ekf.update(m[sl], P[sl], y[sl], no[sl], H, R, joseph))

        return predict, update

    # The maths is the module-level _predict / _update; these hooks run it over the blocks of streams.
    def _predict(self, u: np.ndarray) -> None:
        if self._compiled is not None:
            self._compiled[0]()
            return None
        self._m, self._P, _ = self._blockwise(self._predict_kernel, self._m, self._P, u)
        return None

    def _update(self, y: np.ndarray, skip: np.ndarray | None) -> None:
        if self._compiled is not None:
            self._compiled[1](y, skip)
            return None
        m_post, P_post, _ = self._blockwise(self._update_kernel, self._m, self._P, y)
        self._m, self._P = self._keep(skip, self._m, m_post), self._keep(skip, self._P, P_post)
        return None

    def _estimate(self) -> tuple[np.ndarray, np.ndarray]:
        return self._m, self._P

    def _park(self, mask: np.ndarray) -> None:
        self._m = np.where(mask[:, None], self.m0, self._m)
        self._P = np.where(mask[:, None, None], self.P0, self._P)
