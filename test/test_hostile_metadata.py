"""Recorded QoS metadata (``offered_qos_profiles``) is untrusted: every field is validated, a refusal
is one line naming the topic and the field, ``replay`` and ``recover`` finish with the topic's
messages and default QoS, and nothing out of bounds is copied into their output."""

from __future__ import annotations

import time
import warnings

import pytest

from neural_estimator.stream import messages as MSG
from neural_estimator.bags.errors import BagWarning
from neural_estimator.bags.reader import BagReader
from neural_estimator.bags.writer import (
    QOS_DEPTH_MAX,
    QOS_TEXT_MAX,
    STREAM_QOS,
    BagWriter,
    Qos,
    QosError,
    parse_qos_yaml,
    qos_yaml,
)

DEEP = 5000
HOSTILE = {
    "string depth": "- depth: deep\n",
    "nested 5000 deep": "- " + "[" * DEEP + "]" * DEEP + "\n",
    "block-nested 5000 deep": "".join("  " * i + "a:\n" for i in range(DEEP)),
    "depth 1e12": "- history: keep_last\n  depth: 1000000000000\n",
    "negative depth": "- depth: -1\n",
    "float depth": "- depth: 10.5\n",
    "unknown reliability": "- reliability: sometimes\n",
    "nsec of 2e9": "- deadline: {sec: 1, nsec: 2000000000}\n",
    "huge sec": "- lifespan: {sec: 99999999999999999999, nsec: 0}\n",
    "a mapping, not a list": "depth: 10\n",
    "too many profiles": "- {depth: 1}\n" * 65,
    "over the size bound": "- depth: 10\n" + "#" * QOS_TEXT_MAX,
    "not YAML": "- [unclosed\n",
}


@pytest.mark.parametrize("case", sorted(HOSTILE))
def test_hostile_qos_text_is_refused_in_one_line_and_fast(case):
    t0 = time.perf_counter()
    with pytest.raises(QosError) as info:
        parse_qos_yaml(HOSTILE[case])
    assert time.perf_counter() - t0 < 5.0  # linear: milliseconds (a bound far above, not a timing)
    assert "\n" not in str(info.value) and "offered_qos_profiles" in str(info.value)


def test_valid_profiles_round_trip_v9_and_v8():
    profiles = [STREAM_QOS, Qos(reliability="best_effort", depth=QOS_DEPTH_MAX, deadline=(1, 500))]
    assert parse_qos_yaml(qos_yaml(profiles)) == profiles
    v8 = "- history: 1\n  depth: 5\n  reliability: 2\n  durability: 1\n  liveliness: 1\n"
    assert parse_qos_yaml(v8) == [
        Qos(history="keep_last", depth=5, reliability="best_effort", durability="transient_local")
    ]
    assert parse_qos_yaml("") == []


def _bag_with_qos(path, text):
    """A small scored bag whose /observation channel carries ``text`` as its QoS metadata."""
    import neural_estimator.bags.writer as W

    src = BagReader(MSG.__file__.replace("neural_estimator/stream/messages.py", "bags/lorenz96.mcap")).open()
    real = W.qos_yaml
    try:
        W.qos_yaml = lambda profiles: text if profiles == [Qos(depth=7)] else real(profiles)
        with BagWriter(path) as out:
            for conn in src.connections:
                out.add_topic(conn.topic, conn.msgtype, qos=[Qos(depth=7)] if conn.topic == "/observation" else [])
            for conn, t, raw in src.messages():
                out.write(conn.topic, t, raw)
    finally:
        W.qos_yaml = real
        src.close()


