"""Soak: the live chain for N minutes, memory (RSS) of every node over time and the losses of each.

    nice -n 5 .venv/bin/python benchmarks/soak.py --minutes 60 --rate-hz 500 --methods ekf,ukf,gru
    .venv/bin/python benchmarks/soak.py --minutes 1                      # a quick check

Starts the evaluator (recording ``/diagnostics`` too), one estimator node per method (each writes
its counters to a stats file at shutdown) and the simulator publishing ``rate`` x 60 x ``minutes``
observations (trajectories of ``--horizon`` steps), exactly as ``neural-estimator live`` does, in an
isolated ROS domain. Every ``--sample-s`` seconds it records each node's resident memory (VmRSS)
and the load average. At the end it reports, per node:

- RSS at the end of the warm-up (by default the time the bounded DDS histories take to fill,
  ``--depth`` messages at the rate, plus 30 s), at the end of the stream and the maximum, the growth
  after the warm-up (MiB, and MiB/hour), and the RSS slope after the warm-up (MiB/s, least squares
  over every sample; the flat-memory criterion is a slope under 0.01 MB/s per node);
- losses: for each estimator, the observations it never estimated and why (its stats file: bad,
  oversize, duplicate, out of order, unconfirmed jumps, missing steps, method failures); for the
  evaluator, the (trajectory, step) cells of each stream the run announced that are not in the
  bag (a streaming count over the bag, no dense arrays); the /diagnostics windows at WARN/ERROR.

Prints a table and writes ``soak.json`` and ``rss.csv`` in ``--out``. A soak is a measurement, not a
test: the figures depend on the machine and its load (recorded beside them).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from neural_estimator.nodes.launch import (  # noqa: E402
    ESTIMATOR,
    EVALUATOR,
    SIMULATOR,
    _stop_all,
    isolated_env,
    node_command,
    pick_domain_id,
    start_node,
)


def rss_mib(pid: int) -> float | None:
    """Resident memory of a process in MiB (None once it exited)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


def rss_slope(points: list[tuple[float, float]]) -> float | None:
    """Least-squares slope (MiB/s) of RSS samples (t seconds, MiB): b = sum (t - t_mean)(r - r_mean)
    / sum (t - t_mean)^2. Over every sample after the warm-up, not the last minus the first, so
    one sample caught during a garbage collection or a malloc trim does not make the trend."""
    if len(points) < 3:
        return None
    tm = sum(t for t, _ in points) / len(points)
    rm = sum(r for _, r in points) / len(points)
    var = sum((t - tm) ** 2 for t, _ in points)
    if var <= 0:
        return None
    return sum((t - tm) * (r - rm) for t, r in points) / var


def stream_losses(bag: Path, expected: int, horizon: int) -> dict:
    """Streamed over the bag (bounded memory, one byte per expected cell and stream): per stream its
    messages, distinct (trajectory, step) cells and the highest; per /diagnostics status the count
    of each level; and the span of the observations' publish (source) times."""
    from mcap.reader import make_reader

    from neural_estimator.stream import messages as MSG

    codec = MSG.VectorCodec("", ())
    seen: dict[str, bytearray] = {}
    counts: dict[str, int] = {}
    highest: dict[str, int] = {}
    diag: dict[str, dict[str, int]] = {}
    first_pub = last_pub = None
    with open(bag, "rb") as fh:
        for _, channel, message in make_reader(fh).iter_messages():
            topic = channel.topic
            if topic == "/diagnostics":
                msg = MSG.TYPESTORE.deserialize_cdr(message.data, "diagnostic_msgs/msg/DiagnosticArray")
                for st in msg.status:
                    lv = {0: "OK", 1: "WARN", 2: "ERROR"}.get(int(st.level), "STALE")
                    d = diag.setdefault(st.name, {"OK": 0, "WARN": 0, "ERROR": 0, "STALE": 0})
                    d[lv] += 1
                continue
            role = MSG.topic_role(topic)
            if role is None or role.kind in (MSG.SCENARIO, MSG.RUN_STATUS):
                continue
            counts[topic] = counts.get(topic, 0) + 1
            if role.kind == MSG.OBSERVATION:
                first_pub = message.publish_time if first_pub is None else min(first_pub, message.publish_time)
                last_pub = message.publish_time if last_pub is None else max(last_pub, message.publish_time)
            try:
                vec = codec.decode(message.data)
            except Exception:  # counted as a message, not as a cell
                continue
            bits = seen.setdefault(topic, bytearray(expected))
            g = vec.trajectory * horizon + vec.step
            if 0 <= g < expected:
                bits[g] = 1
                highest[topic] = max(highest.get(topic, -1), g)
    streams = {
        topic: {"messages": n, "cells": sum(seen.get(topic, b"")), "highest": highest.get(topic, -1)}
        for topic, n in sorted(counts.items())
    }
    return {"streams": streams, "diagnostics": diag, "publish_span_ns": (first_pub, last_pub)}


