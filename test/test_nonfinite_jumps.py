"""Corrupt (non-finite) observations cannot move the stream: two NaN observations
claiming steps 53 and 54 while the stream was at 50 were taken as a confirmed forward jump; the real
step 51 then looked like a restarted publisher and the filter was reset to the prior mid-trajectory
(live GRU RMSE 63.3 -> 72.4; through replay NEES mean 2.4 -> 11.3). A non-finite message is now no
evidence for a jump, so the real stream is estimated exactly as without them, live (the node's
OnlineEstimator.feed) and offline (replay, the same code path)."""

from __future__ import annotations

import numpy as np
import pytest

from neural_estimator.bags import BagWriter, bag_to_arrays
from neural_estimator.stream import messages as MSG
from neural_estimator.data import simulate
from neural_estimator.stream.online import OnlineEstimator
from neural_estimator.methods.registry import make_estimator
from neural_estimator.evaluation.replay import replay
from neural_estimator.scenarios import make_scenario

T = 80
AT = 50  # the real stream's last step when the corrupt pair arrives


@pytest.fixture(scope="module")
def scen():
    return make_scenario("bearings")


@pytest.fixture(scope="module")
def data(scen):
    return simulate(scen, 1, T, seed=11)


def _obs(scen, data, k, y=None):
    t = MSG.step_stamp_ns(10**18, k, MSG.dt_ns(scen.dt))
    u_prev = data.u[0, k - 1] if k else np.zeros(scen.du)
    return MSG.encode_observation(scen, t, 0, k, data.y[0, k] if y is None else y, u_prev)


def _sent(scen, data, corrupt):
    nan = np.full(scen.dy, np.nan)
    sent = [_obs(scen, data, k) for k in range(T)]
    pair = [_obs(scen, data, k, nan) for k in corrupt]
    return sent[: AT + 1] + pair + sent[AT + 1 :]


def _run(online, raws):
    out = []
    for raw in raws:
        out += online.feed(raw, 0.0)
    return out + online.flush()


def _estimates(results):
    est = [r for r in results if r.status == "estimated"]
    return [r.step for r in est], np.array([r.x_hat for r in est]), sum(r.reset for r in est)


@pytest.mark.parametrize("method", ["ekf", "gru"])
@pytest.mark.parametrize("corrupt", [(53, 54), (53, 54, 55, 56), (52, 60), (40, 41)])
def test_non_finite_messages_never_confirm_a_jump(scen, data, method, corrupt):
    clean_steps, clean, _ = _estimates(
        _run(OnlineEstimator(make_estimator(method, scen), method), _sent(scen, data, ()))
    )
    results = _run(OnlineEstimator(make_estimator(method, scen), method), _sent(scen, data, corrupt))
    steps, got, resets = _estimates(results)
    assert steps == clean_steps == list(range(T)) and resets == 1  # one stream, started once
    np.testing.assert_array_equal(got, clean)
    dropped = [(r.status, r.step) for r in results if r.status not in ("estimated", "held")]
    assert [s for _, s in dropped] == list(corrupt) and not any(r.status == "held" for r in results)
    # ahead of the stream: unconfirmed; behind it (40, 41 at step 50): stale
    assert {s for s, _ in dropped} == ({"stale"} if corrupt[0] < AT else {"unconfirmed"})


def test_a_finite_jump_still_needs_only_its_confirmation(scen, data):
    """The rule for real observations is unchanged: two finite messages of a later step are a
    confirmed forward gap (a publisher that lost messages), bridged by predict-only steps."""
    online = OnlineEstimator(make_estimator("ekf", scen), "ekf")
    sent = [_obs(scen, data, k) for k in range(AT + 1)] + [_obs(scen, data, k) for k in range(AT + 3, T)]
    steps, _, resets = _estimates(_run(online, sent))
    assert steps == list(range(AT + 1)) + list(range(AT + 3, T)) and resets == 1


def test_replay_estimates_the_real_stream_as_if_the_corrupt_pair_was_never_sent(scen, data, tmp_path):
    paths = {}
    for name, corrupt in (("clean", ()), ("corrupt", (53, 54))):
        paths[name] = tmp_path / f"{name}.mcap"
        with BagWriter(paths[name]) as w:
            w.add_topic("/scenario", MSG.STRING)
            w.write("/scenario", 0, MSG.encode_scenario(scen.describe()))
            w.add_topic("/observation", MSG.JOINT_STATE)
            for i, raw in enumerate(_sent(scen, data, corrupt)):
                w.write("/observation", 1 + i, raw)
    out = {name: replay(path, ["ekf"], tmp_path / f"{name}-out.mcap") for name, path in paths.items()}
    assert out["clean"].estimates == out["corrupt"].estimates == {"ekf": T}
    assert out["corrupt"].skipped == {"ekf": 2}
    np.testing.assert_array_equal(
        bag_to_arrays(out["corrupt"].path).x_hat["ekf"], bag_to_arrays(out["clean"].path).x_hat["ekf"]
    )