@pytest.mark.parametrize("case", ["string depth", "nested 5000 deep", "depth 1e12"])
def test_replay_and_recover_finish_and_copy_nothing_absurd(tmp_path, case):
    from neural_estimator.bags.recover import recover_bag
    from neural_estimator.evaluation.replay import replay

    bag = tmp_path / "hostile.mcap"
    _bag_with_qos(bag, HOSTILE[case])
    with BagReader(bag) as r:  # the hostile text really is in the bag
        assert r.topics["/observation"].offered_qos_profiles == HOSTILE[case]
    for run in (
        lambda out: recover_bag(bag, out),
        lambda out: replay(bag, ["ekf"], out),
    ):
        out = tmp_path / "out.mcap"
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", BagWarning)
            run(out)
        lines = [str(w.message) for w in caught if "recorded QoS ignored" in str(w.message)]
        assert len(lines) == 1 and "/observation" in lines[0] and "\n" not in lines[0], lines
        with BagReader(out) as r:
            copied = r.topics["/observation"]
            assert copied.msgcount == 400  # every message kept
            assert parse_qos_yaml(copied.offered_qos_profiles) == []  # no profile, not the hostile one
            assert "1000000000000" not in copied.offered_qos_profiles
        out.unlink()


@pytest.mark.parametrize(
    "text",
    [
        "rate: 10\nobservation: " + "[" * 5000 + "]" * 5000 + "\n",  # flow nesting
        "rate: 10\nobservation: " + "{a: " * 5000 + "1" + "}" * 5000 + "\n",
        "".join(" " * i + "a:\n" for i in range(1200)),  # block nesting
    ],
    ids=["flow list", "flow mapping", "block mapping"],
)
def test_a_deeply_nested_robot_spec_is_one_line_in_linear_time(tmp_path, text):
    from neural_estimator.robot import SpecError, load_spec

    path = tmp_path / "spec.yaml"
    path.write_text(text)
    t0 = time.perf_counter()
    with pytest.raises(SpecError, match="nesting depth") as info:
        load_spec(path)
    assert time.perf_counter() - t0 < 5.0  # milliseconds through libyaml (the bound is not a timing)
    assert "\n" not in str(info.value) and str(path) in str(info.value)


def _bag_with_schema(path, schema_bytes: int) -> None:
    """The sample bag with ``schema_bytes`` of schema text for its /observation type."""
    src = BagReader(MSG.__file__.replace("neural_estimator/stream/messages.py", "bags/lorenz96.mcap")).open()
    try:
        with BagWriter(path) as out:
            for conn in src.connections:
                huge = conn.topic == "/observation"
                text = conn.msgdef + "\n#" + "x" * schema_bytes if huge else None
                out.add_topic(conn.topic, conn.msgtype, msgdef=text, type_hash=conn.type_hash if huge else None)
            for conn, t, raw in src.messages():
                out.write(conn.topic, t, raw)
    finally:
        src.close()


def test_an_oversized_schema_is_not_read_and_said_in_one_line(tmp_path):
    import tracemalloc

    from neural_estimator.bags.reader import MAX_SCHEMA_BYTES

    bag = tmp_path / "schema.mcap"
    _bag_with_schema(bag, 50 * 2**20)
    tracemalloc.start()
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", BagWarning)
            with BagReader(bag) as r:
                conn = r.topics["/observation"]
                decoded = sum(1 for _ in r.decoded(["/observation"]))  # the Jazzy store knows JointState
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert conn.msgdef == "" and decoded == 400
    lines = [str(w.message) for w in caught]
    assert len(lines) == 1 and f"over the bound of {MAX_SCHEMA_BYTES:,}" in lines[0] and "\n" not in lines[0]
    # the text is neither copied nor decoded: the peak is the one decompressed chunk that holds it
    # (bounded by max_chunk_bytes), 50.0 MiB measured; copying and decoding it had peaked at 200.0 MiB
    assert peak < 1.5 * 50 * 2**20, peak


def test_a_schema_within_the_bound_is_kept(tmp_path):
    bag = tmp_path / "schema.mcap"
    _bag_with_schema(bag, 100_000)
    with warnings.catch_warnings():
        warnings.simplefilter("error", BagWarning)
        with BagReader(bag) as r:
            assert len(r.topics["/observation"].msgdef) > 100_000


def test_infinite_durations_as_each_rosbag2_release_records_them():
    for sec, nsec in ((9223372036, 854775807), (2147483647, 4294967295), (0, 0)):
        text = f"- deadline: {{sec: {sec}, nsec: {nsec}}}\n  lifespan: {{sec: 0, nsec: 5}}\n"
        assert parse_qos_yaml(text) == [Qos(deadline=None, lifespan=(0, 5))]
