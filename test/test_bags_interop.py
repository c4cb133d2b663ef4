"""Bags from other tools and hostile inputs: rosbag2 directories, bags without /scenario, recover,
no silent empty metrics, stream identity (stray messages, step jumps), replay threads and options."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from neural_estimator import cli
from neural_estimator.bags import BagWriter, STREAM_QOS, arrays_to_bag, bag_to_arrays, open_bag
from neural_estimator.stream import messages as MSG
from neural_estimator.data import simulate
from neural_estimator.methods.registry import make_estimator
from neural_estimator.stream.online import OnlineEstimator
from neural_estimator.evaluation.replay import replay
from neural_estimator.scenarios import make_scenario

SCEN = "bearings"
N, T = 2, 12


@pytest.fixture(scope="module")
def scen():
    return make_scenario(SCEN)


@pytest.fixture(scope="module")
def data(scen):
    return simulate(scen, N, T, seed=4)


def _stream_messages(scen, data, start_ns=10**18):
    """(topic, t, raw) of observation and ground truth, as the simulator publishes them."""
    obs_codec = MSG.VectorCodec(scen.name, MSG.observation_labels(scen))
    truth_codec = MSG.VectorCodec(scen.name, MSG.state_labels(scen))
    period = MSG.dt_ns(scen.dt)
    out = []
    for n in range(N):
        for k in range(T):
            t = MSG.step_stamp_ns(start_ns, n * T + k, period)
            u_prev = data.u[n, k - 1] if k else np.zeros(scen.du)
            out.append(("/observation", t, obs_codec.encode(t, n, k, np.concatenate([data.y[n, k], u_prev]))))
            out.append(("/ground_truth", t, truth_codec.encode(t, n, k, data.x[n, k])))
    return out


def _rosbags_directory(path, msgs, split=2):
    """A rosbag2 directory (metadata.yaml + ``split`` .mcap files) written by rosbags, no /scenario."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    store = get_typestore(Stores.ROS2_JAZZY)
    parts = np.array_split(np.arange(len(msgs)), split)
    # rosbags writes one file per bag; a split recording is several bags' files under one metadata
    files = []
    for i, idx in enumerate(parts):
        sub = path.parent / f"{path.name}_part{i}"
        with Writer(sub, version=9, storage_plugin=StoragePlugin.MCAP) as w:
            conns = {
                t: w.add_connection(t, MSG.JOINT_STATE, typestore=store) for t in ("/observation", "/ground_truth")
            }
            for j in idx:
                topic, t, raw = msgs[j]
                w.write(conns[topic], t, raw)
        files.append(next(sub.glob("*.mcap")))
    import shutil

    import yaml

    path.mkdir()
    meta = yaml.safe_load((path.parent / f"{path.name}_part0" / "metadata.yaml").read_text())
    names = []
    for i, f in enumerate(files):
        name = f"{path.name}_{i}.mcap"
        shutil.move(str(f), path / name)
        names.append(name)
    meta["rosbag2_bagfile_information"]["relative_file_paths"] = names
    (path / "metadata.yaml").write_text(yaml.safe_dump(meta))
    return path


# ---- rosbag2 directories and bags without /scenario ------------------------------------------------------------
def test_rosbag2_directory_without_scenario_replays_and_scores(scen, data, tmp_path, capsys):
    bag = _rosbags_directory(tmp_path / "rec", _stream_messages(scen, data), split=2)
    with open_bag(bag) as reader:
        assert reader.topics["/observation"].msgcount == N * T and len(reader.parts) == 2
        times = [t for _, t, _ in reader.messages()]
        assert times == sorted(times)
    with pytest.raises(Exception, match="no /scenario"):
        replay(bag, ["ukf"], tmp_path / "x.mcap")
    assert cli.main(["replay", str(bag), "--methods", "ukf", "--out", str(tmp_path / "out.mcap")]) == 2
    assert "--scenario" in capsys.readouterr().err
    out = tmp_path / "out.mcap"
    assert (
        cli.main(["replay", str(bag), "--methods", "ekf,ukf", "--scenario", SCEN, "--out", str(out), "--metrics"]) == 0
    )
    text = capsys.readouterr().out
    assert "ekf" in text and "ukf" in text and f"{N} trajectories" in text
    ref = make_estimator("ukf", scen).run(data.y, data.u)
    np.testing.assert_allclose(bag_to_arrays(out).x_hat["ukf"], ref.x, rtol=0, atol=1e-10)
    # the replayed output names its scenario; the input directory still needs --scenario for metrics
    assert bag_to_arrays(out).description["scenario"] == SCEN
    assert cli.main(["metrics", str(bag), "--scenario", SCEN]) == 2
    assert "no estimate stream" in capsys.readouterr().err


