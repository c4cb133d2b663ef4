"""The message fuzzer (scripts/fuzz_nodes.py): its hostile messages through the nodes' per-message
code without ROS (fast), and a short live run of the script over three nodes (slow)."""

from __future__ import annotations

import random
import types

import numpy as np
import pytest

from conftest import load_script
from neural_estimator.stream import messages as MSG
from neural_estimator.bags.errors import MessageError
from neural_estimator.nodes import outputs as O
from neural_estimator.stream.online import OnlineEstimator
from neural_estimator.methods.registry import make_estimator
from neural_estimator.scenarios import make_scenario

pytest.importorskip("rclpy")  # the script imports the node launcher


@pytest.fixture(scope="module")
def fuzz():
    return load_script("scripts/fuzz_nodes.py")


@pytest.mark.slow  # about 10 s: 200,000-value messages among them
def test_hostile_observations_are_estimated_or_refused_in_one_line(fuzz):
    """What the estimator node's callback runs (OnlineEstimator.feed) never raises anything but
    MessageError (the node counts it), and its state stays usable."""
    scen = make_scenario(fuzz.SCENARIO)
    online = OnlineEstimator(make_estimator("ekf", scen), "ekf")
    rng = random.Random(0)
    labels = MSG.observation_labels(scen)
    outcomes = {"estimated": 0, "refused": 0, "other": 0}
    for _ in range(150):
        raw = fuzz.vector_message(rng, scen.name, labels)
        try:
            results = online.feed(raw, 0.0)
        except MessageError as exc:
            assert "\n" not in str(exc)
            outcomes["refused"] += 1
            continue
        outcomes["estimated" if any(r.status == "estimated" for r in results) else "other"] += 1
    assert outcomes["refused"] > 50 and outcomes["estimated"] >= 1, outcomes
    online.reset()
    good = MSG.encode_observation(scen, 10**18, 0, 0, np.zeros(scen.dy))
    assert online.feed(good, 0.0)[0].status == "estimated"


def test_hostile_poses_never_escape_the_set_pose_callback(fuzz):
    scen = make_scenario(fuzz.SCENARIO)
    online = OnlineEstimator(make_estimator("ukf", scen), "ukf")
    lines = []
    node = types.SimpleNamespace(
        get_logger=lambda: types.SimpleNamespace(
            warning=lambda text, throttle_duration_sec=0.0: lines.append(text), info=lines.append
        )
    )
    sp = O.SetPose(node, "", lambda: online, "map")
    rng = random.Random(1)
    parsed = 0
    for _ in range(400):
        raw = fuzz.pose_message(rng)
        try:
            msg = MSG.TYPESTORE.deserialize_cdr(raw, fuzz.POSE)  # rclpy refuses what this cannot parse
        except Exception:
            continue
        parsed += 1
        sp._on_pose(msg)  # an exception here is a dead node
    assert parsed > 200 and sp.refused > 100 and sp.refused + sp.applied == parsed
    assert all("\n" not in line for line in lines)


def test_hostile_json_is_one_line_or_a_description(fuzz):
    scen = make_scenario(fuzz.SCENARIO)
    rng = random.Random(2)
    for _ in range(200):
        raw = fuzz.json_message(rng, scen.describe())
        try:
            MSG.decode_scenario(raw)
        except MessageError as exc:
            assert "\n" not in str(exc)


@pytest.mark.slow
@pytest.mark.ros
def test_the_fuzzer_kills_no_node(fuzz, tmp_path):
    rows, deaths = fuzz.run(
        1.0, 0, {"estimator_ekf", "lifecycle_estimator", "evaluator"}, fuzz.default_domain(), tmp_path
    )
    assert deaths == 0, fuzz.table(rows)
    assert len(rows) == 5 + 3 + 6 and not any(r["outcome"].startswith("DEAD") for r in rows)
    assert {r["outcome"] for r in rows if r["node"] == "estimator_ekf" and r["input"] == "observation"} == {"counted"}


def test_hostile_robot_messages_never_escape_the_robot_estimator_path(fuzz):
    """What the robot estimator node runs per message (its fields read by the spec, the stamp, the
    Ticker) takes the fuzzer's hostile Imu / Odometry / PointStamped messages: values it reads are
    a SpecError (counted) or numbers the ticker takes, never another exception; DDS drops the
    garbage that does not deserialise (as rclpy would)."""
    from neural_estimator.robot import load_spec
    from neural_estimator.robot.dataset import message_stamp
    from neural_estimator.robot.spec import SpecError, topic_values
    from neural_estimator.robot.ticker import Ticker

    spec = load_spec(fuzz.ROOT / "examples" / "robot_spec.yaml")

    class Zeros:  # the estimator's place in the node: estimates of the spec's state width
        covariance = None

        def reset(self, batch):
            pass

        def step(self, y, u):
            assert y.shape == (1, 5)
            return np.zeros((1, 3))

    ticker = Ticker(spec, Zeros(), restart_every=30, settle_delay=1.0)
    rng = random.Random(1)
    read = refused = dropped = 0
    for _ in range(100):
        for topic, msgtype in fuzz.ROBOT_TOPICS:
            raw = fuzz.robot_message(rng, msgtype)
            try:
                msg = fuzz.TS.deserialize_cdr(raw, msgtype)
            except Exception:
                dropped += 1  # DDS would not deliver it
                continue
            try:
                values = topic_values(msg, ticker.fields[topic], msgtype)
            except SpecError as exc:
                assert "\n" not in str(exc)
                refused += 1
                continue
            ticker.push(topic, message_stamp(msg, 0, spec), values)
            read += 1
    assert read > 150 and dropped > 10, (read, refused, dropped)
