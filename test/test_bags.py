"""Bags without rclpy: message layout, MCAP writer/reader, rosbags interoperability, recovery."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import dataclass

import numpy as np
import pytest
import yaml
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from neural_estimator.bags import BagError, BagReader, BagWarning, BagWriter, LATCHED_QOS, MessageError, STREAM_QOS
from neural_estimator.stream import messages as MSG
from neural_estimator.bags.dataset import arrays_to_bag, bag_to_arrays
from neural_estimator.data import simulate
from neural_estimator.scenarios import Scenario, register_scenario, scenario_from_description


@dataclass(frozen=True)
class _CartConfig:
    dt: float = 0.05
    horizon: int = 30
    noise_scale: float = 1.0


class Cart(Scenario):
    """A double integrator pushed by a force: a scenario with a control input for these tests."""

    name = "bagtest_cart"
    Config = _CartConfig
    state_names = ("position", "velocity")
    state_units = ("m", "m/s")
    obs_names = ("position",)
    obs_units = ("m",)
    control_names = ("force",)
    control_units = ("N",)

    def f(self, x, u):
        dt = self.config.dt
        return np.stack([x[..., 0] + dt * x[..., 1], x[..., 1] + dt * u[..., 0]], axis=-1)

    def h(self, x):
        return x[..., :1]

    def process_cov(self):
        return np.diag([1e-6, 1e-4])

    def obs_cov_nominal(self):
        return np.array([[0.01]])

    def prior(self):
        return np.zeros(2), np.eye(2)

    def sample_controls(self, rng, n, horizon):
        return rng.standard_normal((n, horizon, 1))


register_scenario(Cart, replace=True)


def test_no_rclpy_in_the_bag_layer():
    code = (
        "import sys, neural_estimator.bags, neural_estimator.bags.dataset;"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in ('rclpy', 'rosidl_runtime_py')))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


# ---- message layout ----------------------------------------------------------------------------------
def test_vector_round_trip_and_identity():
    raw = MSG.encode_vector(1_500_000_123, "lorenz96", 3, 41, ["a", "b"], [1.5, -2.0])
    vec = MSG.decode_vector(raw)
    assert vec.stamp_ns == 1_500_000_123 and vec.frame_id == "lorenz96"
    assert (vec.trajectory, vec.step, vec.names) == (3, 41, ("a", "b"))
    np.testing.assert_array_equal(vec.values, [1.5, -2.0])
    msg = get_typestore(Stores.ROS2_JAZZY).deserialize_cdr(raw, "sensor_msgs/msg/JointState")
    assert list(msg.name) == ["trajectory", "step", "a", "b"]
    assert msg.header.stamp.sec == 1 and msg.header.stamp.nanosec == 500_000_123
    assert len(msg.velocity) == 0 and len(msg.effort) == 0


def test_observation_layout_with_controls():
    s = Cart()
    assert MSG.observation_labels(s) == ("position", "u_prev/force")
    assert MSG.observation_labels(s.describe()) == MSG.observation_labels(s)
    raw = MSG.encode_observation(s, 10, 0, 2, [0.3], [-1.0])
    y, u_prev = MSG.split_observation(MSG.decode_vector(raw), s)
    np.testing.assert_array_equal(y, [0.3])
    np.testing.assert_array_equal(u_prev, [-1.0])
    assert MSG.covariance_labels(2) == ("P[0,0]", "P[0,1]", "P[1,0]", "P[1,1]")


@pytest.mark.parametrize(
    "raw, text",
    [
        (b"", "empty message"),
        (b"\x00\x01\x00\x00garbage", "cannot parse"),
        (MSG.encode_string("hello"), "cannot parse"),
    ],
)
def test_malformed_bytes_are_message_errors(raw, text):
    with pytest.raises(MessageError, match=text):
        MSG.decode_vector(raw)


def test_bad_identity_and_names_are_message_errors():
    ts = MSG.TYPESTORE
    J, H, T = ts.types[MSG.JOINT_STATE], ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"]
    empty = np.zeros(0)

    def raw(names, pos):
        msg = J(
            header=H(stamp=T(sec=0, nanosec=0), frame_id=""),
            name=names,
            position=np.asarray(pos, float),
            velocity=empty,
            effort=empty,
        )
        return bytes(ts.serialize_cdr(msg, MSG.JOINT_STATE))

    with pytest.raises(MessageError, match="identity"):
        MSG.decode_vector(raw(["x", "y"], [0, 1]))
    with pytest.raises(MessageError, match="empty JointState"):
        MSG.decode_vector(raw([], []))
    with pytest.raises(MessageError, match="step index"):
        MSG.decode_vector(raw(["trajectory", "step"], [0, 1.5]))
    with pytest.raises(MessageError, match="trajectory index"):
        MSG.decode_vector(raw(["trajectory", "step"], [np.nan, 1]))
    with pytest.raises(MessageError, match="3 names but 2 positions"):
        MSG.decode_vector(raw(["trajectory", "step", "a"], [0, 1]))
    vec = MSG.decode_vector(raw(["trajectory", "step", "a"], [0, 1, 2.0]))
    with pytest.raises(MessageError, match="1 values"):
        MSG.check_labels(vec, ["a", "b"], "observation")
    with pytest.raises(MessageError, match="'a' where 'z'"):
        MSG.check_labels(vec, ["z"], "observation")


def test_topics_and_namespaces():
    assert MSG.resolve_topic("observation") == "/observation"
    assert MSG.resolve_topic("estimates/ukf", "/robot1/") == "/robot1/estimates/ukf"
    assert MSG.topic_role("/estimates/ukf") == MSG.TopicRole("estimate", "ukf")
    assert MSG.topic_role("/estimates/ukf/covariance") == MSG.TopicRole("covariance", "ukf")
    assert MSG.topic_role("/robot1/observation", "/robot1") == MSG.TopicRole("observation")
    assert MSG.topic_role("/robot1/observation") is None
    assert MSG.topic_role("/rosout") is None
    assert MSG.topic_role("/estimates/ukf/other") is None


def test_scenario_and_status_messages():
    s = Cart(horizon=12)
    desc = MSG.decode_scenario(MSG.encode_scenario(s.describe(), seed=3, trajectories=2, horizon=12))
    assert desc["run"] == {"seed": 3, "trajectories": 2, "horizon": 12}
    assert scenario_from_description(desc).config == s.config
    st = MSG.decode_run_status(MSG.encode_run_status("complete", messages=24))
    assert st == {"status": "complete", "messages": 24}
    with pytest.raises(MessageError, match="not JSON"):
        MSG.decode_run_status(MSG.encode_string("{nope"))


def test_stamps_are_integer_nanoseconds():
    assert MSG.dt_ns(0.05) == 50_000_000
    assert MSG.step_stamp_ns(10**18, 3, MSG.dt_ns(0.05)) == 10**18 + 150_000_000


# ---- writer and reader -----------------------------------------------------------------------------------
def _small_bag(path, n=300, chunk_size=2048):
    rng = np.random.default_rng(0)
    written = []
    with BagWriter(path, chunk_size=chunk_size) as bag:
        bag.add_topic("/observation", MSG.JOINT_STATE, qos=[STREAM_QOS])
        bag.add_topic("/scenario", MSG.STRING, qos=[LATCHED_QOS])
        bag.write("/scenario", 1, MSG.encode_string("{}"))
        written.append(("/scenario", 1, MSG.encode_string("{}")))
        for k in range(n):
            raw = MSG.encode_vector(100 + k, "s", 0, k, ["a"], rng.standard_normal(1))
            bag.write("/observation", 100 + k, raw)
            written.append(("/observation", 100 + k, raw))
    return written


def test_writer_reader_round_trip(tmp_path):
    path = tmp_path / "run.mcap"
    written = _small_bag(path)
    with BagReader(path, strict=True) as bag:
        assert bag.damage is None
        assert bag.profile == "ros2"
        got = [(c.topic, t, raw) for c, t, raw in bag.messages()]
        conn = bag.topics["/observation"]
        assert conn.msgtype == MSG.JOINT_STATE and conn.msgcount == 300
        assert conn.message_encoding == "cdr"
        assert conn.type_hash == MSG.TYPESTORE.hash_rihs01(MSG.JOINT_STATE)
        assert "MSG: std_msgs/Header" in conn.msgdef and "builtin_interfaces/Time stamp" in conn.msgdef
        qos = yaml.safe_load(conn.offered_qos_profiles)
        assert qos[0]["reliability"] == "reliable" and qos[0]["durability"] == "transient_local"
        meta = yaml.safe_load(bag.metadata["rosbag2"]["serialized_metadata"])
        assert meta["version"] == 9 and meta["message_count"] == 301
        assert (bag.start_time, bag.end_time) == (1, 399)
        only = list(bag.messages(["/scenario"]))
        assert len(only) == 1 and only[0][0].topic == "/scenario"
        window = list(bag.messages(start=150, stop=160))
        assert [t for _, t, _ in window] == list(range(150, 160))
    assert got == written  # written in time order, read back in time order, bytes unchanged


def _chunky_bag(path, n):
    """n messages on 8 topics (the evaluator's streams) in chunks of about 2 KB: n / 10 chunks."""
    with BagWriter(path, chunk_size=2048) as bag:
        for c in range(8):
            bag.add_topic(f"/t{c}", MSG.JOINT_STATE, qos=[STREAM_QOS])
        for k in range(n):
            bag.write(f"/t{k % 8}", 100 + k, MSG.encode_vector(100 + k, "s", 0, k, ["a", "b"], np.ones(2)))
            if k == n // 10:
                yield bag
        yield bag


def test_a_long_recording_keeps_its_chunk_indexes_on_disk_not_in_memory(tmp_path, monkeypatch):
    # mcap's writer holds one ChunkIndex object (about 1 KB with 8 channels) per chunk until it
    # writes the summary at close: the evaluator's memory grew with the recording's length
    import tracemalloc

    from mcap.reader import make_reader

    from neural_estimator.bags import writer as writer_module

    n = 40_000
    tracemalloc.start()
    try:
        (tmp_path / "spilled").mkdir()
        chunky = _chunky_bag(tmp_path / "spilled" / "run.mcap", n)
        bag = next(chunky)  # a tenth of the way: every per-topic structure exists
        early, chunks_early = tracemalloc.get_traced_memory()[0], bag._spill.count
        next(chunky)  # all written, not yet closed
        late, chunks_late = tracemalloc.get_traced_memory()[0], bag._spill.count
    finally:
        tracemalloc.stop()
    list(chunky)  # closed
    per_chunk = (late - early) / (chunks_late - chunks_early)
    assert chunks_late - chunks_early > 2000
    assert per_chunk < 150, per_chunk  # bytes a chunk (the writer's own list: 670 here, 1,000 at 8 channels a chunk)

    # the same bag with the writer's own list: byte for byte the same file
    monkeypatch.setattr(writer_module, "_spill_chunk_indexes", lambda writer, directory: None)
    (tmp_path / "listed").mkdir()
    list(_chunky_bag(tmp_path / "listed" / "run.mcap", n))  # the same name: the metadata holds it
    spilled, listed = (tmp_path / "spilled" / "run.mcap").read_bytes(), (tmp_path / "listed" / "run.mcap").read_bytes()
    assert spilled == listed
    with open(tmp_path / "spilled" / "run.mcap", "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert len(summary.chunk_indexes) == summary.statistics.chunk_count == chunks_late + 1
        assert [m.log_time for _, _, m in reader.iter_messages(topics=["/t3"])] == list(range(103, 100 + n, 8))
    assert [p.name for p in (tmp_path / "spilled").iterdir()] == ["run.mcap"]  # the spill file was unlinked


def test_reader_orders_by_log_time(tmp_path):
    path = tmp_path / "shuffled.mcap"
    times = np.random.default_rng(1).permutation(200)
    with BagWriter(path, chunk_size=512) as bag:
        bag.add_topic("/x", MSG.STRING)
        for t in times:
            bag.write("/x", int(t), MSG.encode_string(str(t)))
    with BagReader(path) as bag:
        got = [(t, MSG.decode_string(raw)) for _, t, raw in bag.messages()]
    assert got == [(t, str(t)) for t in range(200)]


def test_rosbags_anyreader_reads_our_bags(tmp_path):
    s = Cart()
    data = simulate(s, 2, 10, seed=0)
    path = arrays_to_bag(
        tmp_path / "cart.mcap",
        s,
        data.x,
        data.y,
        data.u,
        estimates={"ukf": data.x + 0.1},
        covariances={"ukf": np.tile(np.eye(2), (2, 10, 1, 1))},
    )
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        topics = {c.topic: (c.msgtype, c.msgcount) for c in reader.connections}
        assert topics == {
            "/scenario": (MSG.STRING, 1),
            "/run_status": (MSG.STRING, 2),
            "/observation": (MSG.JOINT_STATE, 20),
            "/ground_truth": (MSG.JOINT_STATE, 20),
            "/estimates/ukf": (MSG.JOINT_STATE, 20),
            "/estimates/ukf/covariance": (MSG.JOINT_STATE, 20),
        }
        truth = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages() if c.topic == "/ground_truth"]
        qos = reader.connections[0].ext.offered_qos_profiles
        assert qos and qos[0].depth in (1, 1000)
    assert [list(m.name) for m in truth[:1]] == [["trajectory", "step", "position", "velocity"]]
    np.testing.assert_array_equal(np.array([m.position[2:] for m in truth]), data.x.reshape(20, 2))


def test_arrays_bag_arrays_round_trip(tmp_path):
    s = Cart()
    data = simulate(s, 3, 25, seed=4)
    P = np.tile(np.diag([0.1, 0.2]), (3, 25, 1, 1))
    path = arrays_to_bag(
        tmp_path / "run.mcap",
        s,
        data.x,
        data.y,
        data.u,
        estimates={"ekf": data.x * 0.9},
        covariances={"ekf": P},
        start_ns=10**18,
        run_info={"seed": 4},
    )
    run = bag_to_arrays(path)
    np.testing.assert_array_equal(run.x, data.x)
    np.testing.assert_array_equal(run.y, data.y)
    np.testing.assert_array_equal(run.u[:, :-1], data.u[:, :-1])  # u_{T-1} is never sent
    np.testing.assert_array_equal(run.u_prev[:, 0], 0.0)
    np.testing.assert_array_equal(run.x_hat["ekf"], data.x * 0.9)
    np.testing.assert_array_equal(run.P_hat["ekf"], P)
    assert run.methods == ["ekf"] and run.complete
    assert run.description["run"]["seed"] == 4
    assert run.scenario.config == s.config
    assert run.trajectories.tolist() == [0, 1, 2]
    assert run.stamps[0, 0] == 10**18 and run.stamps[1, 0] == 10**18 + 25 * MSG.dt_ns(s.dt)
    assert np.all(np.diff(run.stamps.reshape(-1)) > 0)  # strictly increasing within the run
    assert set(run.missing.values()) == {0} and not run.rejected and not run.duplicates


def test_bag_to_arrays_keys_by_identity_not_order(tmp_path):
    """Messages recorded in any order, one of them malformed: arrays are still right."""
    s = Cart()
    data = simulate(s, 2, 6, seed=1)
    obs_names, state_names = MSG.observation_labels(s), MSG.state_labels(s)
    items = []
    for n in range(2):
        for k in range(6):
            u_prev = data.u[n, k - 1] if k else np.zeros(1)
            items.append(("/observation", MSG.encode_vector(0, s.name, n, k, obs_names, np.r_[data.y[n, k], u_prev])))
            items.append(("/ground_truth", MSG.encode_vector(0, s.name, n, k, state_names, data.x[n, k])))
    order = np.random.default_rng(2).permutation(len(items))
    path = tmp_path / "any_order.mcap"
    with BagWriter(path) as bag:
        bag.add_topic("/scenario", MSG.STRING)
        bag.add_topic("/observation", MSG.JOINT_STATE)
        bag.add_topic("/ground_truth", MSG.JOINT_STATE)
        bag.write("/scenario", 0, MSG.encode_scenario(s.describe(), trajectories=2, horizon=6))
        for t, i in enumerate(order):
            bag.write(items[i][0], t + 1, items[i][1])
        bag.write("/observation", 999, MSG.encode_vector(0, s.name, 0, 0, ["wrong"], [1.0]))
        bag.write("/observation", 1000, items[0][1])  # a duplicate
    run = bag_to_arrays(path)
    np.testing.assert_array_equal(run.x, data.x)
    np.testing.assert_array_equal(run.y, data.y)
    assert run.rejected == {"observation": 1} and run.duplicates == {"observation": 1}
    assert not run.complete and run.missing["observation"] == 0


# ---- damage and errors ------------------------------------------------------------------------------------
def test_truncated_bag_recovers_complete_chunks(tmp_path):
    s = Cart()
    data = simulate(s, 4, 30, seed=2)
    full = arrays_to_bag(tmp_path / "full.mcap", s, data.x, data.y, data.u, estimates={"ukf": data.x}, chunk_size=2048)
    blob = full.read_bytes()
    with BagReader(full) as bag:
        total = bag.message_count
    for frac in (0.3, 0.5):
        cut = tmp_path / f"cut{frac}.mcap"
        cut.write_bytes(blob[: int(len(blob) * frac)])
        with pytest.warns(BagWarning, match="Recovered"):
            with BagReader(cut) as bag:
                damage = bag.damage
                msgs = list(bag.messages())
        assert damage is not None and 0 < len(msgs) < total
        assert damage.messages_recovered == len(msgs) and damage.chunks_lost <= 1
        assert damage.lost_bytes > 0 and damage.file_size == cut.stat().st_size
        assert damage.lost_span_ns is None or damage.lost_span_ns[0] <= damage.lost_span_ns[1]
        assert "damaged or unfinished bag" in str(damage) and f"file ends at byte {damage.file_size}" in str(damage)
        with pytest.raises(BagError, match="damaged or unfinished"):
            BagReader(cut, strict=True).open()
        with pytest.warns(BagWarning):
            run = bag_to_arrays(cut)
        # everything recovered is exact; the lost tail is NaN and counted
        got = ~np.isnan(run.x[..., 0])
        assert got.any() and run.missing["ground_truth"] == got.size - got.sum() > 0
        np.testing.assert_array_equal(run.x[got], data.x[got])
        assert not run.complete  # the final run_status was in the lost tail

    # cut inside the summary: every message is still there, the damage says so
    cut = tmp_path / "cut_summary.mcap"
    cut.write_bytes(blob[:-30])
    with pytest.warns(BagWarning, match="summary"):
        with BagReader(cut) as bag:
            assert bag.message_count == total and bag.damage.chunks_lost == 0


def test_corrupt_chunk_is_skipped_and_reading_resumes(tmp_path):
    path = tmp_path / "run.mcap"
    _small_bag(path, n=400, chunk_size=1024)
    blob = bytearray(path.read_bytes())
    # find the third chunk record (opcode 0x06) by walking the records
    pos, chunks = 8, []
    while pos < len(blob):
        op, length = blob[pos], int.from_bytes(blob[pos + 1 : pos + 9], "little")
        if op == 0x06:
            chunks.append((pos, length))
        if op == 0x0F:
            break
        pos += 9 + length
    at, length = chunks[2]
    blob[at + 9 + length - 20 : at + 9 + length - 10] = b"\xff" * 10  # damage its compressed data
    path.write_bytes(bytes(blob))
    with pytest.warns(BagWarning, match="chunk at byte"):
        with BagReader(path) as bag:
            n = len(list(bag.messages()))
            assert bag.damage.chunks_lost == 1 and bag.damage.chunks_recovered == len(chunks) - 1
    assert 0 < n < 401


def test_wrong_type_topic_is_an_error(tmp_path):
    path = tmp_path / "wrong.mcap"
    with BagWriter(path) as bag:
        bag.add_topic("/observation", MSG.STRING)
        bag.write("/observation", 1, MSG.encode_string("not a vector"))
    with pytest.raises(BagError, match="'/observation' holds std_msgs/msg/String, expected sensor_msgs/msg/JointState"):
        bag_to_arrays(path)
    with BagReader(path) as bag:
        with pytest.raises(BagError, match="holds std_msgs/msg/String"):
            bag.connection("/observation", MSG.JOINT_STATE)
        with pytest.raises(BagError, match="no topic '/ground_truth'"):
            bag.connection("/ground_truth")


def test_unreadable_files_are_bag_errors(tmp_path):
    with pytest.raises(BagError, match="no such bag file"):
        BagReader(tmp_path / "missing.mcap").open()
    (tmp_path / "empty.mcap").write_bytes(b"")
    with pytest.raises(BagError, match="empty file"):
        BagReader(tmp_path / "empty.mcap").open()
    (tmp_path / "text.mcap").write_text(json.dumps({"not": "mcap"}))
    with pytest.raises(BagError, match="not an MCAP file"):
        BagReader(tmp_path / "text.mcap").open()


def test_writer_refuses_misuse(tmp_path):
    with pytest.raises(BagError, match="must end in .mcap"):
        BagWriter(tmp_path / "x.bag")
    path = tmp_path / "a.mcap"
    with BagWriter(path) as bag:
        with pytest.raises(BagError, match="absolute topic names"):
            bag.add_topic("observation", MSG.JOINT_STATE)
        with pytest.raises(BagError, match="not declared"):
            bag.write("/nope", 0, b"")
        bag.add_topic("/a", MSG.STRING)
        with pytest.raises(BagError, match="already holds"):
            bag.add_topic("/a", MSG.JOINT_STATE)
        with pytest.raises(BagError, match="not in the ROS 2 Jazzy type store"):
            bag.add_topic("/b", "my_msgs/msg/Thing")
    with pytest.raises(BagError, match="file exists"):
        BagWriter(path).open()
    with BagWriter(path, overwrite=True) as bag:
        bag.write_message("/s", 5, MSG.TYPESTORE.types[MSG.STRING](data="hi"))
    with BagReader(path) as bag:
        assert [(c.topic, MSG.decode_string(r)) for c, _, r in bag.messages()] == [("/s", "hi")]
        ((conn, _, msg),) = list(bag.decoded())
        assert msg.data == "hi"


def test_writer_closes_file_when_body_raises(tmp_path):
    path = tmp_path / "err.mcap"
    with pytest.raises(RuntimeError):
        with BagWriter(path) as bag:
            bag.add_topic("/x", MSG.STRING)
            bag.write("/x", 1, MSG.encode_string("kept"))
            raise RuntimeError("boom")
    with BagReader(path, strict=True) as bag:  # complete, not damaged
        assert bag.message_count == 1


# ---- evaluation inputs and offline replay ----------------------------------------------------------------
def test_load_bag_dataset_and_report(tmp_path):
    from neural_estimator.bags import load_bag_dataset
    from neural_estimator.evaluation.bag_report import evaluate_bag, write_report

    s = Cart()
    data = simulate(s, 3, 20, seed=5)
    est = data.x + 0.05
    path = arrays_to_bag(
        tmp_path / "run.mcap",
        s,
        data.x,
        data.y,
        data.u,
        estimates={"a": est, "b": est * 1.1},
        covariances={"a": np.tile(np.eye(2), (3, 20, 1, 1))},
    )
    truth, estimates, angles = load_bag_dataset(path)
    assert truth.x.shape == (3, 20, 2) and set(estimates) == {"a", "b"} and angles == ()
    np.testing.assert_array_equal(estimates["a"][0], est)
    assert estimates["b"][1] is None and estimates["a"][1].shape == (3, 20, 2, 2)
    assert truth.meta["bag"]["left_out"] == []

    report = evaluate_bag(path)
    np.testing.assert_allclose(report.reports["a"].rmse, 0.05)
    assert report.reports["a"].nees is not None and report.reports["b"].nees is None
    assert "a" in report.table() and "RMSE" in report.summary()
    consistency = [line.split()[0] for line in report.consistency().splitlines()]
    assert consistency == ["Method", "a"] and "Verdict" in report.summary()  # the stream with a covariance
    paths = write_report(report)
    assert paths["markdown"].name == "run.metrics.md" and paths["png"].stat().st_size > 0
    assert json.loads(paths["json"].read_text())["methods"]["a"]["rmse"] == pytest.approx(0.05)
    assert report.warmup == 10 and report.reports["a"].rmse_t.shape == (10,)  # steps 10..19 scored
    assert "(steps 10.. scored)" in report.summary() and json.loads(paths["json"].read_text())["warmup"] == 10


def test_bag_report_warmup_and_runs_shorter_than_it(tmp_path):
    from neural_estimator.evaluation.bag_report import evaluate_bag
    from neural_estimator.metrics import MetricsError

    s = Cart()
    data = simulate(s, 2, 8, seed=1)
    est = data.x.copy()
    est[:, :2] += 1.0  # large errors in the first two steps only
    path = arrays_to_bag(tmp_path / "short.mcap", s, data.x, data.y, data.u, estimates={"a": est})
    assert evaluate_bag(path, warmup=2).reports["a"].rmse == pytest.approx(0.0)
    assert evaluate_bag(path, warmup=0).reports["a"].rmse == pytest.approx(np.sqrt(2 / 8))
    with pytest.raises(MetricsError, match="warmup must be an integer in \\[0, 8\\)"):
        evaluate_bag(path)  # 8 steps: nothing left after the 10-step warm-up
    short = evaluate_bag(path, short_runs="score_all")  # the evaluator node: say so, keep the table
    assert short.warmup == 0 and short.reports["a"].rmse == pytest.approx(np.sqrt(2 / 8))
    assert "every step scored: the run has 8 steps, not more than the 10-step warm-up" in short.summary()


def test_incomplete_trajectories_are_left_out_for_every_method(tmp_path):
    from neural_estimator.bags import load_bag_dataset

    s = Cart()
    data = simulate(s, 2, 5, seed=0)
    path = tmp_path / "gappy.mcap"
    arrays_to_bag(path, s, data.x, data.y, data.u, estimates={"a": data.x})
    with BagReader(path) as bag:  # copy without the estimate of trajectory 1, step 3
        msgs = [(c, t, r) for c, t, r in bag.messages()]
    gappy = tmp_path / "gappy2.mcap"
    with BagWriter(gappy) as out:
        for c, t, raw in msgs:
            if c.topic == "/estimates/a" and MSG.decode_vector(raw)[2:4] == (1, 3):
                continue
            if not out.has_topic(c.topic):
                out.add_topic(c.topic, c.msgtype)
            out.write(c.topic, t, raw)
    truth, estimates, _ = load_bag_dataset(gappy)
    assert truth.n == 1 and truth.meta["bag"]["left_out"] == [1]
    assert truth.meta["bag"]["missing"]["estimates/a"] == 1
    # a diverged (NaN) estimate is present, not missing
    nan_est = data.x.copy()
    nan_est[0, 2:] = np.nan
    truth, estimates, _ = load_bag_dataset(
        arrays_to_bag(tmp_path / "nan.mcap", s, data.x, data.y, data.u, estimates={"a": nan_est})
    )
    assert truth.n == 2 and np.isnan(estimates["a"][0][0, 2:]).all()


def test_replay_equals_run_and_reads_any_order(tmp_path):
    from neural_estimator.methods.registry import make_estimator
    from neural_estimator.evaluation.replay import replay

    s = Cart()
    data = simulate(s, 2, 15, seed=6)
    src = arrays_to_bag(tmp_path / "src.mcap", s, data.x, data.y, data.u, estimates={"ukf": np.zeros_like(data.x)})
    with BagReader(src) as bag:  # shuffle the recording order of the observations, add a bad one
        msgs = [(c.topic, c.msgtype, t, r) for c, t, r in bag.messages()]
    order = np.random.default_rng(0).permutation(len(msgs))
    shuffled = tmp_path / "shuffled.mcap"
    with BagWriter(shuffled) as out:
        for topic, msgtype, _, _ in msgs:
            if not out.has_topic(topic):
                out.add_topic(topic, msgtype)
        for t, i in enumerate(order):
            out.write(msgs[i][0], t, msgs[i][3])
        out.write("/observation", len(msgs), MSG.encode_vector(0, s.name, 0, 3, ["bad"], [1.0]))
    res = replay(shuffled, ["ekf", "ukf"], tmp_path / "out.mcap", order="identity")
    assert res.estimates == {"ekf": 30, "ukf": 30} and res.rejected == {"ekf": 1, "ukf": 1}
    assert res.per_step_us("ekf") > 0
    run = bag_to_arrays(res.path)
    assert run.received["estimates/ukf"] == 30 and run.received["estimates/ukf/covariance"] == 30
    for m in ("ekf", "ukf"):
        ref = make_estimator(m, s).run(data.y, data.u)
        np.testing.assert_allclose(run.x_hat[m], ref.x, rtol=0, atol=1e-10)
        np.testing.assert_allclose(run.P_hat[m], ref.cov, rtol=0, atol=1e-10)
    with pytest.raises(BagError, match="cannot overwrite its input"):
        replay(shuffled, ["ekf"], shuffled)


def test_online_estimator_stream_rules():
    from neural_estimator.methods.registry import make_estimator
    from neural_estimator.stream.online import OnlineEstimator

    s = Cart()
    data = simulate(s, 1, 8, seed=2)
    online = OnlineEstimator(make_estimator("ekf", s), "ekf")

    def obs(k, y=None, u=None, n=0):
        y = data.y[0, k] if y is None else y
        u = (data.u[0, k - 1] if k else np.zeros(1)) if u is None else u
        return MSG.encode_observation(s, k, n, k, y, u)

    def feed(raw):
        return [r.status for r in online.feed(raw, 0.0)]

    assert feed(obs(0)) == ["estimated"]
    assert feed(obs(0)) == ["duplicate"]
    assert feed(obs(3)) == ["held"]  # a jump: held until the next message agrees
    assert feed(obs(4, y=[np.nan])) == ["unconfirmed"]  # no observation, no evidence: never a confirmation
    r = online.feed(obs(4), 0.0)
    assert [x.status for x in r] == ["estimated", "estimated"] and r[0].filled == 2
    assert feed(obs(2)) == ["held"]  # late: held, then dropped as stale once the stream goes on
    for bad in (b"", obs(5, u=[np.nan]), MSG.encode_vector(0, s.name, 0, 5, ["position"], [0.0])):
        with pytest.raises(MessageError):
            online.feed(bad)
    assert online.step == 4  # bad messages change nothing
    r = online.feed(obs(5, y=[np.nan]), 0.0)  # the stream's next step without an observation: predict only
    assert [x.status for x in r] == ["estimated"] and r[0].nonfinite and np.isfinite(r[0].x_hat).all()
    assert feed(obs(6)) == ["estimated", "stale"]
    assert feed(obs(0, n=1)) == ["held"]
    online.max_gap = 2
    r = online.feed(obs(7, n=1), 0.0)
    assert [x.status for x in r] == ["estimated", "estimated"] and r[0].reset and r[1].restarted


@pytest.mark.parametrize("frame", ["", "a", "abcd", "lorenz96"])
@pytest.mark.parametrize(
    "names", [[], ["a"], ["ab", "c"], ["position", "u_prev/force"], list(MSG.covariance_labels(3))]
)
def test_vector_codec_equals_the_rosbags_serializer(frame, names):
    codec = MSG.VectorCodec(frame, names)
    values = np.random.default_rng(len(names)).standard_normal(len(names))
    for stamp in (0, 1_500_000_123, 10**18 + 7):
        ref = MSG.encode_vector(stamp, frame, 3, 17, names, values)
        assert codec.encode(stamp, 3, 17, values) == ref
        fast, slow = codec.decode(ref), MSG.decode_vector(ref)
        assert fast[:5] == slow[:5] and np.array_equal(fast.values, slow.values)
    other = MSG.encode_vector(5, frame, 0, 1, ["zz"] * (len(names) + 1), np.zeros(len(names) + 1))
    assert codec.decode(other).names == ("zz",) * (len(names) + 1)  # the fallback reads any layout
    with pytest.raises(MessageError, match="empty message"):
        codec.decode(b"")
