"""Live chain at a kilohertz: simulator -> three estimator nodes -> evaluator, losses and latency.

    .venv/bin/python benchmarks/bench_pipeline.py                       # bearings, ekf/ukf/enkf, 1 kHz, 10 s
    .venv/bin/python benchmarks/bench_pipeline.py --methods ekf,ukf,gru --rate-hz 1000 --seconds 20
    .venv/bin/python benchmarks/bench_pipeline.py --scenario lorenz96 --methods ekf,gru,mamba --executors single,events

Runs :func:`neural_estimator.nodes.launch.run_pipeline` (separate processes, isolated ROS domain),
then reads the recorded bag and reports

- losses: for every stream, the (trajectory, step) cells the run announced that never arrived in
  the bag (expect zero), plus duplicates and messages the estimators could not use;
- latency inside each estimator node: from the start of the subscription callback to the end of
  publishing the estimate (and covariance), p50 / p99 / max over every message (the nodes'
  ``stats_file``);
- wait: observation published (its DDS source timestamp) -> its estimate published, measured by the
  estimator node itself (queueing included): the estimator's share of the end-to-end delay;
- end to end (the live figure of merit): observation published by the simulator -> estimate received
  by the evaluator, an independent subscriber (the DDS source timestamp of the observation and the
  DDS reception timestamp of the estimate, both on this machine's clock), p50 / p99. On a starved
  machine the recorder's own reception lags too, and that lag is in this figure (wait is not);
- the rate the simulator achieved, and wall time.

``--executors single,events`` runs the chain once per executor in turn (the nodes' executor,
``NEURAL_ESTIMATOR_EXECUTOR``; the evaluator always keeps the single-threaded one) and prints the
end-to-end figures side by side, with the load average before each run.

Results print as a table and go to ``<out>/bench_pipeline.json``. The machine matters: each node is
a Python process; ``--cores`` in the JSON records how many this machine had.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from neural_estimator.bags import bag_to_arrays  # noqa: E402
from neural_estimator.stream import messages as MSG  # noqa: E402
from neural_estimator.nodes.common import EXECUTOR_ENV  # noqa: E402
from neural_estimator.nodes.launch import PipelineConfig, PipelineError, PipelineResult, run_pipeline  # noqa: E402


def end_to_end_ms(bag: Path, methods: list[str]) -> dict[str, dict[str, float]]:
    """Observation source time -> estimate receive time per method, from the MCAP records."""
    from mcap.reader import make_reader

    codec_cache: dict[str, MSG.VectorCodec] = {}
    sent: dict[tuple[int, int], int] = {}
    got: dict[str, list[tuple[tuple[int, int], int]]] = {m: [] for m in methods}
    wanted = {MSG.resolve_topic(MSG.estimate_topic(m)): m for m in methods}
    with open(bag, "rb") as fh:
        for _, channel, message in make_reader(fh).iter_messages():
            if channel.topic == "/observation" or channel.topic in wanted:
                codec = codec_cache.setdefault(channel.topic, MSG.VectorCodec("", ()))
                vec = codec.decode(message.data)
                key = (vec.trajectory, vec.step)
                if channel.topic == "/observation":
                    sent[key] = message.publish_time  # the DDS source timestamp of the simulator
                else:
                    got[wanted[channel.topic]].append((key, message.log_time))  # evaluator receive time
    out = {}
    for m, items in got.items():
        lat = np.array([t - sent[k] for k, t in items if k in sent], dtype=np.float64) / 1e6
        out[m] = (
            {"p50": float(np.percentile(lat, 50)), "p99": float(np.percentile(lat, 99)), "max": float(lat.max())}
            if lat.size
            else {}
        )
    return out


def _count_cells(bag: Path):
    """Per vector topic: messages, distinct (trajectory, step) cells, duplicates (no other checks)."""
    from types import SimpleNamespace

    from mcap.reader import make_reader

    codec = MSG.VectorCodec("", ())
    cells: dict[str, set] = {}
    received: dict[str, int] = {}
    with open(bag, "rb") as fh:
        for _, channel, message in make_reader(fh).iter_messages():
            try:
                vec = codec.decode(message.data)
            except Exception:
                continue
            name = channel.topic.lstrip("/")
            received[name] = received.get(name, 0) + 1
            cells.setdefault(name, set()).add((vec.trajectory, vec.step))
    n_obs = len(cells.get("observation", ()))
    return SimpleNamespace(
        received=received,
        missing={k: n_obs - len(v) for k, v in cells.items()},
        duplicates={k: received[k] - len(v) for k, v in cells.items()},
        rejected={},
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="bearings")
    ap.add_argument("--methods", default="ekf,ukf,enkf")
    ap.add_argument("--rate-hz", type=float, default=1000.0)
    ap.add_argument("--seconds", type=float, default=10.0, help="length of the run at the given rate")
    ap.add_argument("--trajectories", type=int, default=2)
    ap.add_argument("--no-covariance", action="store_true", help="estimators publish no covariance streams")
    ap.add_argument("--out", default=str(ROOT / "runs" / "bench_pipeline"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--domain-id",
        type=int,
        default=None,
        help="the chain's ROS domain (0-232; default: a free one, never ROS_DOMAIN_ID's)",
    )
    ap.add_argument(
        "--estimator-param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="a parameter of every estimator node, e.g. drain=false (one wake-up per message) or max_delay=0.05",
    )
    ap.add_argument(
        "--option",
        action="append",
        default=[],
        metavar="METHOD.NAME=VALUE",
        help="a method option, e.g. gru.backend=onnxruntime (ONNX Runtime serving of the neural step)",
    )
    ap.add_argument(
        "--realtime-priority",
        type=int,
        default=0,
        metavar="N",
        help="every node on SCHED_FIFO at priority N (neural_estimator/nodes/realtime.py; 0: normal scheduling)",
    )
    ap.add_argument(
        "--executors",
        default="events",
        help="comma-separated: the nodes' executor in turn (events, single), e.g. single,events to compare "
        "rclpy's single-threaded executor with its EventsExecutor in one invocation",
    )
    a = ap.parse_args(argv)
    if a.domain_id is not None and not 0 <= a.domain_id <= 232:
        ap.error(f"--domain-id must be in 0-232, got {a.domain_id}")
    executors = [e.strip() for e in a.executors.split(",") if e.strip()]
    print(f"command: python benchmarks/bench_pipeline.py {' '.join(argv if argv is not None else sys.argv[1:])}")
    summary = {}
    code = 0
    for executor in executors:
        os.environ[EXECUTOR_ENV] = executor  # the node processes inherit it
        out = Path(a.out) / executor if len(executors) > 1 else Path(a.out)
        print(f"\n== executor: {executor}")
        result = _run(a, out)
        summary[executor] = result
        code = code or int(result["total_lost"] > 0)
    if len(executors) > 1:
        print(f"\nend to end, observation published -> estimate received (ms), {a.rate_hz:g} Hz:")
        print(f"{'executor':10s} {'method':8s} {'p50':>9s} {'p99':>9s} {'lost':>6s} {'load':>5s}")
        for executor, r in summary.items():
            for m in r["methods"]:
                e = r["end_to_end_ms"].get(m, {})
                lost = r["losses"].get(MSG.estimate_topic(m), -1)
                print(
                    f"{executor:10s} {m:8s} {e.get('p50', float('nan')):9.2f} {e.get('p99', float('nan')):9.2f} "
                    f"{lost:6d} {r['load_average_1min_before']:5.1f}"
                )
    return code


def _run(a, out: Path) -> dict:
    methods = [m.strip() for m in a.methods.split(",") if m.strip()]
    out.mkdir(parents=True, exist_ok=True)
    stats_dir = out / "stats"
    for f in stats_dir.glob("*.json"):
        f.unlink()
    horizon = max(1, int(round(a.rate_hz * a.seconds / a.trajectories)))
    cfg = PipelineConfig(
        scenario=a.scenario,
        methods=tuple(methods),
        trajectories=a.trajectories,
        horizon=horizon,
        rate_hz=a.rate_hz,
        seed=a.seed,
        publish_covariance=not a.no_covariance,
        output=str(out / "run.mcap"),
        timeout=max(120.0, 6 * a.seconds + 60),
        stats_dir=str(stats_dir),
        estimator_params=tuple(a.estimator_param),
        realtime_priority=a.realtime_priority,
        options=tuple(a.option),
        domain_id=a.domain_id,
    )
    print(
        f"{a.scenario}: {methods} at {a.rate_hz:g} Hz, {a.trajectories} x {horizon} steps "
        f"({a.trajectories * horizon} observations), {os.cpu_count()} cores"
        + (f", estimator parameters {a.estimator_param}" if a.estimator_param else "")
        + (f", options {a.option}" if a.option else "")
        + (f", SCHED_FIFO priority {a.realtime_priority}" if a.realtime_priority else ""),
        flush=True,
    )
    load_before = os.getloadavg()[0]
    t0 = time.monotonic()
    try:
        res = run_pipeline(cfg)
    except PipelineError as exc:
        bag = out / "run.mcap"
        if not bag.exists():
            raise
        # The evaluator found no complete trajectory to score (estimators that dropped late observations):
        # the recording is there, so the latencies and losses still are.
        print(f"(the evaluator scored nothing: {str(exc).splitlines()[0]}; the bag is analysed anyway)")
        logs = {n: out / "run.logs" / f"{n}.log" for n in ("simulator", "evaluator")}
        res = PipelineResult(bag, -1, {}, logs, {}, 0.0)
    wall = time.monotonic() - t0

    expected = a.trajectories * horizon
    try:
        run = bag_to_arrays(res.bag)
    except Exception as exc:  # e.g. an estimator that dropped late observations left no trajectory complete
        print(f"(the bag's cell accounting failed: {exc}; counting messages per topic instead)")
        run = _count_cells(res.bag)
    streams = {
        k: {
            "received": run.received.get(k, 0),
            "missing": run.missing.get(k, expected),
            "duplicates": run.duplicates.get(k, 0),
            "rejected": run.rejected.get(k, 0),
        }
        for k in sorted(run.received)
    }
    sim_log = res.logs["simulator"].read_text(errors="replace")
    achieved = re.search(r"\(([\d.]+) Hz achieved, (\d+) steps more than 10 ms late\)", sim_log)
    node_stats = {
        m: json.loads((stats_dir / f"{m}.json").read_text()) for m in methods if (stats_dir / f"{m}.json").exists()
    }
    e2e = end_to_end_ms(res.bag, methods)
    result = {
        "scenario": a.scenario,
        "methods": methods,
        "rate_hz": a.rate_hz,
        "observations": expected,
        "cores": os.cpu_count(),
        "wall_s": wall,
        "simulator_rate_hz": float(achieved.group(1)) if achieved else None,
        "simulator_late_steps": int(achieved.group(2)) if achieved else None,
        "losses": {k: v["missing"] for k, v in streams.items()},
        "streams": streams,
        "latency_in_node_ms": {
            m: {k: s.get(f"latency_{k}_ms") for k in ("p50", "p90", "p99", "max")} for m, s in node_stats.items()
        },
        "end_to_end_ms": e2e,
        "node_counters": node_stats,
        "bag": str(res.bag),
    }
    (out / "bench_pipeline.json").write_text(json.dumps(result, indent=1))

    print(
        f"simulator: {result['simulator_rate_hz']} Hz achieved, {result['simulator_late_steps']} steps > 10 ms late; "
        f"wall {wall:.1f} s"
    )
    print(f"{'stream':32s} {'received':>9s} {'lost':>6s} {'dup':>4s} {'bad':>4s}")
    for k, v in streams.items():
        print(f"{k:32s} {v['received']:9d} {v['missing']:6d} {v['duplicates']:4d} {v['rejected']:4d}")
    heads = ("node p50", "node p99", "node max", "wait p50", "wait p99", "e2e p50", "e2e p99")
    print(f"{'method':8s} " + " ".join(f"{h:>10s}" for h in heads) + "   (ms)")
    for m in methods:
        s = result["latency_in_node_ms"].get(m, {})
        e = e2e.get(m, {})
        c = node_stats.get(m, {})
        cells = [s.get("p50"), s.get("p99"), s.get("max"), c.get("delay_p50_ms"), c.get("delay_p99_ms")]
        cells += [e.get("p50"), e.get("p99")]
        print(f"{m:8s} " + " ".join(f"{c:>10.3f}" if c is not None else f"{'n/a':>10s}" for c in cells))
    for m in methods:
        c = node_stats.get(m, {})
        if c.get("late_dropped"):
            print(
                f"{m}: behind, {c['late_dropped']} late observations dropped (max_delay), "
                f"{c.get('gap_steps', 0)} steps bridged, {c.get('restarts', 0)} restarts"
            )
    load = os.getloadavg()[0]
    result["load_average_1min_before"] = load_before
    result["load_average_1min_after"] = load
    (out / "bench_pipeline.json").write_text(json.dumps(result, indent=1))
    print(f"load average (1 min): {load_before:.1f} before, {load:.1f} after the run, on {os.cpu_count()} cores")
    total_lost = sum(v["missing"] for v in streams.values())
    print(f"total lost: {total_lost}; results in {out / 'bench_pipeline.json'}")
    result["total_lost"] = total_lost
    return result


if __name__ == "__main__":
    sys.exit(main())
