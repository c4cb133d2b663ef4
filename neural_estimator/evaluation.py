"""The paper's evaluation protocol: methods x evaluation sets -> metrics -> median +- IQR table.

Paper, "Evaluation Protocol": "Each scenario uses three independent evaluation datasets with 8,000
trajectories each. The default evaluation horizon is 500." Results are "summarized over
independent datasets and random initializations using medians with interquartile ranges".

For each method, every evaluation set (and, for neural methods, every checkpoint given: the paper
trains 15 instances per architecture) is one *run*; metrics are computed per run on every timestep,
then summarised as median and IQR across runs.

Memory: the batch is cut into chunks so that no chunk holds more than ``memory_budget`` bytes of
outputs (the per-step covariances dominate: T dx^2 8 bytes per trajectory, 6.4 MB for Lorenz 96)
plus the method's working set (the PF's particles). NEES is computed chunk by chunk, so the full
(N, T, dx, dx) covariance array never exists.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from neural_estimator import metrics as M
from neural_estimator.data import Trajectories, evaluation_sets
from neural_estimator.estimators import Estimator, check_method, make_estimator
from neural_estimator.filters.base import ClassicalFilter
from neural_estimator.scenarios import Scenario

DEFAULT_MEMORY_BUDGET = 1 << 30  # bytes per chunk; peak stays well under 8 GiB

INIT_MODES = ("prior", "truth")
"""How the classical filters start in the offline protocol (``init``):

