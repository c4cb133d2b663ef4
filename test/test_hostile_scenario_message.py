"""A ``scenario`` message whose fields have the wrong types is refused where it is decoded, so a
bag recorded beside a hostile publisher still scores (the evaluator node died on one: the fuzzer's
``{"scenario": 1, "state_names": 2}`` reached ``len(desc["state_names"])`` in the bag reader)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from neural_estimator.bags import BagError, BagReader, BagWriter
from neural_estimator.bags.dataset import arrays_to_bag, bag_to_arrays
from neural_estimator.data import simulate
from neural_estimator.scenarios import make_scenario, scenario_names
from neural_estimator.stream import messages as MSG
from neural_estimator.stream.messages import MessageError


@pytest.fixture(scope="module")
def scen():
    return make_scenario("nlink")


@pytest.mark.parametrize("name", scenario_names())
def test_every_scenario_description_decodes_as_sent(name):
    desc = make_scenario(name).describe()
    back = MSG.decode_scenario(MSG.encode_scenario(desc, trajectories=2, horizon=6))
    assert {k: v for k, v in back.items() if k != "run"} == json.loads(json.dumps(desc))
    assert back["run"] == {"trajectories": 2, "horizon": 6}


@pytest.mark.parametrize(
    "change, named",
    [
        ({"scenario": 1, "state_names": 2}, "'scenario' must be a non-empty string"),
        ({"scenario": ""}, "'scenario' must be a non-empty string"),
        ({"state_names": 2}, "'state_names' must be a list of strings"),
        ({"state_names": ["a", 3]}, "'state_names' must be a list of strings"),
        ({"state_names": []}, "'state_names' is empty"),
        ({"obs_names": None}, "'obs_names' must be a list of strings"),
        ({"control_names": "u"}, "'control_names' must be a list of strings"),
        ({"angle_states": [99]}, "'angle_states' must be a list of indices below 6"),
        ({"angle_states": [True]}, "'angle_states' must be a list of indices below 6"),
        ({"angle_obs": "0"}, "'angle_obs' must be a list of indices below"),
        ({"config": []}, "'config' must be an object"),
    ],
)
def test_a_description_with_fields_of_the_wrong_type_is_one_message_error(scen, change, named):
    desc = {**scen.describe(), **change}
    with pytest.raises(MessageError, match="not a scenario description") as e:
        MSG.decode_scenario(MSG.encode_scenario(desc))
    assert named in str(e.value) and "\n" not in str(e.value)


def test_a_run_that_is_not_an_object_is_refused(scen):
    raw = MSG.encode_string(json.dumps({**scen.describe(), "run": [1, 2]}))
    with pytest.raises(MessageError, match="'run' must be an object"):
        MSG.decode_scenario(raw)


def test_missing_obs_names_is_refused(scen):
    desc = {k: v for k, v in scen.describe().items() if k != "obs_names"}
    with pytest.raises(MessageError, match="'obs_names' is missing"):
        MSG.decode_scenario(MSG.encode_scenario(desc))


def _bag_after_hostile_announcements(tmp_path, scen, hostile: list[bytes], keep_valid: bool):
    """A valid recorded run (arrays_to_bag) copied behind ``hostile`` scenario messages."""
    tr = simulate(scen, 2, 6, seed=3)
    x, y, u = tr.x, tr.y, tr.u
    src = arrays_to_bag(tmp_path / "src.mcap", scen, x, y, u, estimates={"ekf": x + 0.01})
    out = tmp_path / "hostile.mcap"
    with BagReader(src) as r, BagWriter(out) as w:
        for topic, conn in r.topics.items():
            w.add_topic(topic, conn.msgtype)
        for raw in hostile:
            w.write("/scenario", 0, raw)
        for conn, t, raw in r.messages():
            if conn.topic != "/scenario" or keep_valid:
                w.write(conn.topic, t, raw)
    return out, x


def test_a_bag_whose_first_announcement_is_hostile_scores_from_the_first_valid_one(scen, tmp_path):
    hostile = [MSG.encode_string(json.dumps({"scenario": 1, "state_names": 2})), MSG.encode_string("[]")]
    path, x = _bag_after_hostile_announcements(tmp_path, scen, hostile, keep_valid=True)
    run = bag_to_arrays(path)
    assert run.description["scenario"] == "nlink"
    assert run.rejected.get(MSG.SCENARIO) == 2
    np.testing.assert_array_equal(run.x, x)
    np.testing.assert_allclose(run.x_hat["ekf"], x + 0.01)


def test_a_bag_with_only_hostile_announcements_is_one_bag_error(scen, tmp_path):
    hostile = [MSG.encode_string(json.dumps({"scenario": 1, "state_names": 2}))]
    path, _ = _bag_after_hostile_announcements(tmp_path, scen, hostile, keep_valid=False)
    with pytest.raises(BagError, match="no /scenario message") as e:
        bag_to_arrays(path)
    assert "\n" not in str(e.value)
