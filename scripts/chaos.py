"""Fault injection: drive the live chain through hostile and unlucky cases and print what each did.

    .venv/bin/python scripts/chaos.py                     # every case (a few minutes on 2 cores)
    .venv/bin/python scripts/chaos.py --cases forged-trajectory,restart --out /tmp/chaos

Each case starts its own chain in an isolated ROS domain: the evaluator and two estimator nodes
(EKF and UKF) started as ``neural-estimator live`` starts them, fed by this script in the place of
the simulator (the same messages: ``/scenario``, ``/run_status``, ``/observation``,
``/ground_truth``), with one fault injected in the middle of the run. It listens to
``/diagnostics``, then reads the nodes' stats files, the evaluator's table and every log, and
prints one row per case: what the estimators estimated (of the run's messages), what they
skipped or held, the worst diagnostic level they reported (their own status and their input's
apart), the evaluator's exit status, UKF RMSE
and what it says it lost, tracebacks in any log, and a verdict against the case's expectation:

- no node dies and no log holds a traceback (the disk-full evaluator exits 1 with one line);
- a forged or corrupted message costs itself only: every real observation is estimated, the
  diagnostics say WARN (or ERROR) with the count, and the metrics are computed;
- a restarted publisher's new run starts a fresh stream: UKF RMSE as in the clean run;
- oversize messages are dropped unread and counted, and their memory is not kept (each estimator's
  resident memory grows by less than two of the 20 MB messages over the three: see OVERSIZE_KEPT_MIB).

The table shows each estimator's own status (what it did with the messages) apart from its input
status (frequency and staleness): after a run ends the input goes stale, ERROR in every case.

Only this script and the nodes it starts use rclpy; the verdicts are assertions on what the nodes
did, not on timings.
"""

from __future__ import annotations

import argparse
import json
import re
import signal
import sys
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from neural_estimator.stream import messages as MSG  # noqa: E402
from neural_estimator.data import simulate  # noqa: E402
from neural_estimator.nodes.launch import (  # noqa: E402
    ESTIMATOR,
    EVALUATOR,
    isolated_env,
    node_command,
    pick_domain_id,
    start_node,
)
from neural_estimator.scenarios import make_scenario  # noqa: E402

SCENARIO = "bearings"
METHODS = ("ekf", "ukf")
N, T = 2, 150
RATE_HZ = 300.0
INJECT_AT = (1, 40)  # the fault goes out just before this (trajectory, step)


class Case(NamedTuple):
    name: str
    what: str
    expect: str  # "estimated-all", "restart", "disk-full", "oversize"


CASES = [
    Case("clean", "no fault (the reference)", "estimated-all"),
    Case("forged-trajectory", "one observation claiming trajectory +50", "estimated-all"),
    Case("step-jump", "one observation claiming step +400", "estimated-all"),
    Case("earlier-newer", "one observation of an earlier trajectory with a newer stamp", "estimated-all"),
    Case("step-1e9", "one observation with step index 10^9 (its stamp consistent)", "estimated-all"),
    Case("huge-announcement", "a second /scenario announcing 3*10^7 trajectories x 10^9 steps", "estimated-all"),
    Case("garbage", "12 bytes of garbage, a wrong-width observation, an empty message", "estimated-all"),
    Case("oversize", "three 20 MB observations", "oversize"),
    Case("restart", "the publisher restarts after trajectory 0 with stamps 10x earlier (killed, restarted)", "restart"),
    Case("disk-full", "the evaluator's output on a full disk (/dev/full)", "disk-full"),
]


def _messages(scen, data, start_ns: int, dt_ns: int):
    obs = MSG.VectorCodec(scen.name, MSG.observation_labels(scen))
    truth = MSG.VectorCodec(scen.name, MSG.state_labels(scen))
    for n in range(N):
        for k in range(T):
            stamp = MSG.step_stamp_ns(start_ns, n * T + k, dt_ns)
            u_prev = data.u[n, k - 1] if k else np.zeros(scen.du)
            yield (
                (n, k),
                obs.encode(stamp, n, k, np.concatenate([data.y[n, k], u_prev])),
                truth.encode(stamp, n, k, data.x[n, k]),
            )


