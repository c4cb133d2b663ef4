"""Every allocation sized by input is bounded before it happens, and the bound is named in a
one-line error (bags, recorded runs, cards, robot specs); disk full and read-only outputs."""

from __future__ import annotations

import pytest

from neural_estimator.bags import BagError, BagWriter
from neural_estimator.stream import messages as MSG
from neural_estimator.bags.dataset import arrays_to_bag, bag_to_arrays
from neural_estimator.data import simulate
from neural_estimator.scenarios import make_scenario


@pytest.fixture(scope="module")
def scen():
    return make_scenario("bearings")


def _bag_with(path, scen, extra, *, announce=True, N=2, T=6):
    """A small run bag plus the (trajectory, step) observation messages ``extra`` (one each)."""
    data = simulate(scen, N, T, seed=3)
    arrays_to_bag(path, scen, data.x, data.y, data.u, estimates={"ekf": data.x})
    if not extra and announce:
        return path
    from neural_estimator.bags.directory import open_bag

    with open_bag(path) as bag:
        msgs = [(c.topic, t, bytes(raw)) for c, t, raw in bag.messages()]
    out = path.with_name("x" + path.name)
    with BagWriter(out) as w:
        for topic, t, raw in msgs:
            if topic == "/scenario" and not announce:
                continue
            if not w.has_topic(topic):
                w.add_topic(topic, MSG.STRING if topic in ("/scenario", "/run_status") else MSG.JOINT_STATE)
            w.write(topic, t, raw)
        for n, k in extra:
            w.write("/observation", msgs[-1][1], MSG.encode_observation(scen, msgs[-1][1] + 1, n, k, data.y[0, 0], []))
    return out


def test_a_step_index_of_a_billion_is_rejected_not_allocated(scen, tmp_path):
    """It made the evaluator, ``metrics`` and ``replay`` allocate (N, 10**9, width): 224 GiB."""
    run = bag_to_arrays(_bag_with(tmp_path / "a.mcap", scen, [(0, 10**9), (3 * 10**7, 0)]))
    assert run.x.shape[:2] == (2, 6) and run.outside == {"observation": 2}
    assert run.received["observation"] == 12


def test_without_an_announcement_the_array_bound_is_named(scen, tmp_path, monkeypatch):
    bag = _bag_with(tmp_path / "b.mcap", scen, [(0, 10**9)], announce=False)
    with pytest.raises(BagError) as e:
        bag_to_arrays(bag, description=scen.describe())
    msg = str(e.value)
    assert "\n" not in msg and "largest step index 1000000000" in msg and "NEURAL_ESTIMATOR_MAX_ARRAY_GB" in msg
    monkeypatch.setenv("NEURAL_ESTIMATOR_MAX_ARRAY_GB", "0.0000001")  # the bound is the setting's
    with pytest.raises(BagError, match="over the bound of 0.0 GiB"):
        bag_to_arrays(_bag_with(tmp_path / "c.mcap", scen, []))


@pytest.mark.parametrize("run", [{"trajectories": 3 * 10**7, "horizon": 10}, {"trajectories": 2, "horizon": 10**9}])
def test_an_announced_run_too_large_is_refused_before_allocation(scen, tmp_path, run):
    desc = scen.describe()
    desc["run"] = run
    bag = _bag_with(tmp_path / "d.mcap", scen, [], announce=False)
    with pytest.raises(
        BagError, match=r"the run announces .* over the bound of 4.0 GiB \(NEURAL_ESTIMATOR_MAX_ARRAY_GB\)"
    ):
        bag_to_arrays(bag, description=desc)


# ---- full disks and read-only outputs ------------------------------------------------------------------------
def test_a_full_disk_is_one_line_not_a_traceback(scen, tmp_path):
    full = tmp_path / "full.mcap"
    full.symlink_to("/dev/full")  # every write: ENOSPC
    w = BagWriter(full, overwrite=True, chunk_size=1024).open()
    w.add_topic("/observation", MSG.JOINT_STATE)
    with pytest.raises(BagError) as e:
        for k in range(10_000):
            w.write("/observation", k, MSG.encode_observation(scen, k, 0, k, [0.0], []))
    assert str(e.value) == f"{full}: cannot write: No space left on device"
    with pytest.raises(BagError, match="cannot finish the bag: No space left on device"):
        w.close()
    assert w.closed