- ``"prior"`` (default; the live node's only choice, it never knows the truth): every filter
  starts from the scenario prior, mean m0 and covariance P0; the PF's particles are
  N(m0, init_std^2 I) (paper: x_0 std = 1.0).
- ``"truth"``: each trajectory's filters start at its true initial state x_0 (the mean only:
  covariance P0 and the PF's init_std spread unchanged), i.e. the PF's particles are
  N(x_0, init_std^2 I). This is the reading of the paper's "x_0 std = 1.0" under which a PF with a
  fixed unit spread can lock on in every scenario (see the README, "Fidelity to the paper").
  Neural methods read observations only; the option does not concern them.
"""


def check_init(init: str) -> str:
    """``init`` if it is one of :data:`INIT_MODES`, else a one-line ValueError naming the choices."""
    if init not in INIT_MODES:
        raise ValueError(f"init must be one of {', '.join(INIT_MODES)}; got {init!r}")
    return init


@dataclass
class MethodResult:
    """All runs of one method."""

    method: str
    reports: list[M.MetricReport] = field(default_factory=list)
    seconds: float = 0.0  # wall time spent estimating (excludes data generation and metrics)
    steps: int = 0  # trajectory-steps estimated

    @property
    def summary(self) -> dict[str, M.Stat]:
        return M.summarize(self.reports)

    @property
    def throughput(self) -> float:
        """Trajectory-steps per second."""
        return self.steps / self.seconds if self.seconds > 0 else float("nan")


def chunk_size(scenario: Scenario, method: str, horizon: int, n: int, budget: int = DEFAULT_MEMORY_BUDGET,
               options: Mapping[str, Any] | None = None) -> int:
    """Trajectories per chunk so one chunk's arrays stay within ``budget`` bytes.

    Per trajectory: outputs T (dx + dx^2) float64 plus the inputs, plus the method's members
    (EnKF: 50, PF: 1024 particles; each a few dx-vectors of temporaries).
    """
    dx, dy, du = scenario.dx, scenario.dy, scenario.du
    per = horizon * (dx + dx * dx + dy + du) * 8
    members = {"pf": (options or {}).get("n_particles", 1024), "enkf": (options or {}).get("n_members", 50)}.get(method, 2 * dx + 1)
    per += members * (dx + dy) * 8 * 6
    return int(max(1, min(n, budget // per)))


def run_method(
    estimator: Estimator,
    data: Trajectories,
    chunk: int,
    angle_states: Sequence[int],
    on_chunk: Callable[[int], None] | None = None,
    init: str = "prior",
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray, float]:
    """Estimate every trajectory of ``data`` chunk by chunk.

    ``init="truth"`` starts the classical filters of each trajectory at its true x_0 (see
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
        if from_truth:
            est = estimator.run(data.y[lo:hi], data.u[lo:hi], initial_mean=data.x[lo:hi, 0])
        else:
            est = estimator.run(data.y[lo:hi], data.u[lo:hi])
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
    init: str = "prior",
) -> dict[str, MethodResult]:
    """Run ``methods`` on the evaluation sets of ``scenario`` and compute the paper's metrics.

    Args:
        scenario: the system (with any overrides, e.g. noise_scale).
        methods: method names (see :data:`neural_estimator.estimators.METHODS`).
        trajectories, horizon, seed, sets: the evaluation sets (paper: 8,000, scenario horizon, 3).
        checkpoints: {method: [checkpoint, ...]} for neural methods; each checkpoint is one instance.
            A neural method without an entry uses the shipped default model.
        options: {method: {hyperparameter: value}} for classical filters.
        device: torch device for neural methods.
        memory_budget: bytes per chunk (see :func:`chunk_size`).
        cache_dir: dataset cache (False: no cache).
        progress: show a progress bar on stderr.
        datasets: use these instead of generating evaluation sets.
        init: how the classical filters start, ``"prior"`` or ``"truth"`` (:data:`INIT_MODES`).

    Returns:
        {method: MethodResult} in the order given.
    """
    methods = [check_method(m) for m in methods]
    check_init(init)
    T = scenario.horizon if horizon is None else int(horizon)
    data_sets = list(datasets) if datasets is not None else evaluation_sets(
        scenario, seed=seed, trajectories=trajectories, horizon=T, sets=sets, cache_dir=cache_dir)
    plan = []  # (method, estimator factory)
    for m in methods:
        ckpts = list((checkpoints or {}).get(m) or [None])
        for c in ckpts:
            plan.append((m, c))
    total = sum(d.n for d in data_sets) * len(plan)
    bar = _progress(total, progress, f"{scenario.name}")
    results = {m: MethodResult(m) for m in methods}
    try:
        for m, ckpt in plan:
            est = make_estimator(m, scenario, checkpoint=ckpt, device=device, seed=seed, **dict((options or {}).get(m, {})))
            for data in data_sets:
                bar.set_postfix_str(m)
                chunk = chunk_size(scenario, m, data.horizon, data.n, memory_budget, (options or {}).get(m))
                x_hat, nees_nt, diverged, secs = run_method(est, data, chunk, scenario.angle_states, bar.update, init=init)
                report = M.compute_metrics(data.x, x_hat, scenario.angle_states, diverged=diverged, nees_values=nees_nt)
                r = results[m]
                r.reports.append(report)
                r.seconds += secs
                r.steps += data.n * data.horizon
    finally:
        bar.close()
    return results


class _NoBar:
    def update(self, n=1):
        pass

    def set_postfix_str(self, s):
        pass

    def close(self):
        pass


def _progress(total: int, enabled: bool, desc: str):
    if not enabled:
        return _NoBar()
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="traj", dynamic_ncols=True, leave=False)


def results_table(results: Mapping[str, MethodResult], fmt: str = "markdown") -> str:
    """The paper's per-scenario table (median +- IQR over runs) for these results."""
    return M.format_table({m: r.summary for m, r in results.items()}, fmt=fmt)


def results_json(scenario: Scenario, results: Mapping[str, MethodResult], **info: Any) -> dict[str, Any]:
    """Everything measured, JSON-ready: scenario, settings, per-run reports, summaries, speed."""
    return M.to_json({
        "scenario": scenario.describe(),
        **info,
        "methods": {
            m: {
                "summary": r.summary,
                "runs": r.reports,
                "seconds": r.seconds,
                "trajectory_steps_per_second": r.throughput,
            }
            for m, r in results.items()
        },
    })
