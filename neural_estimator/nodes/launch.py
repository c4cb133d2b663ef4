"""Start a live comparison as processes: simulator -> estimators -> evaluator (no ``ros2 launch``).

    neural-estimator live --scenario lorenz96 --methods ekf,ukf,gru \
        --trajectories 2 --output runs/l96.mcap

Every process gets the same ``ROS_DOMAIN_ID`` (:func:`pick_domain_id`: ``--domain-id``, else one
at random from the range ``NEURAL_ESTIMATOR_DOMAINS`` names, else the caller's ``ROS_DOMAIN_ID``,
else one at random in 100..199) and ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` (unless set), so a
run stays off other graphs on the machine. Start order: the evaluator, then one estimator node per
method (``estimator_<method>``), then the simulator, told to wait for ``len(methods) + 1``
observation subscribers: it starts once everybody listens. The launcher then waits for the
evaluator (which exits after writing the bag and the metrics), stops the estimators with SIGINT
and reports. A node that dies early stops the run with its log in the error. This module does
not import rclpy: nodes run as ``python -m <module> --ros-args ...``. The nodes and their
parameters come from :mod:`neural_estimator.nodes.graph`, the description ``ros2 launch
neural_estimator live.launch.py`` starts too.
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

from neural_estimator.nodes.graph import (  # noqa: F401 - re-exported: the one description of the graph
    ESTIMATOR,
    EVALUATOR,
    MAX_DEPTH,
    SIMULATOR,
    NodeSpec,
    PipelineConfig,
    command,
    live_nodes,
    ros_arg,
)
from neural_estimator.nodes.realtime import MAX_PRIORITY, REALTIME_ENV


class PipelineError(RuntimeError):
    """The run could not complete; the message names the node and ends with its log."""


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


def node_command(python: str, module: str, name: str, params: dict[str, Any]) -> list[str]:
    """``python -m module --ros-args -r __node:=name -p k:=v ...`` (empty lists are left out: an
    empty YAML list has no type)."""
    return command(python, NodeSpec(name, module, params))


DOMAINS_VARIABLE = "NEURAL_ESTIMATOR_DOMAINS"  # LO-HI (or one id): the ROS domains this project may pick
MAX_DOMAIN_ID = 232  # Fast DDS's ports stay below 65535 up to domain 232


class DomainError(ValueError):
    """A domain range or id that ROS cannot use; the message names the variable and the value."""


def domain_range(default: tuple[int, int] = (100, 199)) -> tuple[int, int]:
    """The inclusive range of ROS domains to pick from: ``NEURAL_ESTIMATOR_DOMAINS`` (``LO-HI`` or one
    id) when set, else ``default``. Raises DomainError for a malformed range or one outside 0..232."""
    text = os.environ.get(DOMAINS_VARIABLE, "").strip()
    if not text:
        return default
    lo, sep, hi = text.partition("-")
    try:
        lo_i, hi_i = int(lo), int(hi if sep else lo)
    except ValueError:
        raise DomainError(f"{DOMAINS_VARIABLE}={text!r}: expected LO-HI (e.g. 40-49) or one domain id") from None
    if not 0 <= lo_i <= hi_i <= MAX_DOMAIN_ID:
        raise DomainError(f"{DOMAINS_VARIABLE}={text!r}: need 0 <= LO <= HI <= {MAX_DOMAIN_ID}")
    return lo_i, hi_i


def pick_domain_id(default: tuple[int, int] = (100, 199)) -> int:
    """The ROS domain a run uses when none is given: one at random from ``NEURAL_ESTIMATOR_DOMAINS``
    when that is set (a shared host's share of domains), else the caller's ``ROS_DOMAIN_ID`` when
    set, else one at random from ``default``."""
    if os.environ.get(DOMAINS_VARIABLE, "").strip():
        return random.SystemRandom().randint(*domain_range(default))
    own = os.environ.get("ROS_DOMAIN_ID", "").strip()
    if own:
        if not own.isdigit() or int(own) > MAX_DOMAIN_ID:
            raise DomainError(f"ROS_DOMAIN_ID={own!r}: expected a domain id in 0..{MAX_DOMAIN_ID}")
        return int(own)
    return random.SystemRandom().randint(*default)


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
    if cfg.realtime_priority:
        env[REALTIME_ENV] = str(cfg.realtime_priority)
    nodes = [(spec.name, command(cfg.python, spec)) for spec in live_nodes(cfg, str(bag))]

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
            _signal(p, sig)
        deadline = time.monotonic() + wait
        for p in alive:
            try:
                p.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                pass


def _signal(p: subprocess.Popen, sig: int) -> None:
    """``sig`` to the process group ``p`` leads (a node and the children it made), or to ``p`` alone
    when it shares its parent's group (``run_graph``'s nodes, in the terminal's group like ros2
    launch's): killpg on a pid that leads no group would signal nothing."""
    try:
        if os.getpgid(p.pid) == p.pid:
            os.killpg(p.pid, sig)
        else:
            p.send_signal(sig)
    except ProcessLookupError:
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


def run_graph(specs: list[NodeSpec], python: str = sys.executable, poll: float = 0.1) -> int:
    """Start a graph's nodes as processes in this ROS environment (no domain of their own, output to
    this terminal, as ``ros2 launch`` does) and wait: until a required node exits (then the others
    get SIGINT), or, with none required, until every node exited. Ctrl-C / SIGTERM stop them all.
    Returns the first non-zero exit status of a required node (else 0)."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    procs = {s.name: subprocess.Popen(command(python, s), env=env, preexec_fn=die_with_parent) for s in specs}
    required = [s.name for s in specs if s.required]
    try:
        while True:
            if required and any(procs[n].poll() is not None for n in required):
                break
            if not required and all(p.poll() is not None for p in procs.values()):
                break
            time.sleep(poll)
    except KeyboardInterrupt:
        pass
    finally:
        _stop_all(procs)
    codes = [procs[n].returncode for n in required if procs[n].returncode not in (None, 0)]
    return codes[0] if codes else 0


def build_parser() -> argparse.ArgumentParser:
    from neural_estimator.core.arguments import OneLineParser  # one-line usage errors with "did you mean"

    p = OneLineParser(
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
    p.add_argument(
        "--init",
        choices=("prior", "observation"),
        default="prior",
        help="how the classical filters start: prior (default, the paper's start) or observation (the state the "
        "first observation determines where h is invertible; Lorenz 96: x0 = y0)",
    )
    p.add_argument("--device", default="cpu")
    p.add_argument("--no-covariance", action="store_true", help="do not publish covariances")
    p.add_argument("--output", default="", help="bag path (default runs/<scenario>-<date>-<time>.mcap)")
    p.add_argument(
        "--domain-id",
        type=int,
        default=None,
        help=f"ROS domain of the run (default: one from {DOMAINS_VARIABLE}=LO-HI when set, else ROS_DOMAIN_ID "
        "when set, else a random one in 100..199)",
    )
    p.add_argument("--timeout", type=float, default=600.0)
    p.add_argument(
        "--realtime-priority",
        type=int,
        default=0,
        metavar="N",
        help="run every node on SCHED_FIFO at priority N (1-99; needs root, CAP_SYS_NICE or an rtprio limit; "
        "0: normal scheduling); keeps the estimates current on a busy machine, see docs/performance.md",
    )
    return p


def check_arguments(a: argparse.Namespace) -> None:
    """Scenario, constants and methods checked before any node starts (a bad name is the command
    line's one-line error, not a node's fatal log after start-up)."""
    from neural_estimator.methods.interface import check_method
    from neural_estimator.scenarios import load_plugins, make_scenario, parse_assignments

    load_plugins(a.plugin)
    make_scenario(a.scenario, **parse_assignments(a.set))
    for m in a.methods.split(","):
        if m.strip():
            check_method(m)
    if a.horizon < 0 or a.trajectories < 1:
        raise ValueError(
            f"--trajectories must be >= 1 and --horizon >= 0 (0 = the scenario's), got {a.trajectories} and {a.horizon}"
        )
    if not 0 <= a.realtime_priority <= MAX_PRIORITY:
        raise ValueError(f"--realtime-priority must be from 0 (off) to {MAX_PRIORITY}, got {a.realtime_priority}")


def main(argv: list[str] | None = None) -> int:
    from neural_estimator.methods.interface import EstimatorError
    from neural_estimator.scenarios import ScenarioError

    a = build_parser().parse_args(argv)
    from neural_estimator.nodes.entry import NO_RCLPY, rclpy_missing

    if rclpy_missing():
        print(NO_RCLPY.format(name="neural-estimator live"), file=sys.stderr)
        return 1
    try:
        check_arguments(a)
    except (ScenarioError, EstimatorError, ValueError) as exc:
        print(f"neural-estimator live: error: {exc}", file=sys.stderr)
        return 2
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
        init=a.init,
        device=a.device,
        publish_covariance=not a.no_covariance,
        output=a.output,
        domain_id=a.domain_id,
        timeout=a.timeout,
        realtime_priority=a.realtime_priority,
    )

    def terminate(signum, frame):  # SIGTERM: stop the nodes too (run_pipeline's clean-up runs)
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, terminate)
    try:
        res = run_pipeline(cfg, echo=True)
    except (PipelineError, DomainError) as exc:
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