def losses(out: Path, methods: list[str], total: int, horizon: int) -> dict:
    """What each node lost: the estimators (their stats files) and the recorded streams (the bag),
    against the observations the publisher got out (the highest step recorded on any stream + 1:
    a run stopped at its wall-clock limit published fewer than it planned)."""
    bag = out / "soak.mcap"
    rec = {"streams": {}, "diagnostics": {}, "publish_span_ns": (None, None)}
    if bag.exists():
        try:
            rec = stream_losses(bag, total, horizon)
        except Exception as exc:  # a bag cut short by a crash: say so, keep the other figures
            rec["streams"] = {"error": str(exc)}
    stats = {}
    for m in methods:
        try:
            stats[m] = json.loads((out / f"{m}.json").read_text())
        except (OSError, ValueError):
            stats[m] = None
    streams = {k: v for k, v in rec["streams"].items() if isinstance(v, dict)}
    published = max(
        [v["highest"] + 1 for v in streams.values()] + [(s or {}).get("estimates", 0) for s in stats.values()]
    )
    published = min(published, total)
    for v in streams.values():
        v["lost"] = published - v["cells"]
    estimators = {}
    for m, s in stats.items():
        if s is None:
            estimators[m] = None
            continue
        keys = ("bad", "oversize", "duplicates", "out_of_order", "unconfirmed", "gap_steps", "method_failures")
        estimators[m] = {
            "estimates": s["estimates"],
            "not_estimated": published - s["estimates"],
            **{k: s.get(k, 0) for k in keys},
            "quarantined": s.get("quarantined", 0),
            "restarts": s.get("restarts", 0),
            "latency_p50_ms": s.get("latency_p50_ms"),
            "latency_p99_ms": s.get("latency_p99_ms"),
            "lost_upstream": s.get("lost_upstream"),
            "heap_growth": s.get("heap_growth"),  # --tracemalloc only
            "heap_trim": s.get("heap_trim"),  # the periodic malloc_trim's calls and cost (nodes/heap_trace.py)
        }
    a, b = rec["publish_span_ns"]
    obs = next((v for k, v in streams.items() if k.endswith("/observation")), None)
    # the publisher's mean rate: the highest recorded observation over the span of the recorded
    # observations' publish (source) times; the recorder may have lost some in between
    rate = (obs["highest"] + 1) / ((b - a) / 1e9) if obs and a is not None and b > a else None
    return {
        "published": published,
        "recorded_observation_rate_hz": round(rate, 1) if rate else None,
        "estimators": estimators,
        "streams": rec["streams"],
        "diagnostics": rec["diagnostics"],
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=1.0)
    ap.add_argument("--rate-hz", type=float, default=500.0)
    ap.add_argument("--methods", default="ekf,ukf,gru")
    ap.add_argument("--scenario", default="bearings")
    ap.add_argument("--horizon", type=int, default=1000, help="steps per trajectory")
    ap.add_argument("--sample-s", type=float, default=10.0, help="seconds between RSS samples")
    ap.add_argument(
        "--warmup-s",
        type=float,
        default=0.0,
        help="0 = the time to fill the DDS histories (--depth / rate) + 30 s, or 10%% of the run if longer",
    )
    ap.add_argument(
        "--depth",
        type=int,
        default=100_000,
        help="queue and history depth of every stream (default 100000, as neural-estimator live at 500 Hz)",
    )
    ap.add_argument("--metrics", action="store_true", help="let the evaluator compute the paper's metrics at the end")
    ap.add_argument("--out", default="", help="directory for the bag, logs, soak.json (default /tmp/soak-<time>)")
    ap.add_argument(
        "--wall-limit-min",
        type=float,
        default=0.0,
        help="stop the run (simulator, then evaluator) after this many minutes even if the publisher is behind "
        "(default: minutes + 10); the report then counts against what was published",
    )
    ap.add_argument(
        "--tracemalloc",
        type=int,
        default=0,
        help="run the estimators with python -X tracemalloc=FRAMES: each reports where its heap grew after "
        "--depth estimates (nodes/heap_trace.py; slows them); 0 = off",
    )
    ap.add_argument("--analyze", default="", help="recompute the report of a finished soak directory (its soak.json)")
    args = ap.parse_args(argv)
    if args.analyze:
        return analyze(Path(args.analyze))
    methods = [m for m in args.methods.split(",") if m]
    total = int(round(args.rate_hz * 60 * args.minutes))
    trajectories = max(1, math.ceil(total / args.horizon))
    total = trajectories * args.horizon
    out = Path(args.out or f"/tmp/soak-{time.strftime('%Y%m%d-%H%M%S')}")
    out.mkdir(parents=True, exist_ok=True)
    bag = out / "soak.mcap"
    domain = pick_domain_id()
    env = isolated_env(domain)
    depth = args.depth  # the bounded DDS histories (as neural-estimator live): filled in the warm-up
    py = sys.executable
    nodes = {
        "evaluator": node_command(
            py,
            EVALUATOR,
            "evaluator",
            {
                "output": str(bag),
                "overwrite": True,
                "methods": methods,
                "topics": ["/diagnostics"],
                "queue_depth": depth,
                "completion_timeout": 120.0,
                "compute_metrics": bool(args.metrics),
            },
        )
    }
    for m in methods:
        nodes[f"estimator_{m}"] = node_command(
            py,
            ESTIMATOR,
            f"estimator_{m}",
            {
                "method": m,
                "scenario": args.scenario,
                "stats_file": str(out / f"{m}.json"),
                "queue_depth": depth,
                "history_depth": depth,
            },
        )
        if args.tracemalloc:  # python -X tracemalloc=N -m ...: each estimator traces its heap
            nodes[f"estimator_{m}"][1:1] = ["-X", f"tracemalloc={args.tracemalloc}"]
    nodes["simulator"] = node_command(
        py,
        SIMULATOR,
        "simulator",
        {
            "scenario": args.scenario,
            "trajectories": trajectories,
            "horizon": args.horizon,
            "rate_hz": float(args.rate_hz),
            "wait_for_subscribers": len(methods) + 1,
            "wait_timeout": 120.0,
            "start_delay": 1.0,
            "history_depth": depth,
            "linger": 120.0,
            "stay_after_run": 0.0,
        },
    )
    print(
        f"soak: {args.scenario}, {', '.join(methods)}, {total} observations at {args.rate_hz:g} Hz "
        f"({trajectories} x {args.horizon}), {args.minutes:g} min; domain {domain}; {out}",
        flush=True,
    )
    procs = {}
    samples: list[dict] = []
    t0 = time.monotonic()
    streaming_end = None
    wall_limit = 60 * (args.wall_limit_min or args.minutes + 10)
    stopped = False
    try:
        for name, cmd in nodes.items():
            procs[name] = start_node(cmd, out / f"{name}.log", env)
        next_sample = t0
        while procs["evaluator"].poll() is None:
            now = time.monotonic()
            if now >= next_sample:
                row = {"t": round(now - t0, 1), "load1": os.getloadavg()[0]}
                row.update({n: rss_mib(p.pid) for n, p in procs.items()})
                samples.append(row)
                next_sample += args.sample_s
            if streaming_end is None and procs["simulator"].poll() is not None:
                streaming_end = now - t0
            if now - t0 > wall_limit and not stopped:  # the publisher is behind: end it, then the recording
                print(f"soak: wall-clock limit of {wall_limit:.0f} s reached; stopping the run", flush=True)
                stopped = True
                streaming_end = streaming_end or now - t0
                for name in ("simulator", "evaluator"):
                    if procs[name].poll() is None:
                        procs[name].send_signal(signal.SIGINT)
            for name, p in procs.items():
                if name != "evaluator" and p.poll() not in (None, 0):
                    print(f"soak: {name} exited with status {p.returncode}", flush=True)
            time.sleep(0.5)
        run_end = time.monotonic() - t0
    finally:
        _stop_all(procs)
    codes = {n: p.returncode for n, p in procs.items()}

    # ---- memory ----------------------------------------------------------------------------------
    # the warm-up: until every bounded history is full (depth messages at the rate), then 30 s more;
    # growth before that is the fill-up, after it a leak (a 120 s run at 500 Hz into 100,000-deep
    # histories had not filled them yet: its 0.33 MB/s was the fill-up)
    warm = args.warmup_s or max(depth / args.rate_hz + 30.0, 0.1 * 60 * args.minutes)
    end = streaming_end or run_end
    with open(out / "rss.csv", "w") as fh:
        cols = ["t", "load1", *nodes]
        fh.write(",".join(cols) + "\n")
        for r in samples:
            fh.write(",".join("" if r.get(c) is None else f"{r[c]:.1f}" for c in cols) + "\n")
    memory = {}
    for name in nodes:
        during = [(r["t"], r[name]) for r in samples if r.get(name) is not None and r["t"] <= end]
        after_warm = [v for t, v in during if t >= warm]
        if not after_warm:
            memory[name] = None
            continue
        first, last = after_warm[0], after_warm[-1]
        span_h = max((during[-1][0] - warm) / 3600, 1e-9)
        slope = rss_slope([(t, v) for t, v in during if t >= warm])
        memory[name] = {
            "slope_mib_per_s": None if slope is None else round(slope, 5),
            "samples_after_warmup": len(after_warm),
            "rss_warm_mib": round(first, 1),
            "rss_end_mib": round(last, 1),
            "rss_max_mib": round(max(v for _, v in during), 1),
            "growth_mib": round(last - first, 1),
            "growth_mib_per_h": round((last - first) / span_h, 1),
        }
    loads = [r["load1"] for r in samples]

    # ---- losses ----------------------------------------------------------------------------------
    lost = losses(out, methods, total, args.horizon)
    sim_log = (out / "simulator.log").read_text(errors="replace") if (out / "simulator.log").exists() else ""
    achieved = [ln.split("run complete: ", 1)[1] for ln in sim_log.splitlines() if "run complete:" in ln]
    result = {
        "command": "benchmarks/soak.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "scenario": args.scenario,
        "methods": methods,
        "rate_hz": args.rate_hz,
        "minutes": args.minutes,
        "observations": total,
        "streaming_s": round(end, 1),
        "run_s": round(run_end, 1),
        "simulator": achieved[0] if achieved else "stopped before its 'run complete'",
        "stopped_at_wall_limit": stopped,
        "horizon": args.horizon,
        "returncodes": codes,
        "load1": {
            "min": round(min(loads), 2) if loads else None,
            "mean": round(sum(loads) / len(loads), 2) if loads else None,
            "max": round(max(loads), 2) if loads else None,
        },
        "cores": os.cpu_count(),
        "warmup_s": warm,
        "memory": memory,
        **lost,
    }
    (out / "soak.json").write_text(json.dumps(result, indent=1))
    print(report(result), flush=True)
    return 0 if all(c == 0 for c in codes.values()) else 1


