"""The paper's evaluation protocol: methods x evaluation sets -> metrics -> median +- IQR table.

Paper, "Evaluation Protocol": "Each scenario uses three independent evaluation datasets with 8,000
trajectories each. The default evaluation horizon is 500." Results are "summarized over
independent datasets and random initializations using medians with interquartile ranges".

For each method, every evaluation set (and, for neural methods, every checkpoint given: the paper
trains 15 instances per architecture) is one *run*; metrics are computed per run on the timesteps
after the paper's 10-step warm-up (``warmup``; see :mod:`neural_estimator.metrics`, "Effective
trajectory length"), then summarised as median and IQR across runs.

Memory: the batch is cut into chunks so that no chunk holds more than ``memory_budget`` bytes of
outputs (the per-step covariances dominate: T dx^2 8 bytes per trajectory, 6.4 MB for Lorenz 96)
plus the method's working set (the PF's particles). NEES is computed chunk by chunk, so the full
(N, T, dx, dx) covariance array never exists.

Long runs: a progress bar per run counts trajectory-steps (the classical filters advance it every
time step of a chunk, so its rate and ETA are those of the run in progress), and every finished
run is written at once to the result cache (:func:`run_key`), so an interrupted ``evaluate``
resumes from the runs it finished and a second one with more methods only computes the new ones.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from neural_estimator import metrics as M
from neural_estimator.filters.baselines import check_evaluated_method, is_baseline, make_baseline
from neural_estimator.data import Trajectories, evaluation_sets
from neural_estimator.data.io import DataError
from neural_estimator.data.protocol import default_cache_dir
from neural_estimator.data.simulate import trajectories_digest as dataset_digest
from neural_estimator.methods import table
from neural_estimator.methods.registry import (
    Estimator,
    Estimates,
    make_estimator,
    previous_controls,
)
from neural_estimator.filters.base import ClassicalFilter
from neural_estimator.core.options import parse_value
from neural_estimator.scenarios import Scenario
from neural_estimator.scenarios.model import model_set_of
from neural_estimator.evaluation.families import check_unsealed
from neural_estimator.evaluation.cache import checkpoint_digest, load_run, result_path, run_key, save_run
from neural_estimator.evaluation.starts import INIT_MODES, check_init, effective_init  # noqa: F401

if TYPE_CHECKING:
    from neural_estimator.serving.card import Checkpoint

DEFAULT_MEMORY_BUDGET = 1 << 30  # bytes per chunk; peak stays well under 8 GiB


@dataclass
class MethodResult:
    """All runs of one method."""

    method: str
    reports: list[M.MetricReport] = field(default_factory=list)
    seconds: float = 0.0  # wall time spent estimating (excludes data generation and metrics)
    steps: int = 0  # trajectory-steps estimated
    cached: int = 0  # runs read from the result cache (their seconds are those of the run that made them)
    context: int = 0  # neural: the bounded context it was served with (0: continuous, the paper's way)
    init: str = "prior"  # classical: how the filters started (INIT_MODES); neural methods ignore it
    # Per run, beside ``reports``: the per-trajectory errors (for paired comparisons), the index of
    # the evaluation set and of the trained instance (0 for a classical filter or a baseline).
    errors: list[M.TrajectoryErrors] = field(default_factory=list)
    set_index: list[int] = field(default_factory=list)
    instance: list[int] = field(default_factory=list)
    instance_dirs: list[str] = field(default_factory=list)  # neural: the checkpoint of each instance
    # the model set it was built with (--model-set; {} for the true model and for data-trained networks)
    model_set: dict[str, str] = field(default_factory=dict)

    @property
    def n_instances(self) -> int:
        return len(set(self.instance)) if self.instance else 1

    @property
    def baseline(self) -> bool:
        """A reference row (:mod:`neural_estimator.filters.baselines`), never ranked among the ten."""
        return is_baseline(self.method)

    def add(self, report: M.MetricReport, errors: M.TrajectoryErrors, set_index: int = 0, instance: int = 0) -> None:
        """One more run."""
        self.reports.append(report)
        self.errors.append(errors)
        self.set_index.append(int(set_index))
        self.instance.append(int(instance))

    def runs_by_set(self) -> list[list[M.TrajectoryErrors]]:
        """The runs' errors as ``[set][instance]``, sets in order (the shape of
        :func:`~neural_estimator.metrics.paired_ratio`)."""
        sets = sorted(set(self.set_index))
        return [[e for e, j in zip(self.errors, self.set_index) if j == s] for s in sets]

    @property
    def summary(self) -> dict[str, M.Stat]:
        return M.summarize(self.reports)

    @property
    def throughput(self) -> float:
        """Trajectory-steps per second."""
        return self.steps / self.seconds if self.seconds > 0 else float("nan")


def recorded_result(
    scenario: Scenario, data: Trajectories, x_hat: np.ndarray, name: str, warmup: int = M.EVALUATION_WARMUP
) -> MethodResult:
    """The metrics of estimates that were recorded, not computed here (a robot's own filter): one run,
    no time spent, so no speed is reported. ``warmup``: leading steps not scored (see :func:`evaluate`)."""
    if x_hat.shape != data.x.shape:
        raise DataError(f"recorded estimate {name!r} has shape {x_hat.shape}, the states have {data.x.shape}")
    lab = data.labelled  # partial ground truth: the labelled steps only
    report = M.compute_labelled_metrics(
        data.x, x_hat, scenario.angle_states, lab, diverged=~np.isfinite(x_hat).all(axis=(1, 2)), warmup=warmup
    )
    result = MethodResult(name)
    result.add(report, M.trajectory_errors(data.x, x_hat, scenario.angle_states, report.outlier_idx, warmup, lab))
    return result


def recorded_data_methods(
    methods: Sequence[str], checkpoints: Mapping[str, Sequence[str]], has_model: bool = False
) -> list[str]:
    """``methods`` if recorded data allow them all: a classical filter or a baseline needs the model
    of a system, which recorded data have only where their spec names one (``has_model``), and no
    model is shipped for recorded data, so each neural method must be given a checkpoint. Raises
    ValueError naming the first one refused."""
    for m in methods:
        if is_baseline(m) and not has_model:
            raise ValueError(f"{m}: recorded data have no model to propagate; baselines need a scenario")
        if table.has(m, needs_model=True) and not has_model:
            raise ValueError(
                f"{m}: recorded data have no model for a classical filter; compare the robot's own "
                "filter with --estimate NAME=FILE, or name the system's model in the spec (model:)"
            )
        if table.has(m, trainable=True) and m not in checkpoints:
            raise ValueError(f"{m}: recorded data have no shipped model: pass --checkpoint {m}=DIR")
    return list(methods)


def chunk_size(
    scenario: Scenario,
    method: str,
    horizon: int,
    n: int,
    budget: int = DEFAULT_MEMORY_BUDGET,
    options: Mapping[str, Any] | None = None,
) -> int:
    """Trajectories per chunk so one chunk's arrays stay within ``budget`` bytes.

    Per trajectory: outputs T (dx + dx^2) float64 plus the inputs, plus the members its spec names
    (the EnKF's members, the PF's particles, defaults from their hyperparameters; each a few
    dx-vectors of temporaries).
    """
    dx, dy, du = scenario.dx, scenario.dy, scenario.du
    per = horizon * (dx + dx * dx + dy + du) * 8
    members = table.members_per_stream(method, dict(options or {}), parse_value)  # the spec's members option
    if members is None:
        members = 2 * dx + 1
    per += members * (dx + dy) * 8 * 6
    return int(max(1, min(n, budget // per)))


def run_method(
    estimator: Estimator,
    data: Trajectories,
    chunk: int,
    angle_states: Sequence[int],
    on_chunk: Callable[[int], None] | None = None,
    on_steps: Callable[[int], None] | None = None,
    init: str = "prior",
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray, float]:
    """Estimate every trajectory of ``data`` chunk by chunk.

    Args:
        on_chunk: called with the number of trajectories of each finished chunk.
        on_steps: called with B after every time step of a chunk of B trajectories (classical
            filters, which loop over time: see :func:`run_stepwise`), or with B T after a chunk
            (neural models, whose parallel form has no steps to report); the calls add up to N T.
        init: ``"truth"`` starts the classical filters of each trajectory at its true x_0 (see
            :data:`INIT_MODES`); neural methods are unaffected.

    Returns:
        (x_hat (N, T, dx), nees (N, T) or None, diverged (N,), seconds spent in the estimator).
    """
    N = data.n
    x_hat = np.empty_like(data.x)
    diverged = np.zeros(N, dtype=bool)
    nees_all = np.empty(data.x.shape[:2]) if estimator.has_covariance else None
    seconds = 0.0
    from_truth = check_init(init) == "truth" and isinstance(estimator, ClassicalFilter)
    for lo in range(0, N, chunk):
        hi = min(N, lo + chunk)
        t0 = time.perf_counter()
        initial_mean = data.x[lo:hi, 0] if from_truth else None
        if on_steps is not None and table.has(estimator.method, family="classical"):
            est = run_stepwise(
                estimator, data.y[lo:hi], data.u[lo:hi], lambda: on_steps(hi - lo), initial_mean=initial_mean
            )
        elif from_truth:
            est = estimator.run(data.y[lo:hi], data.u[lo:hi], initial_mean=initial_mean)
        else:
            est = estimator.run(data.y[lo:hi], data.u[lo:hi])
        if on_steps is not None and not table.has(estimator.method, family="classical"):
            on_steps((hi - lo) * data.horizon)
        seconds += time.perf_counter() - t0
        x_hat[lo:hi] = est.x
        diverged[lo:hi] = est.diverged
        if nees_all is not None and est.cov is not None:
            e = M.errors(data.x[lo:hi], est.x, angle_states)
            with np.errstate(invalid="ignore", over="ignore"):
                nees_all[lo:hi] = M.nees(e, est.cov)
        if on_chunk:
            on_chunk(hi - lo)
    return x_hat, nees_all, diverged, seconds


def run_stepwise(
    estimator: Estimator,
    Y: np.ndarray,
    U: np.ndarray,
    on_step: Callable[[], None],
    initial_mean: np.ndarray | None = None,
) -> Estimates:
    """``estimator.run(Y, U)`` as ``reset`` and a loop of ``step``, calling ``on_step()`` after each.

    ``initial_mean`` (B, n), classical filters only, starts each stream there instead of at the
    prior mean (``reset(B, initial_mean)``).

    The estimator contract makes the two equal (tested for every method, and here for the
    filters); the loop lets a long chunk report its progress every time step.
    """
    Y, U = estimator.check_sequences(Y, U)
    B, T, _ = Y.shape
    dx = estimator.scenario.dx
    if initial_mean is None:
        estimator.reset(B)
    else:
        estimator.reset(B, initial_mean=initial_mean)
    Uprev = previous_controls(U)
    xs = np.empty((B, T, dx))
    covs = np.empty((B, T, dx, dx)) if estimator.has_covariance else None
    for k in range(T):
        xs[:, k] = estimator.step(Y[:, k], Uprev[:, k])
        if covs is not None:
            covs[:, k] = estimator.covariance
        on_step()
    return Estimates(xs, covs, estimator.diverged.copy())


# ---- the result cache --------------------------------------------------------------------------------


def served_context(
    scenario: Scenario,
    method: str,
    checkpoint: str | Path | Checkpoint | None,
    options: Mapping[str, Any] | None = None,
) -> int:
    """The bounded context a neural method is served with: the ``context`` option when given, else
    the one its card was validated with (``training.recipe.val_context``); 0 = continuous (the
    paper's way), and 0 for classical filters. Read from the card, so known for cached runs too."""
    if not table.has(method, trainable=True):
        return 0
    if options and options.get("context") not in (None, ""):
        return int(parse_value(options["context"], 0, "context"))
    from neural_estimator.serving.card import Checkpoint, default_checkpoint, read_card
    from neural_estimator.serving.load import validated_context

    if isinstance(checkpoint, Checkpoint):
        card = checkpoint.card
    else:
        try:
            _, card = read_card(checkpoint if checkpoint is not None else default_checkpoint(scenario.name, method))
        except Exception:  # a missing card fails at loading, with its own message
            return 0
    return int(validated_context(card).get("context", 0))


def evaluate(
    scenario: Scenario,
    methods: Sequence[str],
    *,
    trajectories: int = 8000,
    horizon: int | None = None,
    seed: int = 0,
    sets: int = 3,
    checkpoints: Mapping[str, Sequence[str | Path]] | None = None,
    options: Mapping[str, Mapping[str, Any]] | None = None,
    device: str = "cpu",
    memory_budget: int = DEFAULT_MEMORY_BUDGET,
    cache_dir: str | Path | None | bool = None,
    progress: bool = True,
    datasets: Sequence[Trajectories] | None = None,
    recompute: bool = False,
    on_result: Callable[[dict[str, MethodResult]], None] | None = None,
    init: str = "prior",
    warmup: int = M.EVALUATION_WARMUP,
    sealed: bool = False,
    model_scenario: Scenario | None = None,
) -> dict[str, MethodResult]:
    """Run ``methods`` on the evaluation sets of ``scenario`` and compute the paper's metrics.

    Args:
        scenario: the system (with any overrides, e.g. noise_scale).
        methods: method names (see :func:`neural_estimator.methods.table.names`).
        trajectories, horizon, seed, sets: the evaluation sets (paper: 8,000, scenario horizon, 3).
        checkpoints: {method: [checkpoint, ...]} for neural methods; each checkpoint is one instance.
            A neural method without an entry runs every instance the zoo ships (the shipped model
            and ``zoo/instances/i<K>/``; :mod:`neural_estimator.serving.instances`).
        options: {method: {hyperparameter: value}} for classical filters.
        device: torch device for neural methods.
        memory_budget: bytes per chunk (see :func:`chunk_size`).
        cache_dir: root of the dataset and result caches (None: :func:`default_cache_dir`;
            False: no cache, nothing read or written, no resume).
        progress: show a progress bar per run on stderr (trajectory-steps, with the run's ETA).
        datasets: use these instead of generating evaluation sets.
        recompute: compute every run even if a cached result exists (and overwrite it).
        on_result: called with the results so far after every run (the CLI writes partial
            outputs with it).
        init: how the classical filters start, ``"prior"``, ``"truth"`` or ``"observation"``
            (:data:`INIT_MODES`; ``"observation"`` is the prior where h determines nothing, see
            :func:`effective_init`, and each result's ``init`` says which start it got).
        warmup: leading timesteps not scored, for every method alike (default: the paper's 10,
            :data:`neural_estimator.metrics.EVALUATION_WARMUP`; 0 scores every step).
        sealed: allow a seed of the sealed family (:mod:`~neural_estimator.evaluation.families`);
            only the headline measurement passes it, every other caller gets a ValueError.
        model_scenario: the model-based methods' model (``--model-set``, :func:`_told`); None: ``scenario``.

    Returns:
        {method: MethodResult} in the order given.
    """
    methods = [check_evaluated_method(m) for m in methods]
    check_init(init)
    if datasets is None:
        check_unsealed(seed, sealed)
    data_sets = _data_sets(scenario, datasets, seed, trajectories, horizon, sets, cache_dir, warmup)
    cache_root = None if cache_dir is False else Path(cache_dir or default_cache_dir())
    digests = [dataset_digest(d) for d in data_sets] if cache_root is not None else []
    plan = [(m, k, c) for m in methods for k, c in enumerate(_instances(scenario, m, checkpoints))]
    results = {m: _empty_result(scenario, model_scenario, m, init) for m in methods}
    n_runs = len(plan) * len(data_sets)
    run_no = 0
    for m, k, ckpt in plan:
        told = _told(scenario, model_scenario, m)  # the model this method is built with
        if table.has(m, trainable=True):  # resolved once: its card read and its weights hashed here, then passed down
            from neural_estimator.serving.card import resolve_checkpoint

            ckpt = resolve_checkpoint(ckpt, scenario.name, m)
            results[m].instance_dirs.append(str(ckpt.directory))
        opts = dict((options or {}).get(m, {}))
        est = None  # built on the first run that is not cached (loading a model takes seconds)
        ckpt_hash = checkpoint_digest(scenario, m, ckpt) if cache_root is not None else None
        results[m].context = max(results[m].context, served_context(scenario, m, ckpt, opts))
        for j, data in enumerate(data_sets):
            run_no += 1
            r = results[m]
            label = f"{scenario.name} {m} set {j + 1}/{len(data_sets)}"
            path = None
            if cache_root is not None:
                key = run_key(told, m, opts, ckpt_hash, seed, device, digests[j], results[m].init, warmup)
                path = result_path(cache_root, scenario, m, key)
                if not recompute and _reused(path, r, j, k, progress, label):
                    if on_result:
                        on_result(results)
                    continue
            if est is None:
                est = _built(told, m, ckpt, device, seed, opts, results[m].init)
            chunk = chunk_size(scenario, m, data.horizon, data.n, memory_budget, opts)
            bar = _progress(data.n * data.horizon, progress, f"{label} (run {run_no}/{n_runs})")
            report, errs, secs = _scored_run(est, scenario, data, chunk, bar, results[m].init, warmup)
            r.add(report, errs, j, k)
            r.seconds += secs
            r.steps += data.n * data.horizon
            if path is not None:
                save_run(path, report, secs, data.n * data.horizon, errs)
            if on_result:
                on_result(results)
    return results


def _empty_result(scenario: Scenario, model_scenario: Scenario | None, method: str, init: str) -> MethodResult:
    """A method's result before its runs: how its filters start, the model set it is built with."""
    told = model_set_of(_told(scenario, model_scenario, method))
    return MethodResult(method, init=effective_init(scenario, method, init), model_set=told)


def _told(scenario: Scenario, model_scenario: Scenario | None, method: str) -> Scenario:
    """The scenario ``method`` is built with: the model scenario for a model-based method (the
    filters, the baselines, the hybrid; :func:`~neural_estimator.scenarios.model.model_scenario`),
    the data scenario for a data-trained network. The cache keys the model a run was built with."""
    if model_scenario is None or not table.has(method, needs_model=True):
        return scenario
    return model_scenario


def _data_sets(scenario: Scenario, datasets, seed: int, trajectories: int, horizon, sets: int, cache_dir, warmup):
    """The evaluation sets (``datasets`` as given, else generated or read from the cache), the
    warm-up checked against the horizon first."""
    T = scenario.horizon if horizon is None else int(horizon)
    if not 0 <= int(warmup) < T:
        raise ValueError(f"warmup must be in [0, {T}) for a horizon of {T} steps, got {warmup}")
    if datasets is not None:
        return list(datasets)
    return evaluation_sets(scenario, seed=seed, trajectories=trajectories, horizon=T, sets=sets, cache_dir=cache_dir)


def _reused(path: Path, r: MethodResult, j: int, k: int, progress: bool, label: str) -> bool:
    """The run cached at ``path`` added to ``r`` as set ``j`` of instance ``k`` (True), or False where
    none is cached there."""
    hit = load_run(path)
    if hit is None:
        return False
    report, secs, steps, errs = hit
    r.add(report, errs, j, k)
    r.seconds += secs
    r.steps += steps
    r.cached += 1
    _note(progress, f"{label}: cached result reused ({path.name})")
    return True


def _built(scenario: Scenario, m: str, ckpt, device: str, seed: int, opts: dict, init: str):
    """The estimator of method ``m`` (a baseline, a filter started as ``init`` asks, or a model)."""
    if is_baseline(m):
        return make_baseline(m, scenario, **opts)
    start = {"init": "observation"} if init == "observation" and "init" not in opts else {}
    return make_estimator(m, scenario, checkpoint=ckpt, device=device, seed=seed, **opts, **start)


def _scored_run(est, scenario: Scenario, data: Trajectories, chunk: int, bar, init: str, warmup: int) -> tuple:
    """One run of ``est`` over one evaluation set, scored: (report, per-trajectory errors, seconds)."""
    try:
        x_hat, nees_nt, diverged, secs = run_method(
            est, data, chunk, scenario.angle_states, on_steps=bar.update, init=init
        )
    finally:
        bar.close()
    report = M.compute_labelled_metrics(  # partial ground truth: the labelled steps only
        data.x,
        x_hat,
        scenario.angle_states,
        data.labelled,
        diverged=diverged,
        nees_values=nees_nt,
        warmup=warmup,
    )
    errs = M.trajectory_errors(data.x, x_hat, scenario.angle_states, report.outlier_idx, warmup, data.labelled)
    return report, errs, secs


def _instances(
    scenario: Scenario, method: str, checkpoints: Mapping[str, Sequence[str | Path]] | None
) -> list[str | Path | None]:
    """The checkpoints a method runs with, one per trained instance: those given, else for a neural
    method every instance the zoo ships (:func:`~neural_estimator.serving.instances.zoo_instances`;
    None when it ships none, which fails at loading with the command that trains one), else [None]."""
    given = list((checkpoints or {}).get(method) or [])
    if given or not table.has(method, trainable=True):
        return given or [None]
    from neural_estimator.serving.instances import zoo_instances

    return list(zoo_instances(scenario.name, method)) or [None]


def _note(enabled: bool, message: str) -> None:
    if enabled:
        print(message, file=sys.stderr)


class _NoBar:
    def update(self, n=1):
        pass

    def close(self):
        pass


def _progress(total: int, enabled: bool, desc: str):
    """A bar over one run's N T trajectory-steps; its ETA is the run's own (the rate of one method
    on one set, smoothed over the last updates, not an average over methods of different speed)."""
    if not enabled:
        return _NoBar()
    from tqdm import tqdm

    return tqdm(
        total=total,
        desc=desc,
        unit="traj-step",
        unit_scale=True,
        dynamic_ncols=True,
        leave=False,
        mininterval=0.5,
        disable=None,  # only on a terminal: no carriage-return progress in logs and pipes
    )
