"""One job of ``reproduce``: what it is, its cache key, and the code a Ray task runs for it.

Four kinds:

* ``evaluate``: one method on one evaluation set of one scenario (at one observation-noise scale);
  its result is the run's :class:`~neural_estimator.metrics.MetricReport`, stored by
  :mod:`neural_estimator.evaluation`'s result cache (the same cache ``neural-estimator evaluate``
  uses, so either command reuses the other's runs);
* ``runtime``: batch-1 iterations (time steps) per second of one method on one scenario, in one of
  two modes (:data:`RUNTIME_MODES`): ``step``, its real per-step path (``reset(1)`` then ``step``
  once per observation, as the ROS 2 estimator node does), timed after a few untimed warm-up
  steps; or ``sequence``, whole trajectories per call (``run`` on one (1, T) sequence: the
  networks' parallel form, the filters' loop over time), the paper's apparent method; stored as
  JSON under ``runtime/``;
* ``train``: one instance of one architecture on one scenario at one data-to-parameter ratio
  (:func:`neural_estimator.training.loop.train`), written under ``models/`` in a directory
  named by the recipe's hash; an ``evaluate`` job with ``train_job`` set evaluates that model;
* ``mismatch``: one model-mismatch sweep (one constant, or Q or R, of one scenario over a grid of
  multipliers; :func:`neural_estimator.evaluation.mismatch.mismatch`, the ``mismatch`` verb's code),
  stored as JSON under ``mismatch/`` (:mod:`.mismatch`, which runs it).

Jobs are plain data (they travel to Ray workers); :func:`run_job` has no Ray in it, so it is tested
and usable without a cluster.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

JOB_KINDS = ("evaluate", "runtime", "train", "mismatch")
# the experiments (Job.experiment: the report section a job feeds); a run does the ones it is given (--experiments)
EXPERIMENTS = ("accuracy", "noise", "data_ratio", "runtime", "mismatch")
RUNTIME_MODES = ("step", "sequence")  # runtime: one step per call (live) or one whole trajectory per call (run)
SEQUENCE_REPEATS = 5  # sequence mode: at least this many timed calls of run(); the median is reported
SEQUENCE_MIN_SECONDS = 1.0  # ... and more, up to SEQUENCE_MAX_REPEATS, until the calls took this long
SEQUENCE_MAX_REPEATS = 200
# part of runtime keys: bump when the timing procedure changes (2: CPU share recorded; 3: sequence
# mode times at least SEQUENCE_MIN_SECONDS of calls, a 10 ms call having been timed only 3 times)
RUNTIME_REVISION = 3
DONE_FILE = "reproduce-done.json"  # written in a train job's directory once its training finished


@dataclass(frozen=True)
class Job:
    kind: str
    scenario: str
    method: str
    seed: int = 0
    noise_scale: float = 1.0
    set_index: int = 0  # evaluate: which evaluation set
    trajectories: int = 0  # evaluate: per set
    horizon: int | None = None  # evaluate: steps (None: the scenario's)
    steps: int = 0  # runtime: timed steps
    warmup: int = 0  # runtime: untimed steps first
    device: str = "cpu"
    experiment: str = "accuracy"  # one of EXPERIMENTS: which part of the report it feeds
    data_ratio: float = 0.0  # train: the data-to-parameter ratio
    instance: int = 0  # train: the instance (its init_seed); evaluate: the instance of the model it evaluates
    train: tuple[tuple[str, Any], ...] = ()  # train: TrainConfig fields changed from the paper's recipe
    train_job: "Job | None" = None  # evaluate: evaluate the model this train job writes (None: the shipped one)
    init: str = "prior"  # evaluate: how the classical filters start, "prior", "truth" or "observation" (INIT_MODES)
    mode: str = "step"  # runtime: "step" (one step per call, as live) or "sequence" (run on a whole trajectory)
    parameter: str = ""  # mismatch: the constant the model gets wrong, or Q / R (method: "", the sweep's own)
    values: tuple[float, ...] = ()  # mismatch: the multipliers of its true value (1.0: the exact model)
    sets: int = 0  # mismatch: evaluation sets, ``trajectories`` each
    # a job whose cached runs this one reuses: it starts once that one finished (mismatch: the scenario's first
    # sweep, whose exact-model and network runs the other two read back); not part of any result's key
    after: "Job | None" = None

    @property
    def label(self) -> str:
        if self.kind == "mismatch":
            grid = ",".join(f"{v:g}" for v in self.values)
            return f"mismatch {self.scenario} {self.parameter} x{grid} ({self.sets} sets x {self.trajectories})"
        extra = f" noise x{self.noise_scale:g}" if self.noise_scale != 1.0 else ""
        what = {
            "evaluate": f"set {self.set_index}",
            "runtime": f"{self.device} batch 1" + (f" {self.mode}" if self.mode != "step" else ""),
            "train": f"ratio {self.data_ratio:g}:1 instance {self.instance}",
        }[self.kind]
        if self.train_job is not None:
            what += f" (model of ratio {self.train_job.data_ratio:g}:1 instance {self.train_job.instance})"
        return f"{self.kind} {self.scenario} {self.method}{extra} {what}"

    def to_json(self) -> dict[str, Any]:
        out = asdict(self)
        if out["init"] == "prior":  # the default is left out: keys and states from before the option stay valid
            del out["init"]
        if out["mode"] == "step":  # likewise
            del out["mode"]
        for name, default in (("parameter", ""), ("values", ()), ("sets", 0), ("after", None)):  # likewise
            if out[name] == default:
                del out[name]
        return out


def make_job_scenario(job: Job):
    from neural_estimator.scenarios import make_scenario

    return (
        make_scenario(job.scenario, noise_scale=job.noise_scale)
        if job.noise_scale != 1.0
        else make_scenario(job.scenario)
    )


def job_data(job: Job, cache_dir: Path):
    """The job's evaluation set (simulated once, then read from the dataset cache)."""
    from neural_estimator.data.protocol import dataset

    return dataset(make_job_scenario(job), "eval", job.set_index, job.trajectories, job.horizon, job.seed, cache_dir)