def _fault(case: str, scen, data, start_ns: int, dt_ns: int) -> list[tuple[str, bytes]]:
    """(topic, bytes) injected before INJECT_AT."""
    n, k = INJECT_AT
    stamp = MSG.step_stamp_ns(start_ns, n * T + k, dt_ns)
    y, u = data.y[n, k], np.zeros(scen.du)
    enc = lambda s, tn, tk: MSG.encode_observation(scen, s, tn, tk, y, u)  # noqa: E731
    if case == "forged-trajectory":
        return [("observation", enc(stamp, n + 50, k))]
    if case == "step-jump":
        return [("observation", enc(stamp + 400 * dt_ns, n, k + 400))]
    if case == "earlier-newer":
        return [("observation", enc(stamp + 10**12, n - 1, 0))]
    if case == "step-1e9":
        return [("observation", enc(stamp + 10**9 * dt_ns, n, 10**9))]
    if case == "huge-announcement":
        return [("scenario", MSG.encode_scenario(scen.describe(), trajectories=3 * 10**7, horizon=10**9))]
    if case == "garbage":
        return [  # the empty one last: a zero-byte sample stalls the DDS writer that sent it (the intruder's)
            ("observation", b"\x00\x01\x00\x00\x07garbage"),
            ("observation", MSG.encode_vector(stamp, scen.name, n, k, ["a", "b", "c"], [0.0, 1.0, 2.0])),
            ("observation", b""),
        ]
    if case == "oversize":
        big = MSG.encode_vector(stamp, scen.name, n, k, ["x"] * 1_250_000, np.zeros(1_250_000))  # 20 MB
        return [("observation", big)] * 3
    return []


