"""The model-mismatch experiment of ``reproduce`` (beyond the paper): its jobs, their cache, its report section.

The paper gives every filter the exact model. This experiment tells the model-based methods one
constant of the scenario wrong, a multiplier v of its true value (or the process / observation
noise covariance scaled by v: ``Q``, ``R``), and finds the relative error e = v - 1 beyond which a
network trained on the data, or the hybrid, overtakes the best filter: the crossover, with its
interval (:mod:`neural_estimator.evaluation.mismatch`, whose docstring has the construction).

**Jobs** (:func:`~neural_estimator.paper.reproduce.plan.mismatch_jobs`). One per sweep that
:data:`~neural_estimator.evaluation.mismatch.EXPERIMENT` declares (one physical constant per
scenario, then ``Q`` and ``R``), for each scenario of the run that has one (a plugin scenario
declares none). A job is the ``mismatch`` verb's code,
:func:`~neural_estimator.evaluation.mismatch.mismatch` with its default methods (EKF, UKF, the
best shipped network on the sets, the shipped hybrid; ``--methods`` does not change them), on the
scale's ``mismatch_sets`` x ``mismatch_trajectories`` at the scale's horizon, over
``mismatch_values`` (a constant) or ``mismatch_noise_values`` (``Q``, ``R``).

**Cache.** A finished sweep is stored as JSON under ``mismatch/`` in the result cache, keyed by
the job (scenario, parameter, grid, sizes, seed; not the job it waits for), the scenario's
constants, the methods compared with the content digest of every checkpoint they load (every
instance the zoo ships), the package version, the revisions of the simulation and of run results,
the unscored warm-up and a plugin's source. Each run inside a sweep also goes through the
evaluation result cache, so a sweep whose grid changed recomputes only its new values, and the
sweeps of one scenario share its exact-model and network runs (the later ones wait for the first).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from neural_estimator.evaluation import mismatch as MM
from neural_estimator.paper.reproduce.scales import Scale

# A job here is a :class:`~neural_estimator.paper.reproduce.jobs.Job` of kind "mismatch", read by its
# fields only: .jobs imports this module to run one, so this one does not import .jobs (no cycle).


def sweep_values(scale: Scale, parameter: str) -> tuple[float, ...]:
    """The scale's grid of multipliers for ``parameter``: the noise grid for ``Q`` and ``R``."""
    grid = scale.mismatch_noise_values if parameter in MM.NOISE_SCALES else scale.mismatch_values
    return tuple(MM.check_values(grid))


def _checkpoints(scenario, methods: Sequence[str]) -> dict[str, list[str | None]]:
    """{trainable method: content digest of each instance the zoo ships} (what evaluate loads)."""
    from neural_estimator.evaluation import checkpoint_digest
    from neural_estimator.methods import table
    from neural_estimator.serving.instances import zoo_instances

    return {
        m: [checkpoint_digest(scenario, m, p) for p in zoo_instances(scenario.name, m)]
        or [checkpoint_digest(scenario, m, None)]
        for m in methods
        if table.has(m, trainable=True)
    }


def _scenario(job):
    from neural_estimator.scenarios import make_scenario

    return make_scenario(job.scenario)  # the true constants: the sweep tells its methods the wrong ones


def mismatch_key(job) -> str:
    """Hex digest of everything that defines a sweep's result (module docstring, *Cache*)."""
    from neural_estimator import __version__
    from neural_estimator import metrics as M
    from neural_estimator.data.protocol import SIMULATION_REVISION, code_key
    from neural_estimator.evaluation import RESULTS_REVISION

    scenario = _scenario(job)
    methods = MM.default_methods(scenario)
    key = json.dumps(
        {
            "schema": MM.MISMATCH_SCHEMA,
            "rev": RESULTS_REVISION,
            "sim": SIMULATION_REVISION,
            "version": __version__,
            "job": {k: v for k, v in job.to_json().items() if k != "after"},  # whom it waits for: no result
            "scenario": scenario.describe(),
            "methods": methods,
            "checkpoints": _checkpoints(scenario, methods),
            "warmup": M.EVALUATION_WARMUP,
            **code_key(scenario),
        },
        sort_keys=True,
        default=str,
    )
    return hashlib.sha256(key.encode()).hexdigest()[:20]


