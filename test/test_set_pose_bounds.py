"""set_pose refuses what is not a pose in the node's frame, in one WARN line, and the stream goes on
(a covariance diagonal of 1e308 killed the EKF and UKF nodes; x = 1e308, a
covariance of 1e200 and frame 'moon' were accepted silently). Plain code: the subscription's
callback is called with a stand-in node, so a raised exception here is a dead node there."""

from __future__ import annotations

import types

import numpy as np
import pytest

from neural_estimator.nodes import outputs as O
from neural_estimator.nodes.odometry import quaternion
from neural_estimator.stream.online import OnlineEstimator
from neural_estimator.methods.registry import make_estimator
from neural_estimator.scenarios import make_scenario


def _pose(frame="map", x=1.0, y=2.0, yaw=0.3, cov=None):
    o = dict(zip("xyzw", quaternion(0.0, 0.0, yaw)))
    ns = types.SimpleNamespace
    return ns(
        header=ns(stamp=ns(sec=0, nanosec=0), frame_id=frame),
        pose=ns(
            pose=ns(position=ns(x=x, y=y, z=0.0), orientation=ns(**o)),
            covariance=list(np.zeros(36) if cov is None else np.asarray(cov, dtype=float).reshape(-1)),
        ),
    )


class _Logger:
    def __init__(self):
        self.lines = []

    def warning(self, text, throttle_duration_sec=0.0):
        self.lines.append(("WARN", text))

    def info(self, text):
        self.lines.append(("INFO", text))


class _Node:
    def __init__(self):
        self.logger = _Logger()

    def get_logger(self):
        return self.logger


def _diag(*values):
    return np.diag(np.array(values, dtype=float))


HOSTILE = {
    "covariance diagonal 1e308": (_pose(cov=_diag(1e308, 1, 1, 1, 1, 1)), "ceiling"),
    "covariance 1e200": (_pose(cov=_diag(1e200, 1e200, 1, 1, 1, 1)), "ceiling"),
    "x = 1e308": (_pose(x=1e308), "ceiling"),
    "y = -1e8": (_pose(y=-1e8), "ceiling"),
    "frame moon": (_pose(frame="moon"), "frame 'moon'"),
    "no frame": (_pose(frame=""), "frame ''"),
    "x NaN": (_pose(x=float("nan")), "NaN or inf"),
    "covariance inf": (_pose(cov=_diag(np.inf, 1, 1, 1, 1, 1)), "NaN or inf"),
    "covariance not symmetric": (_pose(cov=_diag(1, 1, 1, 1, 1, 1) + np.triu(np.ones((6, 6)), 1)), "not symmetric"),
    "covariance negative": (_pose(cov=_diag(-4, 1, 1, 1, 1, 1)), "not positive semi-definite"),
}


@pytest.mark.parametrize("method", ["ekf", "ukf"])
def test_hostile_set_pose_is_refused_in_one_warn_line_and_the_stream_goes_on(method, monkeypatch):
    clock = iter(range(0, 10**6, 2))  # 2 s between messages: no refusal is a throttled repeat
    monkeypatch.setattr(O.time, "monotonic", lambda: float(next(clock)))
    scen = make_scenario("bearings")
    online = OnlineEstimator(make_estimator(method, scen), method)
    node = _Node()
    sp = O.SetPose(node, "", lambda: online, "map")
    before = online.estimator._P.copy() if hasattr(online.estimator, "_P") else None
    for name, (msg, why) in HOSTILE.items():
        node.logger.lines.clear()
        sp._on_pose(msg)  # an exception here would be a dead node
        assert node.logger.lines and len(node.logger.lines) == 1, name
        level, text = node.logger.lines[0]
        assert level == "WARN" and text.startswith("set_pose") and "\n" not in text, (name, text)
        assert why in text, (name, text)
    assert sp.refused == len(HOSTILE) and sp.applied == 0
    if before is not None:
        np.testing.assert_array_equal(online.estimator._P, before)  # nothing was half-set
    good = _diag(4, 9, 1, 1, 1, 0.25)
    sp._on_pose(_pose(x=40.0, y=-25.0, cov=good))
    assert sp.applied == 1 and node.logger.lines[-1][0] == "INFO"
    assert np.all(np.isfinite(online.estimator.step(np.zeros((1, scen.dy)))))


def test_covariances_at_the_ceiling_are_accepted():
    cov = O.pose_covariance(_pose(cov=_diag(O.SET_POSE_MAX_VARIANCE, 1, 1, 1, 1, 1)))
    assert cov[0, 0] == O.SET_POSE_MAX_VARIANCE
    assert O.pose_values(_pose(x=-O.SET_POSE_MAX_ABS))["x"] == -O.SET_POSE_MAX_ABS


def _huge(off_diagonal):
    P = _diag(1e308, 1e308, 1, 1)
    P[0, 1] = P[1, 0] = off_diagonal
    return P


@pytest.mark.parametrize("method", ["ekf", "ukf", "enkf", "pf"])
@pytest.mark.parametrize("off_diagonal", [0.0, 1e307])
def test_filters_take_a_huge_initial_covariance_without_overflow_or_a_linalg_error(method, off_diagonal):
    """The cause under the node: 0.5 * (P + P^T) overflowed to inf for a finite 1e308, so eigvalsh
    raised LinAlgError ("Eigenvalues did not converge", with a correlation) or returned NaN and an
    inf covariance was taken silently (without)."""
    from neural_estimator.methods.interface import EstimatorError

    scen = make_scenario("bearings")
    f = make_estimator(method, scen)
    try:
        f.reset(1, initial_cov=_huge(off_diagonal)[None])
    except EstimatorError as exc:
        assert "initial_cov" in str(exc)
    else:
        assert np.all(np.isfinite(f._init_cov))


def test_a_flood_of_the_same_refusal_is_one_line_a_second_and_another_reason_is_never_hidden(monkeypatch):
    now = [0.0]
    monkeypatch.setattr(O.time, "monotonic", lambda: now[0])
    scen = make_scenario("bearings")
    online = OnlineEstimator(make_estimator("ekf", scen), "ekf")
    node = _Node()
    sp = O.SetPose(node, "", lambda: online, "map")
    for _ in range(100):  # 100 in 0.99 s
        sp._on_pose(_pose(frame="moon"))
        now[0] += 0.0099
    sp._on_pose(_pose(x=1e308))  # another reason, at once
    now[0] = 1.5
    sp._on_pose(_pose(x=1e308))  # the same again within the second: not repeated
    sp._on_pose(_pose(frame="mars"))  # the first reason (another frame), 1.5 s after its first line
    texts = [t for _, t in node.logger.lines]
    assert len(texts) == 3 and sp.refused == 103
    assert "frame 'moon'" in texts[0] and "(1 refused so far)" in texts[0]
    assert "ceiling" in texts[1] and "frame 'mars'" in texts[2] and "(103 refused so far)" in texts[2]
