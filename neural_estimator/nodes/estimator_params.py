"""Parameters of the estimator node (documented in params/estimator.yaml; the docs' tables are
generated from this dataclass), shared by the estimator and the lifecycle estimator."""

from __future__ import annotations

import dataclasses

from neural_estimator.nodes.common import param
from neural_estimator.stream.online import (
    DEFAULT_CONFIRM,
    DEFAULT_MAX_GAP,
    DEFAULT_MAX_GAP_SECONDS,
    DEFAULT_QUARANTINE_SECONDS,
    OnlineEstimator,
)
from neural_estimator.methods import table

OBSERVATION_QOS = ("reliable", "sensor_data")


@dataclasses.dataclass(frozen=True)
class EstimatorParams:
    """Parameters of the estimator node (documented in params/estimator.yaml)."""

    method: str = param("ukf", f"estimation method: one of {', '.join(table.names())}")
    scenario: str = param("", "scenario name; empty = take it (with its constants) from the 'scenario' topic")
    set: tuple[str, ...] = param((), "scenario constants as name=value (with scenario set)")
    preset: str = param("", "named constants of that scenario, applied before set (empty = the defaults; e.g. v3)")
    model_set: str = param(
        "",
        "model-based methods (filters, baselines, hybrid): the model they are given, as name=value items "
        "separated by commas on top of the scenario's constants (e.g. forcing=8.5,g=9.0; Q=2 / R=0.5 scale the "
        "noise covariances they are told); empty = the true model; networks ignore it",
    )
    plugins: tuple[str, ...] = param((), "Python files registering user scenarios")
    checkpoint: str = param("", "neural methods: checkpoint directory or card.json; empty = shipped default")
    device: str = param("cpu", "torch device of neural methods: cpu, cuda, cuda:N, auto")
    seed: int = param(0, "seed of the random draws of the EnKF and PF")
    init: str = param(
        "prior",
        "how a classical filter starts each trajectory: prior (the paper's start) or observation (the state the "
        "first observation determines where h is invertible, e.g. Lorenz 96 x0 = y0; prior mean elsewhere)",
    )
    threads: int = param(
        1, "torch intra-op threads of neural methods (one suits one-step, B = 1 updates); 0 = torch's default"
    )
    options: tuple[str, ...] = param(
        (),
        "method options as name=value: filter hyperparameters (n_particles=2048), neural compile_step=true, "
        f"context=100 (bounded context: restarted copies for {'/'.join(table.labels(context='recurrent'))}, "
        f"the attention window for {'/'.join(table.labels(context='window'))})",
    )
    observation_topic: str = param("observation", "input topic (relative: namespaced and remappable)")
    scenario_topic: str = param("scenario", "topic of the scenario description (when scenario is empty)")
    output_topic: str = param("", "estimate topic; empty = estimates/<method>; covariance goes to <output>/covariance")
    publish_covariance: bool = param(True, "publish the covariance where the method has one")
    publish_odometry: bool = param(
        True, "publish nav_msgs/Odometry on <output>/odometry where the scenario declares a pose"
    )
    frame_id: str = param(
        "map", "header.frame_id of estimates, covariances and odometry (the estimate's coordinate frame)"
    )
    child_frame_id: str = param("base_link", "child_frame_id of the odometry")
    observation_qos: str = param(
        "reliable",
        "observation subscription reliability: reliable or sensor_data (best effort); "
        "durability follows the publishers (transient_local when all offer it)",
    )
    queue_depth: int = param(10000, "subscription queue (KEEP_LAST): observations buffered while busy")
    drain: bool = param(
        True,
        "take every waiting observation at each wake-up and step them in arrival order (false: one per wake-up)",
    )
    max_delay: float = param(
        0.0,
        "seconds: when the oldest waiting observation was published longer ago than this, only the newest "
        "is stepped and the older ones are dropped (counted; the gap rule bridges or restarts); 0 = never drop",
    )
    delay_warn: float = param(
        0.1, "seconds: diagnostics WARN when observations wait longer than this (p99 of the window) before their step"
    )
    history_depth: int = param(10000, "estimate publisher depth (transient_local): a late or slow recorder's backlog")
    history_mb: float = param(
        64.0,
        "memory bound of each estimate publisher's history (MiB): depth = min(history_depth, "
        "history_mb / message size); large covariances get a shorter history",
    )
    max_gap: int = param(DEFAULT_MAX_GAP, "most missing steps bridged by predict-only steps before a restart")
    max_gap_seconds: float = param(
        DEFAULT_MAX_GAP_SECONDS,
        "most seconds spent bridging one gap before a restart (bounds the cost of a step jump; 0 = no bound)",
    )
    confirm: int = param(
        DEFAULT_CONFIRM,
        "messages that must agree before a jump in trajectory or step (or a new run) is accepted; "
        "1 = accept any single message's jump",
    )
    quarantine_seconds: float = param(
        DEFAULT_QUARANTINE_SECONDS,
        "a held jump is accepted after this long (or 4 inter-arrival times) with no message of the current stream",
    )
    diagnostics_period: float = param(1.0, "seconds between /diagnostics messages")
    log_throttle: float = param(2.0, "seconds between repeated warnings of one kind")
    stats_file: str = param("", "write the counters and latency percentiles as JSON here at shutdown ('' = no)")


def online_estimator(est, method: str, p: EstimatorParams, horizon: int | None = None) -> OnlineEstimator:
    """The per-message estimator these parameters describe (the estimator and lifecycle nodes)."""
    return OnlineEstimator(
        est,
        method,
        publish_covariance=p.publish_covariance,
        max_gap=p.max_gap,
        max_gap_seconds=p.max_gap_seconds,
        frame_id=p.frame_id,
        confirm=max(1, p.confirm),
        quarantine_seconds=max(0.0, p.quarantine_seconds),
        horizon=horizon,
    )