def run_case(case: Case, out: Path, timeout: float = 120.0) -> dict:
    """One chain with one fault; what the nodes did."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import JointState
    from std_msgs.msg import String

    from neural_estimator.nodes.common import latched_qos, stream_qos

    d = out / case.name
    d.mkdir(parents=True, exist_ok=True)
    domain = pick_domain_id()
    env = isolated_env(domain)
    bag = d / "run.mcap"
    if case.expect == "disk-full":
        bag.unlink(missing_ok=True)
        bag.symlink_to("/dev/full")
    procs = {
        "evaluator": start_node(
            node_command(
                sys.executable,
                EVALUATOR,
                "evaluator",
                {"output": str(bag), "overwrite": True, "methods": list(METHODS), "completion_timeout": 15.0},
            ),
            d / "evaluator.log",
            env,
        )
    }
    for m in METHODS:
        procs[m] = start_node(
            node_command(
                sys.executable,
                ESTIMATOR,
                f"estimator_{m}",
                {"method": m, "scenario": SCENARIO, "stats_file": str(d / f"{m}.json"), "log_throttle": 0.5},
            ),
            d / f"{m}.log",
            env,
        )
    scen = make_scenario(SCENARIO)
    data = simulate(scen, N, T, seed=7)
    dt_ns = MSG.dt_ns(scen.dt)
    levels: dict[str, int] = {}
    rss: dict[str, float | None] = {}
    rss_before: dict[str, float | None] = {}
    worst_msg: dict[str, str] = {}
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain)
    t_start = time.monotonic()
    try:
        node = rclpy.create_node("chaos", context=ctx)
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(node)

        def on_diag(msg) -> None:
            for st in msg.status:
                lv = int.from_bytes(st.level, "little") if isinstance(st.level, bytes) else int(st.level)
                if lv > levels.get(st.name, -1):
                    worst_msg[st.name] = st.message
                levels[st.name] = max(levels.get(st.name, 0), lv)

        node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 50)
        pubs = {
            "scenario": node.create_publisher(String, "scenario", latched_qos()),
            "run_status": node.create_publisher(String, "run_status", latched_qos()),
            "observation": node.create_publisher(JointState, "observation", stream_qos(10_000)),
            "ground_truth": node.create_publisher(JointState, "ground_truth", stream_qos(10_000)),
        }
        # the fault comes from another publisher (an intruder on the domain, or a second, broken
        # driver): what it does to its own writer must not be mistaken for what it does to the nodes
        intruder = rclpy.create_node("intruder", context=ctx)
        bad_pubs = {
            "scenario": intruder.create_publisher(String, "scenario", latched_qos()),
            "observation": intruder.create_publisher(JointState, "observation", stream_qos(100)),
        }
        while (
            min(pubs["observation"].get_subscription_count(), bad_pubs["observation"].get_subscription_count())
            < len(METHODS) + 1
        ):
            ex.spin_once(timeout_sec=0.05)
            if time.monotonic() - t_start > 60:
                raise RuntimeError("the nodes did not subscribe within 60 s")
        time.sleep(0.5)  # the other topics' discovery

        def publish_run(start_ns: int, first_trajectory: int = 0, last: bool = True, fault: bool = True) -> None:
            info = {"trajectories": N, "horizon": T, "messages": N * T}
            pubs["scenario"].publish(
                MSG.encode_scenario(scen.describe(), seed=7, rate_hz=RATE_HZ, start_ns=start_ns, dt_ns=dt_ns, **info)
            )
            pubs["run_status"].publish(MSG.encode_run_status(MSG.STATUS_STARTED, **info))
            t0 = time.perf_counter()
            for i, ((n, k), obs, truth) in enumerate(_messages(scen, data, start_ns, dt_ns)):
                if n < first_trajectory:
                    continue
                if fault and (n, k) == INJECT_AT:
                    rss_before.update({m: _rss_mib(procs[m].pid) for m in METHODS})
                    for topic, raw in _fault(case.name, scen, data, start_ns, dt_ns):
                        bad_pubs[topic].publish(raw)
                pubs["observation"].publish(obs)
                pubs["ground_truth"].publish(truth)
                wait = t0 + i / RATE_HZ - time.perf_counter()
                if wait > 0:
                    time.sleep(wait)
                ex.spin_once(timeout_sec=0)
            if last:
                pubs["run_status"].publish(MSG.encode_run_status(MSG.STATUS_COMPLETE, **info))

        start_ns = 10**18
        if case.expect == "restart":  # trajectory 0, then killed; the new run's stamps 10x earlier
            publish_run(start_ns, last=False, fault=False)  # (all of it: the estimators see a whole run)
            time.sleep(1.0)
            publish_run(start_ns // 10, fault=False)
        else:
            publish_run(start_ns)
        while procs["evaluator"].poll() is None and time.monotonic() - t_start < timeout:
            ex.spin_once(timeout_sec=0.1)
        for _ in range(20):  # the last diagnostics windows
            ex.spin_once(timeout_sec=0.05)
        rss.update({m: _rss_mib(procs[m].pid) for m in METHODS})
    finally:
        rclpy.try_shutdown(context=ctx)
        for name, p in procs.items():
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for p in procs.values():
            try:
                p.wait(timeout=15)
            except Exception:
                p.kill()
    row = _summarize(case, d, procs, levels)
    row["worst_diagnostics"] = worst_msg  # the message of each status at its worst level
    row["rss_mib"] = rss  # each estimator's resident memory at the end of the run
    row["rss_growth_mib"] = {  # ... less what it held just before the fault
        m: round(rss[m] - rss_before[m], 1) if rss.get(m) and rss_before.get(m) else None for m in METHODS
    }
    if case.expect == "oversize" and not all(
        g is not None and g < OVERSIZE_KEPT_MIB for g in row["rss_growth_mib"].values()
    ):
        row["verdict"] = ("FAIL: " if row["verdict"] == "PASS" else row["verdict"] + "; ") + (
            f"memory kept after the oversize messages: {row['rss_growth_mib']} MiB"
        )
    return row


# An estimator that kept the three 20 MB messages would grow by 3 x 19.1 = 57 MiB (measured before
# the nodes' DDS profile, docs/reliability.md). One that drops them grows by about one message's
# worth: 19.7 (EKF) and 20.2 MiB (UKF) measured at load average 5 to 7, 20.0 MiB in a failed test run
# under load, where the criterion was "< 20": a bounded retention (one message's worth for three
# messages: the last one, or the allocator's arena for its transient decode), not an accumulation.
# The bound is two messages' worth: it fails a node that keeps two or all three, and sits 1.9x above
# the retention measured, where "< 20" sat on it.
OVERSIZE_MESSAGE_MIB = 20e6 / 2**20
OVERSIZE_KEPT_MIB = 2 * OVERSIZE_MESSAGE_MIB


def _rss_mib(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return round(int(line.split()[1]) / 1024, 1)
    except OSError:
        pass
    return None


def _summarize(case: Case, d: Path, procs: dict, levels: dict) -> dict:
    logs = {name: (d / f"{name}.log").read_text(errors="replace") for name in procs}
    stats = {}
    for m in METHODS:
        try:
            stats[m] = json.loads((d / f"{m}.json").read_text())
        except (OSError, ValueError):
            stats[m] = None
    ev = logs["evaluator"]
    rmse = re.search(r"^\s*ukf\s*\|?\s*([0-9.]+)", ev, re.M) or re.search(r"ukf\s+([0-9.]+)", ev)
    lost = [ln.strip() for ln in ev.splitlines() if re.match(r"\s+(observation|ground_truth|estimates/)", ln)]
    # Each estimator publishes two statuses: "<node>: <method> estimator" (what it did with the
    # messages: faults, drops, divergence) and "<node>: <method> estimator: input <topic>" (the input's
    # frequency and staleness, ERROR once the run has ended and the input stops). Kept apart: merged,
    # the staleness after every run's end would read ERROR in every case, the clean one included.
    worst = {m: max((v for k, v in levels.items() if k.endswith(f"{m} estimator")), default=-1) for m in METHODS}
    worst_input = {m: max((v for k, v in levels.items() if f"{m} estimator: input " in k), default=-1) for m in METHODS}
    row = {
        "case": case.name,
        "fault": case.what,
        "estimates": {m: (s or {}).get("estimates") for m, s in stats.items()},
        "skipped": {
            m: {k: s.get(k, 0) for k in ("bad", "oversize", "out_of_order", "unconfirmed", "quarantined", "gap_steps")}
            if s
            else None
            for m, s in stats.items()
        },
        "publisher_restarts": {m: (s or {}).get("publisher_restarts") for m, s in stats.items()},
        "worst_level": worst,
        "worst_input_level": worst_input,
        "returncodes": {n: p.returncode for n, p in procs.items()},
        "ukf_rmse": float(rmse.group(1)) if rmse else None,
        "evaluator_lost": [ln for ln in lost if " 0 lost" not in ln or "not used" in ln],
        "evaluator_error": next((ln for ln in ev.splitlines() if "[ERROR]" in ln), ""),
        "tracebacks": [n for n, text in logs.items() if "Traceback" in text],
    }
    row["verdict"] = _verdict(case, row)
    return row


def _verdict(case: Case, r: dict) -> str:
    problems = []
    if r["tracebacks"]:
        problems.append(f"traceback in {', '.join(r['tracebacks'])}")
    want_eval = 1 if case.expect == "disk-full" else 0
    codes = r["returncodes"]
    if codes.get("evaluator") != want_eval:
        problems.append(f"evaluator exit {codes.get('evaluator')}")
    if any(codes.get(m) not in (0, -2) for m in METHODS):
        problems.append(f"estimator exits {[codes.get(m) for m in METHODS]}")
    total = N * T * (2 if case.expect == "restart" else 1)
    if case.expect in ("estimated-all", "oversize", "restart"):
        short = {m: n for m, n in r["estimates"].items() if n != total}
        if short:
            problems.append(f"estimates {short} of {total}")
        quiet_ok = ("clean", "huge-announcement")  # nothing reaches the estimators' streams: OK is the truth
        if case.name not in quiet_ok and case.expect != "restart" and min(r["worst_level"].values()) < 1:
            problems.append("diagnostics never left OK")
        if r["ukf_rmse"] is None:
            problems.append("no metrics")
    if case.expect == "oversize" and any((s or {}).get("oversize") != 3 for s in r["skipped"].values()):
        problems.append("oversize not counted 3 times")
    if case.expect == "disk-full" and "No space left on device" not in r["evaluator_error"]:
        problems.append("no one-line disk-full error")
    return "PASS" if not problems else "FAIL: " + "; ".join(problems)


def table(rows: list[dict]) -> str:
    lines = [
        "| case | fault | estimates ekf / ukf | held / dropped (ukf) | worst estimator status ekf / ukf | "
        "worst input status ekf / ukf | evaluator exit | "
        "UKF RMSE | evaluator says lost | UKF RSS MiB (growth after the fault) | verdict |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    names = {-1: "none", 0: "OK", 1: "WARN", 2: "ERROR"}
    for r in rows:
        sk = r["skipped"].get("ukf") or {}
        dropped = sum(sk.get(k, 0) for k in ("bad", "oversize", "out_of_order", "unconfirmed"))
        est = " / ".join(str(r["estimates"].get(m)) for m in METHODS)
        worst = " / ".join(names.get(r["worst_level"].get(m, -1), "?") for m in METHODS)
        inputs = " / ".join(names.get(r.get("worst_input_level", {}).get(m, -1), "?") for m in METHODS)
        lost = "; ".join(r["evaluator_lost"]) or ("-" if not r["evaluator_error"] else r["evaluator_error"][-90:])
        rmse = f"{r['ukf_rmse']:.4f}" if r["ukf_rmse"] is not None else "-"
        lines.append(
            f"| {r['case']} | {r['fault']} | {est} | {sk.get('quarantined', '-')} / {dropped} | {worst} | {inputs} | "
            f"{r['returncodes'].get('evaluator')} | {rmse} | {lost} | {r.get('rss_mib', {}).get('ukf')} "
            f"({r.get('rss_growth_mib', {}).get('ukf')}) | "
            f"{r['verdict']} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", default="", help=f"comma-separated (default: all): {', '.join(c.name for c in CASES)}")
    ap.add_argument("--out", default="/tmp/chaos", help="directory of the bags, logs and chaos.json")
    args = ap.parse_args(argv)
    wanted = [c for c in CASES if not args.cases or c.name in args.cases.split(",")]
    unknown = set(args.cases.split(",")) - {c.name for c in CASES} - {""}
    if unknown:
        print(f"chaos: unknown case(s) {sorted(unknown)}", file=sys.stderr)
        return 2
    out = Path(args.out)
    rows = []
    for case in wanted:
        t0 = time.monotonic()
        rows.append(run_case(case, out))
        print(f"chaos: {case.name}: {rows[-1]['verdict']} ({time.monotonic() - t0:.0f} s)", flush=True)
    (out / "chaos.json").write_text(json.dumps(rows, indent=1))
    print(table(rows), end="")
    return 0 if all(r["verdict"] == "PASS" for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