def test_mcap_ros2_written_bag_is_read(scen, data, tmp_path, capsys):
    from mcap_ros2.writer import Writer

    store = get_typestore(Stores.ROS2_JAZZY)
    msgdef = store.generate_msgdef(MSG.JOINT_STATE, ros_version=2)[0]
    path = tmp_path / "mcap_ros2.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        schema = w.register_msgdef(MSG.JOINT_STATE, msgdef)
        ukf = make_estimator("ukf", scen).run(data.y, data.u).x
        for topic, t, raw in _stream_messages(scen, data):
            vec = MSG.decode_vector(raw)
            w.write_message(topic, schema, _as_dict(vec), log_time=t, publish_time=t)
            if topic == "/observation":
                est = {**_as_dict(vec), "header": {"stamp": _stamp(t), "frame_id": "ukf"}}
                est["name"] = list(MSG.ID_NAMES) + list(MSG.state_labels(scen))
                est["position"] = [vec.trajectory, vec.step] + list(ukf[vec.trajectory, vec.step])
                w.write_message("/estimates/ukf", schema, est, log_time=t + 1, publish_time=t + 1)
        w.finish()
    run = bag_to_arrays(path, description=scen.describe())
    np.testing.assert_array_equal(run.x, data.x)
    assert cli.main(["metrics", str(path), "--scenario", SCEN, "--json"]) == 0
    assert '"ukf"' in capsys.readouterr().out