def train_config(job: Job, cache_dir: Path, **runtime: Any):
    """The job's recipe; ``runtime``: how to run it (resume, keep_resume), not part of the result."""
    from neural_estimator.training.recipe import TrainConfig

    return TrainConfig(
        data_ratio=job.data_ratio,
        init_seed=job.instance,
        data_seed=job.seed,
        device=job.device,
        cache_dir=str(cache_dir),
        **dict(job.train),
        **runtime,
    )


def train_dir(cache_dir: Path, job: Job) -> Path:
    """Where a train job's checkpoint lives: keyed by the recipe, the scenario, the architecture, the version."""
    from neural_estimator import __version__
    from neural_estimator.data.protocol import code_key

    scenario = make_job_scenario(job)
    key = json.dumps(
        {
            "version": __version__,
            "scenario": scenario.describe(),
            "arch": job.method,
            "recipe": train_config(job, cache_dir).recipe(),
            **code_key(scenario),
        },
        sort_keys=True,
        default=str,
    )
    digest = hashlib.sha256(key.encode()).hexdigest()[:20]
    return Path(cache_dir) / "models" / f"{job.scenario}-{job.method}-r{job.data_ratio:g}-i{job.instance}-{digest}"


def runtime_key(job: Job) -> str:
    """Everything that defines a timing: the job, the code's version and the machine that ran it."""
    from neural_estimator import __version__
    from neural_estimator.data.protocol import code_key
    from neural_estimator.evaluation import checkpoint_digest

    scenario = make_job_scenario(job)
    key = json.dumps(
        {
            "rev": RUNTIME_REVISION,
            "version": __version__,
            "job": job.to_json(),
            "scenario": scenario.describe(),
            "checkpoint": checkpoint_digest(scenario, job.method, None),
            "machine": [platform.node(), platform.machine(), os.cpu_count()],
            **code_key(scenario),
        },
        sort_keys=True,
        default=str,
    )
    return hashlib.sha256(key.encode()).hexdigest()[:20]


def runtime_path(cache_dir: Path, job: Job) -> Path:
    mode = "" if job.mode == "step" else f"-{job.mode}"
    return Path(cache_dir) / "runtime" / f"{job.scenario}-{job.method}-{job.device}{mode}-{runtime_key(job)}.json"


