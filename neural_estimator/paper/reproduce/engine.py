"""Run jobs as Ray tasks: local by default, a cluster with ``address``; one progress bar over all.

Each job is one Ray task (:func:`neural_estimator.paper.reproduce.jobs.run_job`). A job that raises is
recorded as failed with its one-line error, and the others go on. Results are cached on disk by
the jobs themselves (keys in :mod:`.jobs`), so a second run, or one after an interruption, reads
the finished jobs back (``cached``) and computes only the missing ones. On a cluster the cache
directory must be on storage every node sees (the same path).

Runtime jobs ask Ray for every CPU of the local run (``num_cpus``), so they are timed while no
other job of this run shares the machine.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from neural_estimator.paper.reproduce.jobs import Job, run_job


@dataclass
class Outcome:
    """Every job's result or error, in the order submitted."""

    results: dict[int, dict[str, Any]] = field(default_factory=dict)  # job index -> run_job's dict
    failed: dict[int, str] = field(default_factory=dict)  # job index -> "ExcType: message"

    @property
    def computed(self) -> int:
        return sum(not r["cached"] for r in self.results.values())

    @property
    def cached(self) -> int:
        return sum(bool(r["cached"]) for r in self.results.values())


def default_num_cpus() -> int:
    """Local Ray CPUs: the usable cores, at most 4 (a laptop stays usable)."""
    try:
        n = len(os.sched_getaffinity(0))
    except AttributeError:
        n = os.cpu_count() or 1
    return max(1, min(4, n))


def init_ray(address: str | None, num_cpus: int | None):
    """``ray.init`` local (``num_cpus`` CPUs, small object store, no dashboard) or joining ``address``."""
    import ray

    if ray.is_initialized():
        return ray
    # the package must be importable by the workers as it is by the driver (editable installs, tests)
    root = str(Path(__file__).resolve().parents[3])
    env = {
        "env_vars": {
            "PYTHONPATH": os.pathsep.join([root, os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep),
            "OMP_NUM_THREADS": "1",
            "MKL_NUM_THREADS": "1",
        }
    }
    if address:
        ray.init(address=address, runtime_env=env, log_to_driver=False)
    else:
        ray.init(
            num_cpus=num_cpus or default_num_cpus(),
            include_dashboard=False,
            log_to_driver=False,
            object_store_memory=256 << 20,
            runtime_env=env,
        )
    return ray


def run_jobs(
    jobs: Sequence[Job],
    cache_dir: str | Path,
    *,
    address: str | None = None,
    num_cpus: int | None = None,
    progress: bool = True,
    shutdown: bool = True,
    plugins: Sequence[str] = (),
) -> Outcome:
    """Run every job on Ray; returns their results and failures (never raises for a failed job).

    ``plugins``: scenario plugin files each task loads before its job (the same paths on every node).
    Train jobs are submitted first, so that every evaluation of a trained model finds the training
    it waits for, whatever the order of ``jobs``; a job with ``after`` set waits for that job too
    (submitted before it: ``plan_jobs`` orders them so).

    Joins the Ray instance already initialised in this process if there is one (and leaves it
    running); otherwise starts one (or joins ``address``) and shuts it down at the end when
    ``shutdown``.
    """
    import ray as _ray

    owned = not _ray.is_initialized()
    ray = init_ray(address, num_cpus)
    total_cpus = int(ray.cluster_resources().get("CPU", 1))
    local_cpus = (num_cpus or default_num_cpus()) if not address else 1
    task = ray.remote(max_retries=0)(run_job)
    refs = {}
    submitted = {}  # job -> its ref: an evaluation of a trained model waits for its training, a job for its `after`
    order = sorted(range(len(jobs)), key=lambda i: jobs[i].kind != "train")  # stable: trainings first
    for i in order:
        job = jobs[i]
        cpus = min(local_cpus, total_cpus) if job.kind == "runtime" else 1
        after = [submitted[d] for d in (job.train_job, job.after) if d is not None and d in submitted]
        ref = task.options(num_cpus=cpus).remote(job, str(cache_dir), 1, tuple(plugins), *after)
        refs[ref] = i
        submitted[job] = ref
    outcome = Outcome()
    bar = _bar(len(refs), progress)
    pending = list(refs)
    try:
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            for ref in done:
                i = refs[ref]
                try:
                    outcome.results[i] = ray.get(ref)
                except Exception as exc:  # a failed job is reported, the others go on
                    cause = getattr(exc, "cause", None) or exc
                    lines = str(cause).strip().splitlines() or [""]
                    outcome.failed[i] = f"{type(cause).__name__}: {lines[0]}"
                    bar.write(f"failed: {jobs[i].label}: {outcome.failed[i]}")
                bar.update(1)
                bar.set_postfix(failed=len(outcome.failed), cached=outcome.cached, refresh=False)
    finally:
        bar.close()
        if shutdown and owned:
            ray.shutdown()
    return outcome


class _NoBar:
    def update(self, n=1):
        pass

    def set_postfix(self, **kw):
        pass

    def write(self, s):
        print(s, file=sys.stderr)

    def close(self):
        pass


def _bar(total: int, enabled: bool):
    if not enabled:
        return _NoBar()
    from tqdm import tqdm

    # disable=None: only on a terminal (no carriage-return progress in logs and pipes)
    return tqdm(total=total, desc="reproduce", unit="job", dynamic_ncols=True, mininterval=0.5, disable=None)