def _stamp(t):
    return {"sec": t // 10**9, "nanosec": t % 10**9}


def _as_dict(vec):
    return {
        "header": {"stamp": _stamp(vec.stamp_ns), "frame_id": vec.frame_id},
        "name": list(MSG.ID_NAMES) + list(vec.names),
        "position": [vec.trajectory, vec.step] + list(vec.values),
        "velocity": [],
        "effort": [],
    }


# ---- recover ---------------------------------------------------------------------------------------------------
def test_recover_makes_a_killed_recording_readable_by_every_tool(scen, data, tmp_path, capsys):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    from rosbags.highlevel import AnyReader

    full = arrays_to_bag(tmp_path / "full.mcap", scen, data.x, data.y, data.u, chunk_size=2048)
    cut = tmp_path / "cut.mcap"
    raw = full.read_bytes()
    cut.write_bytes(raw[: int(len(raw) * 0.6)])  # what SIGKILL leaves: no summary, a half chunk
    with pytest.raises(Exception):
        with open(cut, "rb") as f:
            list(make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages())
    fixed = tmp_path / "fixed.mcap"
    assert cli.main(["recover", str(cut), "--out", str(fixed)]) == 0
    out = capsys.readouterr().out
    assert "wrote" in out and "lost" in out
    with warnings.catch_warnings(record=True):
        warnings.simplefilter("always")
        expected = sum(c.msgcount for c in open_bag(cut).open().connections)
    assert 0 < expected < 2 * N * T + 3
    with open(fixed, "rb") as f:
        decoded = list(make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages())
    assert len(decoded) == expected
    with AnyReader([fixed]) as r:
        assert sum(1 for _ in r.messages()) == expected
    with open_bag(fixed, strict=True) as r:  # and our reader sees no damage now
        assert r.message_count == expected and r.damage is None
    assert cli.main(["recover", str(cut), "--out", str(cut)]) == 2
    assert "cannot overwrite its input" in capsys.readouterr().err


# ---- no silent empty answers -------------------------------------------------------------------------------------
def test_metrics_never_prints_an_empty_table(scen, data, tmp_path, capsys):
    no_est = arrays_to_bag(tmp_path / "noest.mcap", scen, data.x, data.y, data.u)
    assert cli.main(["metrics", str(no_est)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no estimate stream" in err
    # a cut bag whose estimate stream is gone from the complete trajectories
    ukf = make_estimator("ukf", scen).run(data.y, data.u).x
    ekf = make_estimator("ekf", scen).run(data.y, data.u).x
    both = arrays_to_bag(tmp_path / "both.mcap", scen, data.x, data.y, data.u, estimates={"ukf": ukf, "ekf": ekf})
    with open_bag(both) as r:
        msgs = [(c.topic, c.msgtype, t, raw) for c, t, raw in r.messages()]
    partial = tmp_path / "partial.mcap"
    with BagWriter(partial) as w:  # ekf's stream stopped after step 0 (a cut recording); ukf complete
        for topic, msgtype, t, raw in msgs:
            if not w.has_topic(topic):
                w.add_topic(topic, msgtype, qos=[STREAM_QOS])
            if topic == "/estimates/ekf":
                vec = MSG.decode_vector(raw)
                if vec.step > 0:
                    continue
            w.write(topic, t, raw)
    assert cli.main(["metrics", str(partial)]) == 0
    cap = capsys.readouterr()
    assert "ukf" in cap.out and "ekf" not in cap.out.split("\n", 1)[1]
    assert "method ekf left out" in cap.err and f"{N} trajectories" in cap.out
    only_ekf = tmp_path / "only_ekf.mcap"
    with BagWriter(only_ekf) as w:
        for topic, msgtype, t, raw in msgs:
            if topic.startswith("/estimates/ukf"):
                continue
            if not w.has_topic(topic):
                w.add_topic(topic, msgtype, qos=[STREAM_QOS])
            if topic == "/estimates/ekf" and MSG.decode_vector(raw).step > 3:
                continue
            w.write(topic, t, raw)
    assert cli.main(["metrics", str(only_ekf)]) == 2
    assert "no trajectory is complete" in capsys.readouterr().err


# ---- stream identity ---------------------------------------------------------------------------------------------
def _obs(scen, data, n, k, start_ns=10**18):
    t = MSG.step_stamp_ns(start_ns, n * T + k, MSG.dt_ns(scen.dt))
    u_prev = data.u[n, k - 1] if k else np.zeros(scen.du)
    return MSG.encode_observation(scen, t, n, k, data.y[n, k], u_prev)


def _run(online, raws, now=0.0):
    """Every result of feeding ``raws`` (no quarantine time-outs), then the flush at the end."""
    out = []
    for raw in raws:
        out += online.feed(raw, now)
    return out + online.flush()


def _estimates(results):
    return [(r.trajectory, r.step) for r in results if r.status == "estimated"], np.array(
        [r.x_hat for r in results if r.status == "estimated"]
    )


def _clean(scen, data):
    return [_obs(scen, data, n, k) for n in range(N) for k in range(T)]


def test_a_stray_message_is_skipped_never_a_reset(scen, data, tmp_path):
    clean = OnlineEstimator(make_estimator("ukf", scen), "ukf", horizon=T)
    hostile = OnlineEstimator(make_estimator("ukf", scen), "ukf", horizon=T)
    ref = [r.x_hat for raw in _clean(scen, data) for r in clean.feed(raw, 0.0)]
    sent = []
    for n in range(N):
        for k in range(T):
            if n == 1 and k == 3:  # trajectory 0, step 5 (and 0) arrive late, during trajectory 1
                sent += [_obs(scen, data, 0, 5), _obs(scen, data, 0, 0)]
            sent.append(_obs(scen, data, n, k))
    results = _run(hostile, sent)
    assert [(r.trajectory, r.step) for r in results if r.status not in ("estimated", "held")] == [(0, 5), (0, 0)]
    assert all(r.status == "stale" for r in results if r.status not in ("estimated", "held"))
    assert sum(r.status == "unconfirmed" for r in results) == 0 and sum(r.reset for r in results) == N
    np.testing.assert_array_equal(_estimates(results)[1], np.array(ref))

    # replay processes a bag in recorded order: the same skip, the same estimates as live
    msgs = _stream_messages(scen, data)
    i = next(j for j, m in enumerate(msgs) if m[0] == "/observation" and MSG.decode_vector(m[2])[2:4] == (1, 3))
    msgs.insert(i, ("/observation", msgs[i][1], _obs(scen, data, 0, 5)))
    path = tmp_path / "stray.mcap"
    with BagWriter(path) as w:
        w.add_topic("/scenario", MSG.STRING)
        w.write("/scenario", msgs[0][1], MSG.encode_scenario(scen.describe()))
        for topic, t, raw in msgs:
            if not w.has_topic(topic):
                w.add_topic(topic, MSG.JOINT_STATE)
            w.write(topic, t, raw)
    res = replay(path, ["ukf"], tmp_path / "out.mcap")
    assert res.estimates == {"ukf": N * T} and res.skipped == {"ukf": 1}
    np.testing.assert_array_equal(bag_to_arrays(res.path).x_hat["ukf"].reshape(-1, scen.dx), np.array(ref))


@pytest.mark.parametrize(
    "forged",
    [
        "later trajectory",  # (n + 50, k): the real stream looked out of order (602 of 1,500 estimates)
        "step jump",  # (n, k + 400): the next 399 real steps were dropped
        "earlier trajectory, newer stamp",  # (n - 1, 0) stamped later: the stream was reset
        "far trajectory start",  # (n + 7, 0) stamped later
    ],
)
@pytest.mark.parametrize("horizon", [None, T])
def test_one_message_cannot_subvert_the_stream(scen, data, forged, horizon):
    """A single forged or corrupted identity in the middle of trajectory 1 costs itself only: every
    real message is estimated exactly as in the clean stream; the forged one is dropped, counted."""
    clean = OnlineEstimator(make_estimator("ukf", scen), "ukf", horizon=horizon)
    ref_ids, ref = _estimates(_run(clean, _clean(scen, data)))
    n, k = 1, 4
    period = MSG.dt_ns(scen.dt)
    t_now = MSG.step_stamp_ns(10**18, n * T + k, period)
    bad = {
        "later trajectory": MSG.encode_observation(scen, t_now, n + 50, k, data.y[n, k], data.u[n, k - 1]),
        "step jump": MSG.encode_observation(scen, t_now + 400 * period, n, k + 400, data.y[n, k], data.u[n, k - 1]),
        "earlier trajectory, newer stamp": MSG.encode_observation(
            scen, t_now + 10**12, n - 1, 0, data.y[0, 0], np.zeros(scen.du)
        ),
        "far trajectory start": MSG.encode_observation(scen, t_now + 10**12, n + 7, 0, data.y[0, 0], np.zeros(scen.du)),
    }[forged]
    sent = _clean(scen, data)
    sent.insert(n * T + k, bad)
    results = _run(OnlineEstimator(make_estimator("ukf", scen), "ukf", horizon=horizon), sent)
    ids, got = _estimates(results)
    assert ids == ref_ids
    np.testing.assert_array_equal(got, ref)
    dropped = [r.status for r in results if r.status in ("stale", "unconfirmed")]
    assert len(dropped) == 1 and sum(r.status == "held" for r in results) >= 1


def test_a_restarted_publisher_starts_a_fresh_stream(scen, data):
    """A publisher killed at step 7 and restarted with stamps that went back (a simulator running
    ahead of wall time): its new run is a new stream from the prior after one confirming message,
    estimated exactly as a fresh estimator would; nothing of the killed run carries over."""
    online = OnlineEstimator(make_estimator("ukf", scen), "ukf")
    for k in range(8):
        online.feed(_obs(scen, data, 0, k, start_ns=2 * 10**18), 0.0)
    new_run = [_obs(scen, data, 0, k, start_ns=10**18) for k in range(T)]
    results = _run(online, new_run)
    assert results[0].status == "held" and results[1].new_run and results[1].reset
    fresh = _run(OnlineEstimator(make_estimator("ukf", scen), "ukf"), new_run)
    np.testing.assert_array_equal(_estimates(results)[1], _estimates(fresh)[1])
    assert len(_estimates(results)[0]) == T


def test_quarantine_is_bounded_in_time_and_reordering_is_repaired(scen, data):
    online = OnlineEstimator(make_estimator("ekf", scen), "ekf", quarantine_seconds=0.5)
    for k in range(3):
        online.feed(_obs(scen, data, 0, k), 10.0)
    assert [r.status for r in online.feed(_obs(scen, data, 0, 6), 10.0)] == ["held"]
    assert online.held == 1 and online.poll(10.4) == []
    r = online.poll(10.5)  # nothing confirmed or refuted it for 0.5 s: accepted, the gap bridged
    assert [x.status for x in r] == ["estimated"] and r[0].filled == 3 and online.held == 0
    # reordered delivery: 8 before 7 -> 8 is held, 7 releases it, both estimated in order
    reordered = OnlineEstimator(make_estimator("ekf", scen), "ekf")
    in_order = OnlineEstimator(make_estimator("ekf", scen), "ekf")
    ks = [0, 1, 2, 4, 3, 5]
    res = _run(reordered, [_obs(scen, data, 0, k) for k in ks])
    ref = _run(in_order, [_obs(scen, data, 0, k) for k in sorted(ks)])
    assert [r.step for r in res if r.status == "estimated"] == sorted(ks)
    np.testing.assert_array_equal(_estimates(res)[1], _estimates(ref)[1])


def test_a_step_jump_costs_bounded_time(scen, data):
    online = OnlineEstimator(make_estimator("pf", scen), "pf", max_gap=10**9, max_gap_seconds=0.05, confirm=1)
    online.feed(_obs(scen, data, 0, 0))
    far = MSG.encode_observation(scen, 10**18 + 10**15, 0, 10_000_000, data.y[0, 1], data.u[0, 0])
    (_, r) = online.feed(far)
    # restarted without bridging: 10 million PF predict steps would take hours (the work done is
    # asserted, not the wall time, which includes the kernels' first compilation in a fresh clone)
    assert r.status == "estimated" and r.restarted and r.filled == 0
    counted = OnlineEstimator(make_estimator("ekf", scen), "ekf", max_gap=5, max_gap_seconds=0, confirm=1)
    counted.feed(_obs(scen, data, 0, 0))
    assert counted.feed(_obs(scen, data, 0, 3))[-1].filled == 2
    assert counted.feed(_obs(scen, data, 0, 11))[-1].restarted


# ---- options and threads -----------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "option", ["mamba.bogus=1", "mamba.threads=1", "gru.bogus=1", "ukf.bogus=1", "pf.n_particles=-3"]
)
def test_bad_method_options_are_one_line(option, scen, data, tmp_path, capsys):
    bag = arrays_to_bag(tmp_path / "b.mcap", scen, data.x, data.y, data.u)
    method = option.split(".")[0]
    assert (
        cli.main(["replay", str(bag), "--methods", method, "--out", str(tmp_path / "o.mcap"), "--option", option]) == 2
    )
    err = capsys.readouterr().err
    assert err.startswith("neural-estimator: error:") and err.count("\n") == 1, err


def test_replay_threads(scen, data, tmp_path, capsys):
    torch = pytest.importorskip("torch")
    from neural_estimator.stream.online import set_torch_threads

    before = torch.get_num_threads()
    try:
        set_torch_threads(["ukf"], 1)
        assert torch.get_num_threads() == before  # no neural method: torch untouched
        set_torch_threads(["gru"], 1)
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)
    bag = arrays_to_bag(tmp_path / "b.mcap", scen, data.x, data.y, data.u)
    assert cli.main(["replay", str(bag), "--methods", "ukf", "--out", str(tmp_path / "o.mcap"), "--threads", "-1"]) == 2
    assert "--threads" in capsys.readouterr().err