def run_job(
    job: Job, cache_dir: str | Path, threads: int = 1, plugins: tuple[str, ...] = (), *after: Any
) -> dict[str, Any]:
    """Do one job (or read its cached result). Returns ``{"job", "cached", "seconds", "result"}``:
    for ``evaluate`` the result is the run's report as JSON (:func:`neural_estimator.metrics.to_json`),
    for ``runtime`` ``{"it_per_s", "steps", "seconds"}``, for ``mismatch`` the sweep's JSON; ``node``:
    the Ray node that ran it (None outside Ray).

    ``threads`` bounds the job's own threads (classical filters' pool, torch) so that parallel jobs
    do not oversubscribe the cores they were given. ``after``: results of the jobs this one waits
    for (Ray passes them once they are done: an evaluation waits for its model's training).
    ``plugins``: scenario plugin files to load first (a Ray worker is a fresh process).
    """
    if job.kind not in JOB_KINDS:
        raise ValueError(f"unknown job kind {job.kind!r}; expected one of {JOB_KINDS}")
    if plugins:
        from neural_estimator.scenarios import load_plugins

        load_plugins(plugins)  # loading the same file twice is harmless (see register_scenario)
    import torch

    torch.set_num_threads(max(1, int(threads)))
    cache_dir = Path(cache_dir)
    t0 = time.perf_counter()
    if job.kind == "evaluate":
        result, cached = _evaluate(job, cache_dir, threads)
    elif job.kind == "train":
        result, cached = _train(job, cache_dir)
    elif job.kind == "mismatch":
        from neural_estimator.paper.reproduce.mismatch import run_mismatch

        result, cached = run_mismatch(job, cache_dir, threads)
    else:
        result, cached = _runtime(job, cache_dir, threads)
    seconds = time.perf_counter() - t0
    return {"job": job.to_json(), "cached": cached, "seconds": seconds, "result": result, "node": ray_node()}


def ray_node() -> str | None:
    """The id of the Ray node running this job (recorded with its result, so a run on a cluster
    shows where each job ran), or None outside a Ray task."""
    if "ray" not in sys.modules:
        return None
    import ray

    if not ray.is_initialized():
        return None
    try:
        return ray.get_runtime_context().get_node_id()
    except Exception:  # noqa: BLE001  an older or stubbed Ray: where a job ran is a report, never a failure
        return None


def _evaluate(job: Job, cache_dir: Path, threads: int) -> tuple[dict[str, Any], bool]:
    from neural_estimator import metrics as M
    from neural_estimator.methods import table
    from neural_estimator.evaluation import evaluate

    scenario = make_job_scenario(job)
    data = job_data(job, cache_dir)
    options = {job.method: {"threads": threads}} if table.has(job.method, family="classical") else None
    checkpoints = None
    if job.train_job is not None:
        ckpt = train_dir(cache_dir, job.train_job)
        if not (ckpt / DONE_FILE).is_file():
            raise RuntimeError(f"{ckpt}: the model of {job.train_job.label} is not trained")
        checkpoints = {job.method: [str(ckpt)]}
    elif table.has(job.method, trainable=True):
        # one job, one model: the zoo's instance ``job.instance``, not every instance the zoo ships
        # (evaluate's default), whose reports this job would drop and whose runs it would redo
        checkpoints = {job.method: [str(shipped_instance(scenario.name, job.method, job.instance))]}
    result = evaluate(
        scenario,
        [job.method],
        seed=job.seed,
        datasets=[data],
        options=options,
        device=job.device,
        cache_dir=cache_dir,
        progress=False,
        checkpoints=checkpoints,
        init=job.init,
    )
    res = result[job.method]
    # the context it was served with (read from its card, so known for cached runs) and the start the filters
    # really got (the prior where --init observation cannot apply): the report marks both
    return {**M.to_json(res.reports[0]), "context": res.context, "start": res.init}, res.cached == 1