def _short_run_bag(path, scen, n_obs):
    """A bag announcing 2 x 6 steps that holds only ``n_obs`` observations (a recorder that died)."""
    with BagWriter(path) as w:
        w.add_topic("/scenario", MSG.STRING)
        w.add_topic("/observation", MSG.JOINT_STATE)
        w.write("/scenario", 0, MSG.encode_scenario(scen.describe(), trajectories=2, horizon=6))
        for g in range(n_obs):
            w.write("/observation", g + 1, MSG.encode_observation(scen, g + 1, g // 6, g % 6, [0.0], []))
    return path


def test_recover_counts_lost_messages_not_only_chunks(scen, tmp_path):
    from neural_estimator.bags.recover import recover_bag

    res = recover_bag(_short_run_bag(tmp_path / "short.mcap", scen, 9), tmp_path / "fixed.mcap")
    assert res.lost == {"/observation": 3} and "/observation 3" in res.lost_note()


def test_recover_onto_a_full_disk_leaves_no_file(scen, tmp_path, monkeypatch):
    """It left a 0-byte file and a traceback."""
    import builtins
    import errno

    from neural_estimator.bags import writer as writer_module
    from neural_estimator.bags.recover import recover_bag

    src = _short_run_bag(tmp_path / "src.mcap", scen, 12)

    class Full:
        def __init__(self, f):
            self.f = f

        def write(self, data):
            raise OSError(errno.ENOSPC, "No space left on device")

        def __getattr__(self, name):
            return getattr(self.f, name)

    monkeypatch.setattr(writer_module, "open", lambda *a, **k: Full(builtins.open(*a, **k)), raising=False)
    out = tmp_path / "out" / "fixed.mcap"
    with pytest.raises(BagError) as e:
        recover_bag(src, out)
    assert "No space left on device" in str(e.value) and "\n" not in str(e.value)
    assert not out.exists() and list(out.parent.iterdir()) == []


def test_the_loss_lines_say_what_each_stream_lost_and_why():
    from neural_estimator.evaluation.bag_report import loss_lines

    bag = {
        "received": {"observation": 98, "estimates/ukf": 90},
        "missing": {"observation": 2, "estimates/ukf": 10},
        "rejected": {"estimates/ukf": 1},
        "outside": {"observation": 1},
        "duplicates": {},
    }
    lines = loss_lines(bag, {"estimates/ukf": {"oversize (dropped by the evaluator)": 2}})
    assert lines == [
        "estimates/ukf: 90 received, 10 lost; not used: 1 malformed, 2 oversize (dropped by the evaluator)",
        "observation: 98 received, 2 lost; not used: 1 outside the announced run",
    ]


# ---- decompressed chunk sizes ---------------------------------------------------------------------------------
def _mcap(path, compression, payload=b"\0" * 1000, n=3):
    """A one-topic MCAP written by the mcap library with ``compression`` (zstd or lz4)."""
    from mcap.writer import CompressionType, Writer

    with open(path, "wb") as fh:
        w = Writer(fh, compression={"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4}[compression])
        w.start(profile="ros2")
        sid = w.register_schema("std_msgs/msg/String", "ros2msg", b"string data")
        cid = w.register_channel("/blob", "cdr", sid)
        for i in range(n):
            w.add_message(cid, log_time=i, data=payload, publish_time=i)
        w.finish()
    return path


def _declare_chunk_size(path, usize):
    """Rewrite the uncompressed_size field of the file's first chunk record (a crafted header)."""
    import struct

    data = bytearray(path.read_bytes())
    at = 8  # after the magic: records of opcode (1 byte), length (8), body
    while data[at] != 0x06:
        at += 9 + struct.unpack_from("<Q", data, at + 1)[0]
    struct.pack_into("<Q", data, at + 9 + 16, usize)  # body: start, end (8 each), uncompressed_size
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("compression", ["zstd", "lz4"])
def test_a_chunk_declaring_gigabytes_is_not_decompressed(tmp_path, compression):
    """zstd: 2.25 GB and 100 s before a clean error; lz4: no bound at all."""
    import time
    import warnings

    from neural_estimator.bags import BagReader, BagWarning

    path = _mcap(tmp_path / f"{compression}.mcap", compression)
    _declare_chunk_size(path, 2**31)
    t0 = time.monotonic()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with BagReader(path) as bag:
            assert list(bag.messages()) == []  # the chunk is lost, not inflated
    assert time.monotonic() - t0 < 10
    text = " ".join(str(w.message) for w in caught if issubclass(w.category, BagWarning))
    assert "over the bound of 67108864 bytes (NEURAL_ESTIMATOR_MAX_CHUNK_MB, MiB)" in text


@pytest.mark.parametrize("compression", ["zstd", "lz4"])
def test_a_chunk_holding_more_than_it_declares_stops_at_the_declared_size(tmp_path, compression, monkeypatch):
    import tracemalloc
    import warnings

    from neural_estimator.bags import BagReader

    path = _mcap(tmp_path / f"{compression}.mcap", compression, payload=b"\0" * 40_000_000, n=1)  # 40 MB of zeros
    _declare_chunk_size(path, 1000)
    tracemalloc.start()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with BagReader(path) as bag:
            assert list(bag.messages()) == []
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 10_000_000  # the file itself is small; nothing near the 40 MB it inflates to


def test_a_rosbag2_directory_listing_more_files_than_can_be_open_is_one_line(tmp_path, scen):
    """30,000 listed files gave a ``Too many open files`` traceback in three tools; now the listing
    is refused before any file is opened, the bound named (here the open-file limit, set to 256)."""
    import resource

    import yaml

    from neural_estimator.bags.directory import open_bag

    bag = tmp_path / "many"
    bag.mkdir()
    one = _short_run_bag(tmp_path / "one.mcap", scen, 2).read_bytes()
    names = [f"part_{i}.mcap" for i in range(300)]
    for name in names:
        (bag / name).write_bytes(one)
    (bag / "metadata.yaml").write_text(
        yaml.safe_dump({"rosbag2_bagfile_information": {"storage_identifier": "mcap", "relative_file_paths": names}})
    )
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (256, hard))
    try:
        with pytest.raises(BagError) as e:
            with open_bag(bag):
                pass
    finally:
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))
    assert "lists 300 files, over the bound of 192 files open at once" in str(e.value)
    assert "\n" not in str(e.value)


# ---- checkpoint cards ------------------------------------------------------------------------------------------
def _card(tmp_path, edit):
    import json
    import shutil

    from neural_estimator.serving.card import default_checkpoint

    src = default_checkpoint("bearings", "gru")
    dst = tmp_path / "ckpt"
    shutil.copytree(src, dst)
    card = json.loads((dst / "card.json").read_text())
    edit(card)
    (dst / "card.json").write_text(json.dumps(card))
    return dst


@pytest.mark.parametrize(
    "edit, text",
    [
        (lambda c: c.update(format_version="abc"), "format_version 'abc' is not a version number"),
        (lambda c: c.update(weights=[]), "'weights' is a list, not an object"),
        (lambda c: c.update(architecture="gru"), "'architecture' is a str, not an object"),
        (lambda c: c["architecture"].update(config=None), "architecture needs a name and a config object"),
        (lambda c: c["architecture"]["config"].update(layers=200_000), "layers=200000; at most 256"),
    ],
)
def test_a_corrupt_card_is_one_line(tmp_path, edit, text):
    """``"format_version": "abc"`` and ``"weights": []`` gave 20-line tracebacks; ``"layers": 200000``
    hung the size check for over 300 s (200,000 modules built on the meta device)."""
    import time

    from neural_estimator.methods.registry import EstimatorError, make_estimator

    ckpt = _card(tmp_path, edit)
    t0 = time.monotonic()
    with pytest.raises(EstimatorError) as e:
        make_estimator("gru", make_scenario("bearings"), checkpoint=str(ckpt))
    assert text in str(e.value) and "\n" not in str(e.value) and time.monotonic() - t0 < 30
