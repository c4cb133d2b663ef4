"""The estimator node's reporting rules, without ROS (neural_estimator/nodes/estimator_stats.py)."""

from __future__ import annotations

import json

from neural_estimator.nodes.estimator_stats import (
    ERROR,
    OK,
    WARN,
    EstimatorStats,
    diagnostic_values,
    health,
    stats_summary,
)


def test_health_levels_and_problems_over_a_window():
    s = EstimatorStats()
    first = s.window(0.0)
    assert health(s, first, waiting=False, foreign=set()) == (OK, [])
    assert health(s, first, waiting=True, foreign=set()) == (WARN, ["waiting for the scenario"])
    s.estimated, s.bad, s.gap_steps = 100, 2, 5
    s.latency.extend([0.001] * 100)
    w = s.window(1.0)
    level, problems = health(s, w, waiting=False, foreign={"/x (std_msgs/msg/String)"})
    assert level == WARN and problems == [
        "2 bad messages dropped",
        "5 missing steps",
        "foreign publishers: /x (std_msgs/msg/String)",
    ]
    assert w["rate"] == 100.0 and abs(w["p50"] - 0.001) < 1e-12
    assert health(s, s.window(2.0), waiting=False, foreign=set()) == (OK, [])  # the window moved on
    s.errors, s.diverged = 1, True
    level, problems = health(s, s.window(3.0), waiting=False, foreign=set())
    assert level == ERROR and problems[0].startswith("diverged") and "failures inside the method" in problems[1]


def test_values_and_the_stats_file_are_plain_text_and_json():
    s = EstimatorStats(estimated=3, bad=1, early=1)
    s.latency.extend([0.002, 0.004])
    values = diagnostic_values(s, s.window(1.0), "ukf")
    assert (
        values["bad messages"] == "2" and values["method"] == "ukf" and all(isinstance(v, str) for v in values.values())
    )
    summary = stats_summary(s, "/est", "ukf")
    assert json.loads(json.dumps(summary))["latency_samples"] == 2 and summary["bad"] == 2


def test_window_after_more_latencies_than_kept_does_not_raise():
    """Regression: trimming an array.array while a np.frombuffer view of it was alive raised
    BufferError in the diagnostics timer after 200,000 estimates, and the node exited."""
    s = EstimatorStats()
    for _ in range(200_001):
        s.latency.append(1e-3)
    w = s.window(1.0)
    assert w["p50"] == 1e-3 and len(s.latency) == s.latency.capacity and s.latency.total == 200_001


def test_ring_keeps_the_newest_in_order():
    from neural_estimator.nodes.estimator_stats import LatencyRing

    r = LatencyRing(5)
    r.extend(range(8))
    assert r.values().tolist() == [3, 4, 5, 6, 7] and r.since(6).tolist() == [6, 7] and r.since(100).size == 0
    assert r.since(0).tolist() == [3, 4, 5, 6, 7]


def _resident_mib(buf) -> float:
    """Resident MiB of ``buf``'s own pages (``mincore``, page by page): whatever other threads of the
    process allocate or free meanwhile (the process's RssAnon moved by -12 MiB around a 38 MiB ring
    in a loaded test worker)."""
    import ctypes
    import mmap

    import numpy as np

    page = mmap.PAGESIZE
    start = buf.ctypes.data // page * page
    length = buf.ctypes.data + buf.nbytes - start
    vec = np.zeros((length + page - 1) // page, dtype=np.uint8)
    libc = ctypes.CDLL(None, use_errno=True)
    libc.mincore.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_void_p]
    assert libc.mincore(start, length, vec.ctypes.data) == 0, ctypes.get_errno()
    return int(np.count_nonzero(vec & 1)) * page / 2**20


def test_the_ring_is_resident_from_the_start_so_filling_it_does_not_grow_the_process():
    # a calloc'ed (np.zeros) ring has its pages mapped only when first written: the node's RSS
    # then grew 8 bytes per sample (2 rings: 16 bytes a message) until the rings wrapped, 3 MiB
    # over the first 400 s at 500 Hz, which a soak reads as a leak. 5,000,000 samples (38 MiB):
    # above glibc's largest mmap threshold (32 MiB), so the ring is a mapping of its own whose
    # resident pages /proc/self/smaps counts
    import mmap

    import numpy as np

    from neural_estimator.nodes.estimator_stats import LatencyRing

    r = LatencyRing(5_000_000)
    size = r._buf.nbytes / 2**20
    assert _resident_mib(r._buf) > 0.99 * size  # resident when made (a calloc'ed ring: about 0)
    r.extend(1e-3 for _ in range(400_000))  # 3 MiB of it written
    assert _resident_mib(r._buf) > 0.99 * size  # and still all of it: nothing more to map
    # the check itself tells the two apart: a fresh anonymous mapping, never written, is what a
    # calloc'ed ring is when glibc maps it on its own (np.zeros itself may be carved from a heap top
    # that earlier tests of the worker left, which calloc clears and so makes resident)
    untouched = np.frombuffer(mmap.mmap(-1, r._buf.nbytes), dtype=np.float64)
    assert _resident_mib(untouched) < 0.1 * size