def analyze(out: Path) -> int:
    """The report of a finished soak, its losses recomputed from its directory (the memory samples
    and load from its soak.json)."""
    r = json.loads((out / "soak.json").read_text())
    horizon = int(r.get("horizon", 1000))
    r.update(losses(out, r["methods"], r["observations"], horizon))
    r["command"] += f"  (losses recomputed: benchmarks/soak.py --analyze {out})"
    (out / "soak-analyzed.json").write_text(json.dumps(r, indent=1))
    print(report(r), flush=True)
    return 0


def report(r: dict) -> str:
    lines = [
        f"# soak: {r['command']}",
        f"{r['scenario']}, {', '.join(r['methods'])}: {r['observations']} observations at {r['rate_hz']:g} Hz; "
        f"streaming {r['streaming_s']:.0f} s, run {r['run_s']:.0f} s; simulator: {r['simulator']}",
        f"load average (1 min) during the run: min {r['load1']['min']}, mean {r['load1']['mean']}, "
        f"max {r['load1']['max']} on {r['cores']} cores; exit codes {r['returncodes']}",
        f"published: {r.get('published')} of {r['observations']} observations"
        + (" (stopped at the wall-clock limit)" if r.get("stopped_at_wall_limit") else "")
        + f" (the most any node received); the publisher's mean rate over the recorded observations: "
        f"{r.get('recorded_observation_rate_hz')} Hz; losses below count against what was published",
        "",
        f"| node | RSS after warm-up ({r['warmup_s']:.0f} s) MiB | RSS at end MiB | max MiB | growth MiB | MiB/h | "
        "slope after warm-up MiB/s (least squares, samples) |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, m in r["memory"].items():
        if m is None:
            lines.append(f"| {name} | - | - | - | - | - | no sample after the warm-up |")
        else:
            slope = m.get("slope_mib_per_s")
            lines.append(
                f"| {name} | {m['rss_warm_mib']} | {m['rss_end_mib']} | {m['rss_max_mib']} | "
                f"{m['growth_mib']} | {m['growth_mib_per_h']} | "
                f"{'-' if slope is None else f'{slope:.4f}'} ({m.get('samples_after_warmup', '-')}) |"
            )
    lines += [
        "",
        "| estimator | estimates | not estimated | bad | oversize | dup | out of order | unconfirmed | "
        "missing steps | failures | quarantined | restarts | p50 ms | p99 ms |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for m, e in r["estimators"].items():
        if e is None:
            lines.append(f"| {m} | no stats file |")
            continue
        lines.append(
            f"| {m} | {e['estimates']} | {e['not_estimated']} | {e['bad']} | {e['oversize']} | {e['duplicates']} | "
            f"{e['out_of_order']} | {e['unconfirmed']} | {e['gap_steps']} | {e['method_failures']} | "
            f"{e['quarantined']} | {e['restarts']} | {_ms(e['latency_p50_ms'])} | {_ms(e['latency_p99_ms'])} |"
        )
    trims = {m: (e or {}).get("heap_trim") for m, e in r["estimators"].items()}
    if any(trims.values()):
        lines += ["", "| estimator | heap trims (period s) | released memory | mean ms | max ms |"]
        lines += ["|---|---|---|---|---|"]
        for m, t in trims.items():
            if t:
                cost = f"{_ms(t['mean_ms'])} | {_ms(t['max_ms'])}"
                lines.append(f"| {m} | {t['calls']} ({t['period_s']:g}) | {t['released']} | {cost} |")
    for m, e in r["estimators"].items():
        heap = (e or {}).get("heap_growth")
        if heap:
            lines += [
                "",
                f"{m}: traced heap grew {heap['traced_growth_kib']} KiB from estimate {heap['baseline_estimates']} "
                f"to {heap['estimates']}; largest growth by call stack (innermost first):",
            ]
            lines += [f"  {t['kib']:+.1f} KiB in {t['blocks']:+d} blocks: {t['where']}" for t in heap["top"][:8]]
    lines += ["", "| recorded stream (evaluator) | messages | cells | lost cells |", "|---|---|---|---|"]
    for topic, s in r["streams"].items():
        if isinstance(s, dict):
            lines.append(f"| {topic} | {s['messages']} | {s['cells']} | {s.get('lost')} |")
        else:
            lines.append(f"| {topic} | {s} | | |")
    if r["diagnostics"]:
        lines += ["", "| /diagnostics status | OK | WARN | ERROR |", "|---|---|---|---|"]
        for name, d in sorted(r["diagnostics"].items()):
            lines.append(f"| {name} | {d['OK']} | {d['WARN']} | {d['ERROR']} |")
    return "\n".join(lines) + "\n"


def _ms(v) -> str:
    return "-" if v is None else f"{v:.3f}"


if __name__ == "__main__":
    sys.exit(main())
