"""Start a live comparison as processes: simulator -> estimators -> evaluator (no ``ros2 launch``).

    neural-estimator live --scenario lorenz96 --methods ekf,ukf,gru \
        --trajectories 2 --output runs/l96.mcap

Every process gets the same, otherwise unused ``ROS_DOMAIN_ID`` (random in 100..199 unless given)
and ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` (unless set), so a run never meets another one on
the machine. Start order: the evaluator, then one estimator node per method (``estimator_<method>``),
then the simulator, told to wait for ``len(methods) + 1`` observation subscribers: it starts once
everybody listens. The launcher then waits for the evaluator (which exits after writing the bag
and the metrics), stops the estimators with SIGINT and reports. A node that dies early stops the
run with its log in the error. This module does not import rclpy: nodes run as
``python -m <module> --ros-args ...``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import random
import signal
import subprocess
import sys
import time
from datetime import datetime
from pathlib import Path
from typing import Any

SIMULATOR = "sim_nodes.simulator"
ESTIMATOR = "neural_estimator.nodes.estimator_node"
EVALUATOR = "neural_estimator.nodes.evaluator_node"
MAX_DEPTH = 100_000  # queue depth cap (about 30 MB per transient_local stream)


class PipelineError(RuntimeError):
    """The run could not complete; the message names the node and ends with its log."""


@dataclasses.dataclass(frozen=True)
class PipelineConfig:
    """One live run (the simulator's, estimators' and evaluator's parameters that matter)."""

    scenario: str
    methods: tuple[str, ...]
    trajectories: int = 2
    horizon: int = 0  # 0 = the scenario's
    rate_hz: float = 0.0  # 0 = real time (1 / dt)
    seed: int = 0
    set: tuple[str, ...] = ()  # scenario constants name=value
    preset: str = ""  # named scenario constants applied before set; empty = the defaults
    plugins: tuple[str, ...] = ()  # files registering user scenarios
    noise_scale: float = -1.0  # negative = the scenario's
    checkpoints: tuple[str, ...] = ()  # method=path for neural methods
    options: tuple[str, ...] = ()  # method.name=value filter hyperparameters
    device: str = "cpu"
    publish_covariance: bool = True
    output: str = ""  # bag path; empty = runs/<scenario>-<date>-<time>.mcap
    domain_id: int | None = None
    timeout: float = 600.0  # s for the whole run
    record_topics: tuple[str, ...] = ()  # extra topics for the evaluator to record (e.g. /diagnostics)
    stats_dir: str = ""  # each estimator writes <stats_dir>/<method>.json at shutdown ('' = no)
    python: str = sys.executable


@dataclasses.dataclass
class PipelineResult:
    bag: Path
    domain_id: int
    returncodes: dict[str, int]
    logs: dict[str, Path]
    reports: dict[str, Path]  # markdown / json / png beside the bag (when written)
    seconds: float

    def metrics(self) -> dict[str, Any]:
        """The evaluator's JSON report."""
        return json.loads(self.reports["json"].read_text())


def ros_arg(value: Any) -> str:
    """A parameter value as ``--ros-args -p name:=VALUE`` parses it (YAML)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, (list, tuple)):
        return json.dumps([str(v) for v in value]) if value else "[]"
    return json.dumps(str(value))  # a quoted YAML string: "123" stays a string


def node_command(python: str, module: str, name: str, params: dict[str, Any]) -> list[str]:
    """``python -m module --ros-args -r __node:=name -p k:=v ...`` (empty lists are left out: an
    empty YAML list has no type)."""
    cmd = [python, "-m", module, "--ros-args", "-r", f"__node:={name}"]
    for k, v in params.items():
        if isinstance(v, (list, tuple)) and not v:
            continue
        cmd += ["-p", f"{k}:={ros_arg(v)}"]
    return cmd


def pick_domain_id() -> int:
    """A random ROS domain in 100..199 (Fast DDS ports stay below 65535 up to 232)."""
    return random.SystemRandom().randint(100, 199)


def isolated_env(domain_id: int) -> dict[str, str]:
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = str(domain_id)
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    env["PYTHONUNBUFFERED"] = "1"
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):  # one small step per message:
        env.setdefault(var, "1")  # threads only compete with the other nodes
    env.setdefault("MPLBACKEND", "Agg")
    return env


def die_with_parent() -> None:
    """``preexec_fn`` of node processes: SIGTERM when the launching process dies, however it dies
    (the nodes run in their own session, so a terminal's Ctrl-C does not reach them either)."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):  # not Linux: the launcher's own clean-up still applies
        pass


def start_node(cmd: list[str], log: Path, env: dict[str, str]) -> subprocess.Popen:
    """One node process, output to ``log``, in its own session, ended when the caller dies."""
    with open(log, "wb") as fh:
        return subprocess.Popen(
            cmd, stdout=fh, stderr=subprocess.STDOUT, env=env, start_new_session=True, preexec_fn=die_with_parent
        )


def run_pipeline(cfg: PipelineConfig, *, echo: bool = False) -> PipelineResult:
    """Run the chain once and wait for the evaluator (see the module docstring).

    Raises:
        PipelineError: a node exited early with an error, or the run exceeded ``cfg.timeout``.
    """
    if not cfg.methods:
        raise PipelineError("no methods given")
    bag = Path(cfg.output or f"runs/{cfg.scenario}-{datetime.now():%Y%m%d-%H%M%S}.mcap")
    log_dir = bag.with_name(bag.stem + ".logs")
    log_dir.mkdir(parents=True, exist_ok=True)
    domain = cfg.domain_id if cfg.domain_id is not None else pick_domain_id()
    env = isolated_env(domain)
    ckpt = dict(c.split("=", 1) for c in cfg.checkpoints)
    opts: dict[str, list[str]] = {}
    for item in cfg.options:
        key, _, value = item.partition("=")
        method, _, name = key.partition(".")
        opts.setdefault(method, []).append(f"{name}={value}")

    # Every queue holds the whole run (up to MAX_DEPTH messages): a node that falls behind catches
    # up later instead of losing messages (reliable, KEEP_LAST; transient_local publishers keep
    # this many messages in memory).
    depth = int(min(MAX_DEPTH, max(10_000, cfg.trajectories * (cfg.horizon or 10_000) + 100)))
    nodes: list[tuple[str, list[str]]] = [
        (
            "evaluator",
            node_command(
                cfg.python,
                EVALUATOR,
                "evaluator",
                {
                    "output": str(bag),
                    "overwrite": True,
                    "methods": list(cfg.methods),
                    "completion_timeout": 60.0,
                    "topics": list(cfg.record_topics),
                    "queue_depth": depth,
                },
            ),
        ),
    ]
    for m in cfg.methods:
        nodes.append(
            (
                f"estimator_{m}",
                node_command(
                    cfg.python,
                    ESTIMATOR,
                    f"estimator_{m}",
                    {
                        "method": m,
                        "scenario": cfg.scenario,
                        "set": list(cfg.set),
                        "preset": cfg.preset,
                        "plugins": list(cfg.plugins),
                        "checkpoint": ckpt.get(m, ""),
                        "device": cfg.device,
                        "seed": cfg.seed,
                        "options": opts.get(m, []),
                        "publish_covariance": cfg.publish_covariance,
                        "stats_file": str(Path(cfg.stats_dir) / f"{m}.json") if cfg.stats_dir else "",
                        "queue_depth": depth,
                        "history_depth": depth,
                    },
                ),
            )
        )
    nodes.append(
        (
            "simulator",
            node_command(
                cfg.python,
                SIMULATOR,
                "simulator",
                {
                    "scenario": cfg.scenario,
                    "set": list(cfg.set),
                    "preset": cfg.preset,
                    "plugins": list(cfg.plugins),
                    "noise_scale": float(cfg.noise_scale),
                    "seed": cfg.seed,
                    "trajectories": cfg.trajectories,
                    "horizon": cfg.horizon,
                    "rate_hz": float(cfg.rate_hz),
                    "wait_for_subscribers": len(cfg.methods) + 1,
                    "wait_timeout": 120.0,
                    "start_delay": 1.0,
                    "history_depth": depth,
                    "linger": 120.0,
                    "stay_after_run": 0.0,
                },
            ),
        )
    )

    procs: dict[str, subprocess.Popen] = {}
    logs: dict[str, Path] = {}
    t0 = time.monotonic()
    try:
        for name, cmd in nodes:
            logs[name] = log_dir / f"{name}.log"
            procs[name] = start_node(cmd, logs[name], env)
        while True:
            rc = procs["evaluator"].poll()
            if rc is not None:
                break
            for name, proc in procs.items():
                code = proc.poll()
                if code not in (None, 0) and name != "evaluator":
                    raise PipelineError(f"{name} exited with status {code}:\n{_tail(logs[name])}")
            if time.monotonic() - t0 > cfg.timeout:
                raise PipelineError(
                    f"the run took longer than {cfg.timeout:g} s; evaluator log:\n{_tail(logs['evaluator'])}"
                )
            time.sleep(0.1)
    finally:
        _stop_all(procs)
    codes = {n: p.returncode for n, p in procs.items()}
    if echo:
        sys.stdout.write(_table_from_log(logs["evaluator"]))
    reports = {
        k: bag.with_name(bag.stem + suffix)
        for k, suffix in (("markdown", ".metrics.md"), ("json", ".metrics.json"), ("png", ".rmse.png"))
    }
    reports = {k: p for k, p in reports.items() if p.exists()}
    if codes["evaluator"] != 0:
        raise PipelineError(f"evaluator exited with status {codes['evaluator']}:\n{_tail(logs['evaluator'])}")
    return PipelineResult(bag, domain, codes, logs, reports, time.monotonic() - t0)


def _stop_all(procs: dict[str, subprocess.Popen], grace: float = 5.0) -> None:
    """SIGINT (the nodes close cleanly), then SIGTERM, then SIGKILL, to each process group."""
    for sig, wait in ((signal.SIGINT, grace), (signal.SIGTERM, 2.0), (signal.SIGKILL, 2.0)):
        alive = [p for p in procs.values() if p.poll() is None]
        if not alive:
            return
        for p in alive:
            try:
                os.killpg(p.pid, sig)
            except ProcessLookupError:
                pass
        deadline = time.monotonic() + wait
        for p in alive:
            try:
                p.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                pass


def _tail(path: Path, lines: int = 25) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return "(no log)"


def _table_from_log(path: Path) -> str:
    """The evaluator's printed table (its stdout lines that are not ROS log lines)."""
    try:
        text = path.read_text(errors="replace")
    except OSError:
        return ""
    keep = [ln for ln in text.splitlines() if ln and not ln.startswith("[")]
    return "\n".join(keep) + "\n" if keep else ""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="neural-estimator live", description="Live comparison on ROS 2: simulator -> estimators -> evaluator."
    )
    p.add_argument("--scenario", required=True)
    p.add_argument("--methods", required=True, help="comma-separated, e.g. ekf,ukf,gru")
    p.add_argument("--trajectories", type=int, default=2)
    p.add_argument("--horizon", type=int, default=0, help="steps (0 = the scenario's)")
    p.add_argument("--rate-hz", type=float, default=0.0, help="observations per second (0 = real time)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="scenario constant")
    p.add_argument(
        "--preset", default="", metavar="NAME", help="named scenario constants, applied before --set (e.g. v3)"
    )
    p.add_argument("--plugin", action="append", default=[], metavar="FILE", help="file registering user scenarios")
    p.add_argument("--noise-scale", type=float, default=-1.0)
    p.add_argument("--checkpoint", action="append", default=[], metavar="METHOD=DIR")
    p.add_argument("--option", action="append", default=[], metavar="METHOD.NAME=VALUE")
    p.add_argument("--device", default="cpu")
    p.add_argument("--no-covariance", action="store_true", help="do not publish covariances")
    p.add_argument("--output", default="", help="bag path (default runs/<scenario>-<date>-<time>.mcap)")
    p.add_argument("--domain-id", type=int, default=None)
    p.add_argument("--timeout", type=float, default=600.0)
    return p


def main(argv: list[str] | None = None) -> int:
    a = build_parser().parse_args(argv)
    cfg = PipelineConfig(
        scenario=a.scenario,
        methods=tuple(m.strip() for m in a.methods.split(",") if m.strip()),
        trajectories=a.trajectories,
        horizon=a.horizon,
        rate_hz=a.rate_hz,
        seed=a.seed,
        set=tuple(a.set),
        preset=a.preset,
        plugins=tuple(a.plugin),
        noise_scale=a.noise_scale,
        checkpoints=tuple(a.checkpoint),
        options=tuple(a.option),
        device=a.device,
        publish_covariance=not a.no_covariance,
        output=a.output,
        domain_id=a.domain_id,
        timeout=a.timeout,
    )

    def terminate(signum, frame):  # SIGTERM: stop the nodes too (run_pipeline's clean-up runs)
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, terminate)
    try:
        res = run_pipeline(cfg, echo=True)
    except PipelineError as exc:
        print(f"pipeline: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("pipeline: interrupted", file=sys.stderr)
        return 130
    print(
        f"bag: {res.bag} (ROS_DOMAIN_ID {res.domain_id}, {res.seconds:.1f} s); "
        + ", ".join(str(p) for p in res.reports.values())
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
