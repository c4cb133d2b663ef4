"""The estimator node's per-message path: the observation's values read straight from the message
bytes (no Vector, no name check when the layout is exactly the stream's), both finiteness checks
in one pass; the same results as the full decoding."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from neural_estimator.stream import messages as MSG
from neural_estimator.bags.errors import MessageError
from neural_estimator.stream.online import OnlineEstimator, finite_parts
from neural_estimator.methods.registry import make_estimator
from neural_estimator.scenarios import make_scenario


@pytest.fixture(scope="module")
def quad():
    return make_scenario("quadrotor")  # observations and controls


def test_in_place_values_equal_the_full_decoding(quad):
    codec = MSG.VectorCodec(quad.name, MSG.observation_labels(quad))
    rng = np.random.default_rng(0)
    for stamp, traj, step in ((0, 0, 0), (1_700_000_000_123_456_789, 3, 499), (-5_000_000_001, 2**40, 7)):
        y, u = rng.normal(size=quad.dy), rng.normal(size=quad.du)
        y[1] = np.nan
        raw = MSG.encode_observation(quad, stamp, traj, step, y, u)
        vec = MSG.decode_vector(raw)
        got = codec.decode_values(raw)
        assert got is not None and got[:3] == (vec.stamp_ns, vec.trajectory, vec.step) == (stamp, traj, step)
        np.testing.assert_array_equal(got[3], vec.values)
        assert got[3].dtype == np.float64 and got[3].flags.aligned and got[3].flags.writeable
        # a memoryview of a buffer that is reused afterwards: the values keep the message's numbers
        buf = bytearray(raw)
        kept = codec.decode_values(memoryview(buf))[3]
        buf[:] = bytes(len(buf))
        np.testing.assert_array_equal(kept, vec.values)


def test_anything_but_the_exact_layout_goes_to_the_full_decoding(quad):
    codec = MSG.VectorCodec(quad.name, MSG.observation_labels(quad))
    raw = MSG.encode_observation(quad, 10, 1, 2, np.zeros(quad.dy), np.zeros(quad.du))
    other = MSG.encode_vector(
        10, quad.name, 1, 2, [f"v{i}" for i in range(quad.dy + quad.du)], np.zeros(quad.dy + quad.du)
    )
    bad = [
        raw[:-9],  # truncated
        raw[:-8] + b"\x01" + raw[-7:],  # a non-empty velocity array
        other,  # other names
        b"\x00\x00\x00\x00" + raw[4:],  # big-endian header
        MSG.encode_vector(10, quad.name, 1, 2, MSG.observation_labels(quad), np.zeros(quad.dy + quad.du)).replace(
            np.float64(2.0).tobytes(), np.float64(2.5).tobytes(), 1
        ),  # a fractional step
        raw + bytes(codec.max_bytes),  # larger than any valid message
    ]
    for b in bad:
        assert codec.decode_values(b) is None
    assert codec.decode_values(raw) is not None


def test_finite_parts_equals_numpy():
    rng = np.random.default_rng(1)
    for n, dy in ((1, 1), (5, 3), (12, 12), (7, 0)):
        for bad in itertools.chain([None], range(n)):
            for value in (np.nan, np.inf, -np.inf):
                v = rng.normal(size=n)
                if bad is not None:
                    v[bad] = value
                want = (bool(np.isfinite(v[:dy]).all()), bool(np.isfinite(v[dy:]).all()))
                assert finite_parts(v, dy) == want


def test_the_callback_flags_a_missing_observation_and_refuses_a_bad_control(quad):
    online = OnlineEstimator(make_estimator("ekf", quad), "ekf")
    y, u = np.zeros(quad.dy), np.zeros(quad.du)
    first = online.feed(MSG.encode_observation(quad, 1, 0, 0, y, u), now=0.0)[0]
    assert first.status == "estimated" and not first.nonfinite
    y[0] = np.nan
    second = online.feed(MSG.encode_observation(quad, 2, 0, 1, y, u), now=0.0)[0]
    assert second.status == "estimated" and second.nonfinite and np.isfinite(second.x_hat).all()
    u[0] = np.inf
    with pytest.raises(MessageError, match="control u_prev contains NaN or inf"):
        online.feed(MSG.encode_observation(quad, 3, 0, 2, np.zeros(quad.dy), u), now=0.0)
    assert online.step == 1  # the state untouched