def test_short_soak_of_the_stats_path_keeps_memory_fixed():
    """250,000 estimates through the node's stats path (record + a diagnostics window every 500, as
    at 500 Hz with a 1 s period): no exception, the latency store never grows, counts exact."""
    s = EstimatorStats()
    buf = s.latency._buf
    windows = 0
    for i in range(250_000):
        s.record(1e-4 if i % 1000 else 5e-3)
        s.estimated += 1
        if i % 500 == 499:
            w = s.window(i / 500)
            windows += 1
            assert w["estimated"] == 500 and health(s, w, waiting=False, foreign=set())[0] == OK
    assert s.latency._buf is buf and buf.nbytes == 8 * s.latency.capacity
    summary = stats_summary(s, "/est", "ukf")
    assert summary["estimates"] == 250_000 and summary["latency_samples"] == 250_000 and windows == 500
    assert summary["latency_kept"] == s.latency.capacity and abs(summary["latency_p50_ms"] - 0.1) < 1e-9


def test_drops_quarantine_and_falling_behind_are_never_ok():
    s = EstimatorStats()
    s.window(0.0)
    s.estimated = 100
    s.skipped["stale"] = 3
    s.quarantined = 2
    level, problems = health(s, s.window(1.0), waiting=False, foreign=set())
    assert level == WARN and "3 messages skipped" in problems[0] and "2 messages quarantined" in problems[1]
    s.record(0.95)  # busy 95 % of a 1 s window
    s.estimated += 10
    level, problems = health(s, s.window(2.0), waiting=False, foreign=set())
    assert level == WARN and problems == ["falling behind: busy 95% of the time"]
    s.waited(2.5)  # a message sent 2.5 s before it was processed
    level, problems = health(s, s.window(2.5), waiting=False, foreign=set())
    assert level == WARN and problems == ["falling behind: a message waited 2.5 s in the queue"]
    assert s.window(2.6)["lag"] == 0.0  # per window
    s.skipped["unconfirmed"] += 40
    s.oversize += 1
    s.estimated += 20
    level, problems = health(s, s.window(3.0), waiting=False, foreign=set())
    assert level == ERROR and problems[0] == "lost 41 messages against 20 estimates"


def test_steps_a_restart_skipped_are_lost_upstream_and_reported():
    """A node 2-4 min behind at 500 Hz never received 46,513 observations (its
    DDS queue overflowed) and its diagnostics never went ERROR: a gap longer than max_gap restarts
    the stream with filled = 0, so those steps were counted nowhere. They are now the stream's
    missed steps, in the window's losses and in "observations lost upstream"."""
    import numpy as np

    from neural_estimator.stream import messages as MSG
    from neural_estimator.data import simulate
    from neural_estimator.stream.online import OnlineEstimator
    from neural_estimator.methods.registry import make_estimator
    from neural_estimator.scenarios import make_scenario

    scen = make_scenario("bearings")
    data = simulate(scen, 1, 5, seed=1)
    online = OnlineEstimator(make_estimator("ekf", scen), "ekf", max_gap=1000)

    def obs(k):
        t = MSG.step_stamp_ns(10**18, k, MSG.dt_ns(scen.dt))
        return MSG.encode_observation(scen, t, 0, k, data.y[0, k % 5], np.zeros(scen.du))

    s = EstimatorStats()
    s.window(0.0)
    sent = (
        [obs(k) for k in range(5)] + [obs(k) for k in range(3000, 3005)] + [obs(3010), obs(3011)]
    )  # 3010 confirmed by 3011
    for raw in sent:
        for res in online.feed(raw, 0.0):
            if res.status == "estimated":  # what the node's _handle counts
                s.estimated += 1
                s.gap_steps += res.filled
                s.restarts += res.restarted
                s.missed += res.missed
    assert s.estimated == 12 and s.restarts == 1 and s.gap_steps == 5 and s.missed == 2995 + 5
    s.late_dropped = 5  # five of the missed steps were dropped here as late, not upstream
    level, problems = health(s, s.window(1.0), waiting=False, foreign=set())
    assert level == ERROR and problems[0] == "lost 3000 messages against 12 estimates"
    assert "2995 observations lost upstream (never received)" in problems
    assert diagnostic_values(s, s.window(2.0), "ekf")["observations lost upstream"] == "2995"
    assert stats_summary(s, "/est", "ekf")["lost_upstream"] == 2995


def test_whole_trajectories_lost_from_a_lagging_nodes_queue_are_counted():
    """A 4-minute soak at 500 Hz under load: the EKF node jumped from 64/152 to 69/193 (its queue
    overflowed) and counted only the 193 steps it bridged; with the horizon known, the steps of the
    trajectories in between are missed too: (H - 1 - 152) + 4 H + 193."""
    import numpy as np

    from neural_estimator.stream import messages as MSG
    from neural_estimator.stream.online import OnlineEstimator
    from neural_estimator.methods.registry import make_estimator
    from neural_estimator.scenarios import make_scenario

    scen = make_scenario("bearings")
    H = 1000
    online = OnlineEstimator(make_estimator("ekf", scen), "ekf", horizon=H)

    def obs(n, k):
        t = MSG.step_stamp_ns(10**18, n * H + k, MSG.dt_ns(scen.dt))
        return MSG.encode_observation(scen, t, n, k, np.zeros(scen.dy), np.zeros(scen.du))

    missed = filled = 0
    for n, k in [(64, 150), (64, 151), (64, 152), (69, 193), (69, 194), (69, 195)]:
        for res in online.feed(obs(n, k), 0.0):
            if res.status == "estimated":
                missed += res.missed
                filled += res.filled
    # (the first message, at step 150, bridges 150 steps from the prior: a late start, not a loss)
    assert filled == 150 + 193 and missed == (H - 1 - 152) + 4 * H + 193
    # without the horizon, at least the steps of the new trajectory before the jump
    blind = OnlineEstimator(make_estimator("ekf", scen), "ekf")
    got = [r.missed for raw in (obs(64, 152), obs(69, 193), obs(69, 194)) for r in blind.feed(raw, 0.0)]
    assert sum(got) == 193
