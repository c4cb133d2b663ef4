"""Where one message's time goes in a node: publish, executor wake-up, take, deserialise, callback.

    .venv/bin/python benchmarks/bench_executor.py                 # 2000 messages a case, both executors
    .venv/bin/python benchmarks/bench_executor.py --messages 5000 --rounds 3

One process, one node, an isolated ROS domain, a JointState observation of the Lorenz 96 size
(40 values) on a reliable topic. Per message, microseconds (p50; p99 in the table beside it):

- ``publish``: ``Publisher.publish`` of a message object (serialise + DDS write);
- ``publish raw``: publishing already serialised bytes (what a node skips by keeping the CDR);
- ``take raw`` / ``take msg``: ``take_message`` of one waiting message, as bytes or deserialised
  into a Python message (the estimator node takes raw: its decoder reads the bytes directly);
- ``round trip`` per executor: publish one message, then spin until its callback ran (an empty
  raw-subscription callback): publish + DDS delivery + the executor's wake-up + take + dispatch.
  Executors: rclpy's ``SingleThreadedExecutor`` and ``rclpy.experimental.EventsExecutor`` (driven
  by ``spin_once``, as :func:`neural_estimator.nodes.common.spin` does);
- ``burst`` per executor: 200 messages published, then spun until all callbacks ran, per message
  (the executor's per-message cost when a backlog waits), without and with the node's drain (the
  first callback takes every waiting message itself);
- the callback's own work, per method (``--methods``, Lorenz 96 at its defaults): decoding
  the observation's CDR (``VectorCodec.decode``), ``Estimator.step``, encoding the estimate and the
  covariance, the ``<output>/state`` bytes (``StateEncoder``), and the whole
  ``OnlineEstimator.feed`` (decode, the stream's checks, step, encode), outside ROS.

Rounds alternate the executors; each figure is the best round's. The machine's load average is
printed (on this 2-core machine a training may hold one core: the figures then include waits).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _quantiles(samples: list[float]) -> tuple[float, float]:
    a = np.asarray(samples) * 1e6
    return float(np.percentile(a, 50)), float(np.percentile(a, 99))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--messages", type=int, default=2000)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--width", type=int, default=40, help="values in the observation")
    ap.add_argument(
        "--methods", nargs="*", default=["ekf", "gru"], help="methods whose callback work is timed (gru: ORT backend)"
    )
    a = ap.parse_args(argv)
    from neural_estimator.nodes.launch import pick_domain_id  # NEURAL_ESTIMATOR_DOMAINS, ROS_DOMAIN_ID or 100..199

    os.environ["ROS_DOMAIN_ID"] = str(pick_domain_id())
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import JointState

    from neural_estimator.nodes.common import events_executor

    rclpy.init()
    node = rclpy.create_node("bench_executor")
    qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
    msg = JointState()
    msg.name = [f"y{i}" for i in range(a.width)]
    msg.position = [float(i) for i in range(a.width)]
    msg.header.frame_id = "0/0"
    raw_bytes = serialize_message(msg)
    pub = node.create_publisher(JointState, "obs", qos)
    seen = [0]
    drain = [False]
    sub_ref: list = []

    def on_raw(raw, info=None) -> None:
        seen[0] += 1
        if drain[0]:
            sub = sub_ref[0]
            with sub.handle:
                while sub.handle.take_message(sub.msg_type, True) is not None:
                    seen[0] += 1

    sub = node.create_subscription(JointState, "obs", on_raw, qos, raw=True)
    sub_ref.append(sub)
    probe = node.create_subscription(JointState, "probe", lambda m: None, qos, raw=True)  # for take timings
    probe_pub = node.create_publisher(JointState, "probe", qos)
    time.sleep(0.5)  # discovery within the process

    executors = {"single-threaded": SingleThreadedExecutor(context=node.context)}
    events = events_executor(node.context)
    if events is not None:
        executors["events"] = events
    else:
        print("rclpy.experimental.EventsExecutor: not in this rclpy; the single-threaded executor only")

    def spin_until(ex, count: int) -> None:
        deadline = time.monotonic() + 10
        while seen[0] < count and time.monotonic() < deadline:
            ex.spin_once(timeout_sec=0.1)

    best: dict[str, tuple[float, float]] = {}

    def keep(name: str, samples: list[float]) -> None:
        q = _quantiles(samples)
        if name not in best or q[0] < best[name][0]:
            best[name] = q

    n = a.messages
    for _ in range(a.rounds):
        # publish costs
        ts = []
        for _ in range(n):
            t0 = time.perf_counter()
            probe_pub.publish(msg)
            ts.append(time.perf_counter() - t0)
        keep("publish (message object)", ts)
        ts = []
        for _ in range(n):
            t0 = time.perf_counter()
            probe_pub.publish(raw_bytes)
            ts.append(time.perf_counter() - t0)
        keep("publish raw (CDR bytes)", ts)
        time.sleep(0.2)
        # take costs: the probe queue holds up to 1000 messages
        for raw, label in ((True, "take raw"), (False, "take + deserialise")):
            ts = []
            for _ in range(min(n, 900)):
                probe_pub.publish(raw_bytes)
            time.sleep(0.2)
            with probe.handle:
                while True:
                    t0 = time.perf_counter()
                    got = probe.handle.take_message(JointState, raw)
                    dt = time.perf_counter() - t0
                    if got is None:
                        break
                    ts.append(dt)
            keep(label, ts)
        for name, ex in executors.items():
            ex.add_node(node)
            drain[0] = False
            seen[0] = 0
            ts = []
            for i in range(n):
                t0 = time.perf_counter()
                pub.publish(raw_bytes)
                spin_until(ex, i + 1)
                ts.append(time.perf_counter() - t0)
            keep(f"round trip, {name}", ts)
            for drained in (False, True):
                drain[0] = drained
                seen[0] = 0
                per = []
                for _ in range(max(1, n // 200)):
                    start = seen[0]
                    for _ in range(200):
                        pub.publish(raw_bytes)
                    time.sleep(0.02)
                    t0 = time.perf_counter()
                    spin_until(ex, start + 200)
                    per.append((time.perf_counter() - t0) / 200)
                keep(f"burst of 200, {name}{', drained' if drained else ''}", per)
            ex.remove_node(node)
    print(f"command: python benchmarks/bench_executor.py {' '.join(argv if argv is not None else sys.argv[1:])}")
    print(
        f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}; JointState of {a.width} values "
        f"({len(raw_bytes)} bytes CDR); microseconds a message, best of {a.rounds} rounds\n"
    )
    print("| per message | p50 µs | p99 µs |")
    print("|---|---:|---:|")
    for k, (p50, p99) in best.items():
        print(f"| {k} | {p50:.1f} | {p99:.1f} |")
    node.destroy_node()
    rclpy.try_shutdown()
    if a.methods:
        print()
        print("| callback work (Lorenz 96 at its defaults, 10 variables: the shipped models) | p50 µs | p99 µs |")
        print("|---|---:|---:|")
        for k, (p50, p99) in callback_work(a.methods, a.messages).items():
            print(f"| {k} | {p50:.1f} | {p99:.1f} |")
    return 0


def callback_work(methods: list[str], messages: int) -> dict[str, tuple[float, float]]:
    """p50 / p99 µs of each part of the estimator node's per-message work, outside ROS."""
    from neural_estimator.stream import messages as MSG
    from neural_estimator.data import simulate
    from neural_estimator.nodes.outputs import StateEncoder
    from neural_estimator.stream.online import OnlineEstimator
    from neural_estimator.methods.registry import make_estimator
    from neural_estimator.scenarios import make_scenario

    scen = make_scenario("lorenz96")
    n = max(200, messages)
    data = simulate(scen, 1, 2 * n + 1, 0)
    codec = MSG.VectorCodec(scen.name, list(scen.obs_names))
    raws = [codec.encode(int(k * scen.dt * 1e9), 0, k, data.y[0, k]) for k in range(2 * n + 1)]
    out_codec = MSG.VectorCodec("map", MSG.state_labels(scen))
    cov_codec = MSG.VectorCodec("map", MSG.covariance_labels(scen.dx))
    state = StateEncoder(scen.state_names)
    found: dict[str, tuple[float, float]] = {}

    def timed(label: str, fn, items) -> None:
        ts = []
        for item in items:
            t0 = time.perf_counter()
            fn(item)
            ts.append(time.perf_counter() - t0)
        found[label] = _quantiles(ts)

    timed("decode the observation (VectorCodec)", codec.decode, raws[:n])
    for m in methods:
        options = {"backend": "onnxruntime"} if m in ("gru", "lstm", "gpt2", "filterformer", "mamba", "mamba2") else {}
        est = make_estimator(m, scen, **options)
        est.reset(1)
        y = data.y[0]
        timed(f"{m}: Estimator.step{' (ORT)' if options else ''}", lambda k: est.step(y[k : k + 1]), range(n))
        x, P = est.step(y[:1]), est.covariance
        timed(f"{m}: encode the estimate", lambda k: out_codec.encode(k, 0, k, x[0]), range(n))
        if P is not None:
            timed(f"{m}: encode the covariance", lambda k: cov_codec.encode(k, 0, k, P[0]), range(n))
            timed(f"{m}: <output>/state bytes (StateEncoder)", lambda k: state.encode(x[0], P[0]), range(n))
        online = OnlineEstimator(est, m, publish_covariance=True)
        online.feed(raws[0])
        timed(f"{m}: OnlineEstimator.feed (decode, checks, step, encode)", online.feed, raws[1 : 2 * n + 1])
    return found


if __name__ == "__main__":
    sys.exit(main())