def mismatch_path(cache_dir: str | Path, job) -> Path:
    return Path(cache_dir) / "mismatch" / f"{job.scenario}-{job.parameter}-{mismatch_key(job)}.json"


def run_mismatch(job, cache_dir: Path, threads: int = 1) -> tuple[dict[str, Any], bool]:
    """The sweep's JSON (:func:`~neural_estimator.evaluation.mismatch.mismatch`), read back when
    cached; ``threads`` bounds the filters' threads (a speed option: no result changes with it)."""
    from neural_estimator.core.atomic import write_text_atomically
    from neural_estimator.methods import table

    path = mismatch_path(cache_dir, job)
    if path.is_file():
        try:
            return json.loads(path.read_text()), True
        except (OSError, ValueError):
            pass  # a damaged entry is computed again
    scenario = _scenario(job)
    classical = [m for m in MM.default_methods(scenario) if table.has(m, family="classical")]
    result = MM.mismatch(
        scenario,
        job.parameter,
        job.values,
        trajectories=job.trajectories,
        sets=job.sets,
        horizon=job.horizon,
        seed=job.seed,
        cache_dir=cache_dir,
        options={m: {"threads": threads} for m in classical},
    )
    write_text_atomically(path, json.dumps(result, allow_nan=False))
    return result, False


def mismatch_section(scale: Scale, scenarios: Sequence[str], jobs: Sequence, outcome, out: Path) -> list[str]:
    """The report's section: per scenario the exact model's row, the crossover table and each
    sweep's figure, written from the finished mismatch jobs of ``outcome`` (an
    :class:`~neural_estimator.paper.reproduce.engine.Outcome`); every sweep's JSON, CSV and PNG
    go to ``out``/mismatch/ under the names of docs/results/mismatch."""
    results = {
        (job.scenario, job.parameter): outcome.results[i]["result"]
        for i, job in enumerate(jobs)
        if job.kind == "mismatch" and i in outcome.results
    }
    grid = ", ".join(f"{v:g}" for v in scale.mismatch_values)
    noise = ", ".join(f"{v:g}" for v in scale.mismatch_noise_values)
    L = [
        "## Model mismatch (beyond the paper)",
        "",
        "The paper gives every filter the exact model. Here the model-based methods (EKF, UKF and the hybrid "
        "`kalmannet`, trained with the exact model) are told one constant wrong, v × its true value (v = "
        f"{grid}), or the process / observation noise covariance scaled by v (`Q`, `R`; v = {noise}), on "
        f"{scale.mismatch_sets} sets × {scale.mismatch_trajectories} trajectories per sweep simulated with the "
        "true constants; the networks do not see the model (their RMSE is the same at every v). The relative "
        "error of the model is e = v − 1. The network is the best shipped one on these sets, whatever "
        "`--methods`. A crossover is the smallest |e| at which the challenger's paired RMSE ratio to the best "
        "filter there falls below 1, interpolated between grid points, with the 95 % interval the ratio's "
        "interval gives: `0` it is ahead at the exact model already, `> X` not within the grid (X the largest "
        "error tried). Each sweep's JSON, CSV (every method's RMSE per component at every v) and figure are in "
        "`mismatch/`, named as in docs/results/mismatch.",
        "",
    ]
    skipped = [s for s in scenarios if s not in MM.EXPERIMENT]
    if skipped:
        where = "`EXPERIMENT` in neural_estimator/evaluation/mismatch.py"
        L += [f"No sweep is declared for {', '.join(skipped)} ({where}).", ""]
    for s in scenarios:
        if s not in MM.EXPERIMENT:
            continue
        sweeps = [results[(s, p)] for p in MM.EXPERIMENT[s] if (s, p) in results]
        L += [f"### {s}", ""]
        if not sweeps:
            L += ["No sweep of this scenario finished (see the failed jobs).", ""]
            continue
        L += ["At the exact model:", ""] + MM.exact_table(sweeps, scenario_column=False) + [""]
        L += MM.crossover_table(sweeps, scenario_column=False) + [""]
        for r in sweeps:
            stem = MM.write_result(r, out / "mismatch")
            L += [f"![{s}: {r['parameter']} mismatch](mismatch/{stem.name}.png)", ""]
    return L