def _runtime(job: Job, cache_dir: Path, threads: int) -> tuple[dict[str, Any], bool]:
    from neural_estimator.methods import table
    from neural_estimator.methods.registry import make_estimator, previous_controls

    path = runtime_path(cache_dir, job)
    if path.is_file():
        try:
            return json.loads(path.read_text()), True
        except (OSError, ValueError):
            pass  # a damaged entry is measured again
    scenario = make_job_scenario(job)
    from neural_estimator.data.protocol import dataset

    data = dataset(scenario, "eval", 0, 1, job.warmup + job.steps, job.seed, cache_dir)
    opts = {"threads": threads} if table.has(job.method, family="classical") else {}
    est = make_estimator(job.method, scenario, device=job.device, seed=job.seed, **opts)
    if job.mode == "sequence":
        seconds, cpu_share = _time_sequence(est, data, job)
    elif job.mode == "step":
        Uprev = previous_controls(data.u)
        est.reset(1)
        for k in range(job.warmup):
            est.step(data.y[:, k], Uprev[:, k])
        t0, c0 = time.perf_counter(), time.process_time()
        for k in range(job.warmup, job.warmup + job.steps):
            est.step(data.y[:, k], Uprev[:, k])
        seconds = time.perf_counter() - t0
        cpu_share = _cpu_share(time.process_time() - c0, seconds)
    else:
        raise ValueError(f"unknown runtime mode {job.mode!r}; expected one of {RUNTIME_MODES}")
    result = {
        "it_per_s": job.steps / seconds if seconds > 0 else float("inf"),
        "steps": job.steps,
        "seconds": seconds,
        "threads": threads,
        "mode": job.mode,
        # the process's CPU time over the wall time of the timed part: about 1 (one thread) when the
        # job had its core to itself, lower when other work took the CPU and the figure understates
        "cpu_share": cpu_share,
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(result))
    tmp.replace(path)
    return result, False


def _time_sequence(est, data, job: Job) -> tuple[float, float]:
    """Seconds of one ``run`` over the (1, steps) sequence after the warm-up steps (the median of at
    least :data:`SEQUENCE_REPEATS` calls, more until they took :data:`SEQUENCE_MIN_SECONDS`, at most
    :data:`SEQUENCE_MAX_REPEATS`; after one untimed call on the warm-up steps), and the CPU share of
    the timed calls (the process's CPU time over their wall time)."""
    Y, U = data.y[:, job.warmup :], data.u[:, job.warmup :]
    if job.warmup:
        est.run(data.y[:, : job.warmup], data.u[:, : job.warmup])  # first-call costs (allocation, compilation)
    times = []
    c0 = time.process_time()
    while len(times) < SEQUENCE_REPEATS or (sum(times) < SEQUENCE_MIN_SECONDS and len(times) < SEQUENCE_MAX_REPEATS):
        t0 = time.perf_counter()
        est.run(Y, U)
        times.append(time.perf_counter() - t0)
    return sorted(times)[len(times) // 2], _cpu_share(time.process_time() - c0, sum(times))


def _cpu_share(cpu_seconds: float, wall_seconds: float) -> float:
    """The process's CPU time over the wall time of a timed part (1.0 for a part too short to time)."""
    return cpu_seconds / wall_seconds if wall_seconds > 0 else 1.0


def _train(job: Job, cache_dir: Path) -> tuple[dict[str, Any], bool]:
    from neural_estimator.training.loop import train

    out = train_dir(cache_dir, job)
    done = out / DONE_FILE
    if done.is_file():
        try:
            return json.loads(done.read_text()), True
        except (OSError, ValueError):
            pass
    t0 = time.perf_counter()
    cfg = train_config(job, cache_dir, resume=True, keep_resume=False)  # an interrupted training continues
    train(make_job_scenario(job), job.method, out, cfg, progress=False)
    result = {"checkpoint": str(out), "seconds": time.perf_counter() - t0}
    tmp = done.with_suffix(".tmp")
    tmp.write_text(json.dumps(result))
    tmp.replace(done)
    return result, False


def shipped_instance(scenario_name: str, method: str, instance: int) -> Path:
    """The checkpoint directory of the zoo's instance ``instance`` of (scenario, method): 0 the shipped
    model, K >= 1 ``zoo/instances/i<K>/``. A missing one is a one-line error naming what the zoo has."""
    from neural_estimator.serving.instances import instance_checkpoint, instance_number, zoo_instances

    if instance == 0:  # the shipped model; a pair the zoo lacks fails at loading, with the command that trains it
        return instance_checkpoint(scenario_name, method, 0)
    found = {instance_number(path): path for path in zoo_instances(scenario_name, method)}
    if instance not in found:
        raise FileNotFoundError(
            f"the zoo ships no instance {instance} of {scenario_name}-{method} (it has {sorted(found) or 'none'})"
        )
    return found[instance]
