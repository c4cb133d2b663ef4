"""Hostile inputs: type names from bags and the graph become imports only when they are ROS interfaces.

A crafted package ``evilpkg`` on the path writes a marker file when imported: no check below may
let its import-time code run.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from neural_estimator.core.interfaces import InterfaceError, check_message_type, is_message_class, parse_message_type

EVIL = "evilpkg/msg/Boom"


@pytest.fixture
def evil_package(tmp_path, monkeypatch) -> Path:
    """A Python package that is not a ROS interface package and leaves a marker when imported."""
    marker = tmp_path / "imported"
    pkg = tmp_path / "site" / "evilpkg"
    (pkg / "msg").mkdir(parents=True)
    (pkg / "__init__.py").write_text(f"open({str(marker)!r}, 'w').write('ran')\n")
    (pkg / "msg" / "__init__.py").write_text("class Boom:\n    pass\n")
    monkeypatch.syspath_prepend(str(tmp_path / "site"))
    monkeypatch.delitem(sys.modules, "evilpkg", raising=False)
    monkeypatch.delitem(sys.modules, "evilpkg.msg", raising=False)
    yield marker
    assert "evilpkg" not in sys.modules or marker.exists()  # consistency of the fixture itself


@pytest.mark.parametrize(
    "name",
    [
        "sensor_msgs/Imu",
        "sensor_msgs/srv/SetCameraInfo",
        "a.b/msg/C",
        "../x/msg/Y",
        "sensor_msgs/msg/Imu; rm -rf /",
        "Sensor_msgs/msg/Imu",
        "sensor_msgs/msg/imu",
        "",
        "x" * 300 + "/msg/Y",
        None,
        42,
    ],
)
def test_malformed_type_names_are_refused_before_anything_else(name):
    with pytest.raises(InterfaceError, match="form <package>/msg/<Type>"):
        parse_message_type(name)


def test_only_types_declared_by_the_ament_index_pass():
    pytest.importorskip("sensor_msgs")
    assert check_message_type("sensor_msgs/msg/Imu") == ("sensor_msgs", "Imu")
    assert check_message_type("nav_msgs/msg/Odometry") == ("nav_msgs", "Odometry")
    with pytest.raises(InterfaceError, match="declares no message 'Nope'"):
        check_message_type("sensor_msgs/msg/Nope")
    with pytest.raises(InterfaceError, match="'numpy' is not an installed ROS interface package"):
        check_message_type("numpy/msg/Array")


def test_a_crafted_package_name_runs_no_code(evil_package):
    pytest.importorskip("rclpy")
    from neural_estimator.nodes.common import message_class

    with pytest.raises(InterfaceError, match="not an installed ROS interface package"):
        message_class(EVIL)
    assert not evil_package.exists() and "evilpkg" not in sys.modules
    assert is_message_class(message_class("sensor_msgs/msg/JointState"), "JointState")


def test_a_declared_name_must_still_be_a_rosidl_message_class(evil_package, tmp_path, monkeypatch):
    """A package the index declares (the index is trusted) still has to hold a generated message class."""
    pytest.importorskip("rclpy")
    from neural_estimator.core.interfaces import _declared
    from neural_estimator.nodes.common import message_class

    index = tmp_path / "prefix" / "share" / "ament_index" / "resource_index" / "rosidl_interfaces"
    index.mkdir(parents=True)
    (index / "evilpkg").write_text("msg/Boom.idl\nmsg/Boom.msg\n")
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(tmp_path / "prefix"))
    _declared.cache_clear()
    try:
        with pytest.raises(InterfaceError, match="is not a ROS message class"):
            message_class(EVIL)
    finally:
        _declared.cache_clear()


@pytest.fixture
def ros():
    rclpy = pytest.importorskip("rclpy")
    yield rclpy
    rclpy.try_shutdown()


def test_the_player_plays_nothing_a_bag_names_that_is_not_a_ros_interface(ros, evil_package, tmp_path):
    from neural_estimator.stream import messages as MSG
    from neural_estimator.bags.writer import BagWriter
    from neural_estimator.nodes.player_node import PlayerNode

    bag = tmp_path / "crafted.mcap"
    with BagWriter(bag) as w:
        w.add_topic("/observation", MSG.JOINT_STATE)
        w.add_topic("/evil", EVIL, msgdef="int32 x", type_hash="RIHS01_" + "0" * 64)  # as a crafted bag declares it
        w.write("/observation", 1_000, MSG.encode_vector(1_000, "", 0, 0, ["y0"], np.zeros(1)))
        w.write("/evil", 2_000, b"\x00\x01\x00\x00")
    ros.init(args=["--ros-args", "-p", f"bag:={bag}", "-p", "exit_when_done:=false"])
    node = PlayerNode()
    try:
        assert set(node.pubs) == {"/observation"}
    finally:
        node.destroy_node()
    assert not evil_package.exists() and "evilpkg" not in sys.modules


def test_the_evaluator_records_no_crafted_type_from_the_graph(ros, evil_package, tmp_path, monkeypatch):
    from neural_estimator.nodes.evaluator_node import EvaluatorNode

    ros.init(
        args=[
            "--ros-args",
            "-p",
            f"output:={tmp_path / 'rec.mcap'}",
            "-p",
            "topics:=[/evil]",
            "-p",
            "discovery_period:=100.0",
        ]
    )
    node = EvaluatorNode()
    try:
        monkeypatch.setattr(node, "get_topic_names_and_types", lambda: [("/evil", [EVIL])])
        monkeypatch.setattr(node, "get_publishers_info_by_topic", lambda name: [_FakeInfo(EVIL)])
        node._discover()
        assert "/evil" not in node.subs and "/evil" in node._refused
    finally:
        node.on_shutdown()
        node.destroy_node()
    assert not evil_package.exists() and "evilpkg" not in sys.modules


class _FakeInfo:
    """What ``get_publishers_info_by_topic`` reports for a publisher someone else started."""

    def __init__(self, topic_type: str) -> None:
        from rclpy.qos import QoSProfile

        self.topic_type = topic_type
        self.qos_profile = QoSProfile(depth=10)


# ---- bounded resources on hostile streams ------------------------------------------------------------
def test_a_description_declaring_a_huge_dimension_is_refused_before_any_allocation():
    import tracemalloc

    from neural_estimator.scenarios import ScenarioError, make_scenario, scenario_from_description
    from neural_estimator.scenarios.base import MAX_DIMENSION

    desc = make_scenario("lorenz96").describe()
    desc["config"]["n_vars"] = 10**9
    tracemalloc.start()
    try:
        with pytest.raises(ScenarioError, match=f"more than the {MAX_DIMENSION}"):
            scenario_from_description(desc)
        assert tracemalloc.get_traced_memory()[1] < 10 << 20
    finally:
        tracemalloc.stop()
    with pytest.raises(ScenarioError, match="n_links = 513 gives 1026 dimensions"):
        make_scenario("nlink", n_links=513)
    assert make_scenario("nlink", n_links=512).dx == MAX_DIMENSION


def test_an_oversized_or_deeply_nested_json_message_is_refused():
    from neural_estimator.stream import messages as MSG
    from neural_estimator.bags.errors import MessageError

    with pytest.raises(MessageError, match="larger than the"):
        MSG.decode_scenario(MSG.encode_string("x" * (MSG.MAX_JSON_BYTES + 1)))
    with pytest.raises(MessageError, match="nests JSON too deeply"):
        MSG.decode_scenario(MSG.encode_string("[" * 200_000))


@pytest.mark.slow
def test_a_jointstate_with_millions_of_entries_is_refused_before_decoding():
    import time
    import tracemalloc

    from neural_estimator.stream import messages as MSG
    from neural_estimator.bags.errors import MessageError

    codec = MSG.VectorCodec("lorenz96", [f"y{j}" for j in range(40)])
    huge = MSG.encode_vector(0, "lorenz96", 0, 0, [f"v{j}" for j in range(1_000_000)], np.zeros(1_000_000))
    tracemalloc.start()
    t0 = time.perf_counter()
    try:
        with pytest.raises(MessageError, match="larger than any valid one of this stream"):
            codec.decode(huge)
        assert tracemalloc.get_traced_memory()[1] < 1 << 20  # nothing of the message's size was built
    finally:
        tracemalloc.stop()
    assert time.perf_counter() - t0 < 1.0  # generous: the check is a length comparison
    ok = codec.encode(5, 1, 2, np.arange(40.0))
    assert codec.decode(ok).step == 2 and len(ok) <= codec.max_bytes


def test_the_estimator_node_refuses_a_hostile_scenario_and_keeps_serving(ros, tmp_path):
    from neural_estimator.stream import messages as MSG
    from neural_estimator.nodes.estimator_node import EstimatorNode
    from neural_estimator.scenarios import make_scenario

    ros.init(args=["--ros-args", "-p", "method:=ekf"])
    node = EstimatorNode()
    try:
        desc = make_scenario("lorenz96").describe()
        bad = {**desc, "config": {**desc["config"], "n_vars": 10**9}}
        node._on_scenario(MSG.encode_scenario(bad))
        node._on_scenario(MSG.encode_string("[" * 100_000))
        node._on_scenario(MSG.encode_scenario({**desc, "scenario": "no-such-scenario"}))
        assert node.online is None and node.context.ok()  # still running, still waiting
        node._on_scenario(MSG.encode_scenario(make_scenario("ballistic").describe()))
        assert node.online is not None and node.online.scenario.name == "ballistic"
        labels = MSG.observation_labels(node.online.scenario)
        huge = MSG.encode_vector(0, "ballistic", 0, 0, [f"v{j}" for j in range(200_000)], np.zeros(200_000))
        node._on_observation(huge)
        assert node.stats.oversize == 1 and node.stats.bad == 0 and node.context.ok()  # dropped unread
        node._on_observation(MSG.encode_vector(0, "ballistic", 0, 0, labels, np.zeros(len(labels))))
        assert node.stats.estimated == 1
    finally:
        node.destroy_node()


# ---- checkpoint cards someone sent you --------------------------------------------------------------
def _copy_shipped(tmp_path: Path, edit) -> Path:
    import json
    import shutil

    from neural_estimator.serving.card import default_checkpoint

    src = default_checkpoint("lorenz96", "mamba")
    dst = tmp_path / "ckpt"
    shutil.copytree(src, dst)
    card = json.loads((dst / "card.json").read_text())
    edit(card)
    (dst / "card.json").write_text(json.dumps(card))
    return dst


def test_a_card_declaring_a_huge_model_is_refused_before_allocation(tmp_path):
    import tracemalloc

    from neural_estimator.methods.registry import EstimatorError
    from neural_estimator.serving.checkpoint import load_checkpoint

    ckpt = _copy_shipped(tmp_path, lambda c: c["architecture"]["config"].update(d_model=200_000))
    with pytest.raises(EstimatorError):  # once untraced: the first meta-device build imports parts of torch
        load_checkpoint(ckpt)
    tracemalloc.start()
    try:
        with pytest.raises(EstimatorError, match="more than the"):
            load_checkpoint(ckpt)
        assert tracemalloc.get_traced_memory()[1] < 50 << 20
    finally:
        tracemalloc.stop()
    bigger = _copy_shipped(tmp_path / "b", lambda c: c["architecture"]["config"].update(d_model=400))
    with pytest.raises(EstimatorError, match="card and weights do not belong together"):
        load_checkpoint(bigger)


@pytest.mark.parametrize("name", ["../../etc/passwd", "/etc/passwd", "..", "sub/model.safetensors", 7])
def test_a_card_cannot_name_a_weight_file_outside_its_checkpoint(tmp_path, name):
    from neural_estimator.methods.registry import EstimatorError
    from neural_estimator.serving.checkpoint import load_checkpoint

    ckpt = _copy_shipped(tmp_path, lambda c: c["weights"].update(file=name))
    with pytest.raises(EstimatorError, match="must be a file name inside the checkpoint"):
        load_checkpoint(ckpt)


def test_no_message_or_card_can_name_a_plugin_to_load(tmp_path):
    """Plugins run code: only the user's explicit --plugin / plugins parameter loads one."""
    from neural_estimator.stream import messages as MSG
    from neural_estimator.scenarios import ScenarioError, make_scenario, scenario_from_description

    marker = tmp_path / "ran"
    plugin = tmp_path / "plugin.py"
    plugin.write_text(f"open({str(marker)!r}, 'w').write('ran')\n")
    desc = make_scenario("ballistic").describe()
    for crafted in (
        {**desc, "scenario": str(plugin)},
        {**desc, "scenario": "plugin", "plugins": [str(plugin)]},
        {**desc, "scenario": f"{plugin}:Scenario"},
    ):
        with pytest.raises(ScenarioError, match="unknown scenario"):
            scenario_from_description(MSG.decode_scenario(MSG.encode_scenario(crafted)))
    assert not marker.exists()
