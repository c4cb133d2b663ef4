"""The paper's experiments at one scale, and the model-mismatch experiment beyond it, expanded into
independent jobs."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

from neural_estimator.evaluation.mismatch import EXPERIMENT
from neural_estimator.paper.reproduce.jobs import EXPERIMENTS, RUNTIME_MODES, Job
from neural_estimator.paper.reproduce.mismatch import sweep_values
from neural_estimator.paper.reproduce.scales import Scale


def noise_reuses_accuracy(scale: Scale) -> bool:
    """The nominal point of the noise sweep is the accuracy experiment when their sizes agree."""
    return (scale.noise_trajectories, scale.noise_sets) == (scale.trajectories, scale.sets)


def train_job(scale: Scale, scenario: str, method: str, ratio: float, instance: int) -> Job:
    """The training of one instance of ``method`` on ``scenario`` at ``ratio``:1 with the scale's recipe."""
    overrides = dict(scale.train_overrides)
    n = scale.train_trajectories(ratio)
    if n is not None:
        overrides["trajectories"] = n
    return Job(
        "train",
        scenario,
        method,
        seed=scale.seed,
        data_ratio=float(ratio),
        instance=instance,
        train=tuple(sorted(overrides.items())),
        experiment="data_ratio",
    )


MAIN_RATIO = 20.0  # the paper's main tables: models trained at about 20:1


def plan_jobs(
    scale: Scale,
    scenarios: Sequence[str],
    methods: Sequence[str],
    gpu: bool = False,
    init: str = "prior",
    experiments: Sequence[str] = EXPERIMENTS,
) -> list[Job]:
    """The jobs of ``experiments`` (default all of :data:`~.jobs.EXPERIMENTS`): accuracy (every
    method on every evaluation set), the noise sweep (same, per noise scale; models trained at the
    nominal noise; its nominal point is the accuracy run's where the sizes agree and accuracy runs too),
    data efficiency (train every neural architecture at every ratio, then evaluate each trained
    instance on every set), runtime (batch-1 throughput on CPU, and on GPU for the neural methods
    when ``gpu``, in both modes: step by step and whole sequences per call), model mismatch (one job
    per declared sweep of each scenario, :mod:`.mismatch`; its methods are its own, not ``methods``).

    With ``scale.main_from_training`` (the paper scale) the accuracy and noise experiments evaluate
    each neural architecture's ``train_instances`` models trained at 20:1 (the same trainings as the
    data-efficiency experiment's 20:1 point) instead of the shipped model; each training is one job.

    ``init`` (``"prior"``, ``"truth"`` or ``"observation"``): how the classical filters of the accuracy and noise
    evaluations start (:func:`neural_estimator.evaluation.run_method`); neural methods ignore it.
    """
    from neural_estimator.methods import table

    run = set(experiments)
    neural = table.names(trainable=True)
    jobs = _accuracy_jobs(scale, scenarios, methods, init, neural) if "accuracy" in run else []
    if "noise" in run:
        jobs += _noise_jobs(scale, scenarios, methods, init, neural, reuse_accuracy="accuracy" in run)
    trainings: dict[Job, None] = {}  # every train job once, in order
    for job in jobs:
        if job.train_job is not None:
            trainings.setdefault(job.train_job)
    if "data_ratio" in run:
        jobs += _ratio_jobs(scale, scenarios, [m for m in methods if table.has(m, trainable=True)], trainings)
    jobs = list(trainings) + jobs  # trainings first (the engine submits them first anyway)
    jobs += mismatch_jobs(scale, scenarios) if "mismatch" in run else []
    return jobs + (_runtime_jobs(scale, scenarios, methods, gpu, neural) if "runtime" in run else [])


def _models(scale: Scale, s: str, m: str, neural_methods) -> list[tuple[Job | None, int]]:
    """What an accuracy or noise evaluation of ``m`` evaluates, as (train job, instance) pairs: the
    scale's trainings at 20:1 (``main_from_training``), else every instance of the zoo's model (train
    job None, the instance number K of ``zoo/instances/i<K>/``; 0 the shipped model), as the paper
    takes the median over instances. A filter, or a pair the zoo lacks, is one evaluation (None, 0)."""
    if m in neural_methods and scale.main_from_training:
        return [(train_job(scale, s, m, MAIN_RATIO, i), i) for i in range(scale.train_instances)]
    if m in neural_methods:
        from neural_estimator.serving.instances import instance_number, zoo_instances

        shipped = [instance_number(path) for path in zoo_instances(s, m)]
        return [(None, k) for k in shipped] or [(None, 0)]
    return [(None, 0)]


def _accuracy_jobs(scale: Scale, scenarios: Sequence[str], methods: Sequence[str], init: str, neural_methods):
    """Every method on every evaluation set of every scenario."""
    jobs: list[Job] = []
    for s in scenarios:
        for m in methods:
            for tj, instance in _models(scale, s, m, neural_methods):
                for j in range(scale.sets):
                    jobs.append(
                        Job(
                            "evaluate",
                            s,
                            m,
                            seed=scale.seed,
                            set_index=j,
                            trajectories=scale.trajectories,
                            horizon=scale.horizon,
                            experiment="accuracy",
                            train_job=tj,
                            init=init,
                            instance=instance,
                        )
                    )
    return jobs


def _noise_jobs(
    scale: Scale, scenarios: Sequence[str], methods: Sequence[str], init: str, neural_methods, reuse_accuracy=True
):
    """The accuracy evaluation per noise scale (the nominal one left out where it is the accuracy run,
    when ``reuse_accuracy``: the accuracy experiment runs too)."""
    jobs: list[Job] = []
    for s in scenarios:
        for m in methods:
            for ns in scale.noise_scales:
                if ns == 1.0 and reuse_accuracy and noise_reuses_accuracy(scale):
                    continue
                for tj, instance in _models(scale, s, m, neural_methods):
                    for j in range(scale.noise_sets):
                        jobs.append(
                            Job(
                                "evaluate",
                                s,
                                m,
                                seed=scale.seed,
                                noise_scale=float(ns),
                                set_index=j,
                                trajectories=scale.noise_trajectories,
                                horizon=scale.horizon,
                                experiment="noise",
                                train_job=tj,
                                init=init,
                                instance=instance,
                            )
                        )
    return jobs


def _ratio_jobs(scale: Scale, scenarios: Sequence[str], neural: Sequence[str], trainings: dict) -> list[Job]:
    """Data efficiency: each neural method trained at every ratio (its train jobs added to
    ``trainings``), each instance evaluated on every set."""
    jobs: list[Job] = []
    for s in scenarios:
        for m in neural:
            for ratio in scale.data_ratios:
                for i in range(scale.train_instances):
                    tj = train_job(scale, s, m, ratio, i)
                    trainings.setdefault(tj)
                    for j in range(scale.sets):
                        jobs.append(
                            Job(
                                "evaluate",
                                s,
                                m,
                                seed=scale.seed,
                                set_index=j,
                                trajectories=scale.ratio_trajectories or scale.trajectories,
                                horizon=scale.horizon,
                                experiment="data_ratio",
                                data_ratio=float(ratio),
                                instance=i,
                                train_job=tj,
                            )
                        )
    return jobs


def mismatch_jobs(scale: Scale, scenarios: Sequence[str]) -> list[Job]:
    """One job per declared sweep of ``scenarios``, parameter-major (every scenario's first sweep,
    then every second one, ...). The sweeps of one scenario share its exact-model and network runs
    through the result cache: its later sweeps wait for its first (``after``), which computes them,
    and read them back instead of computing the same runs at the same time."""
    per_scenario = [
        _chain(
            [
                Job(
                    "mismatch",
                    s,
                    "",
                    seed=scale.seed,
                    trajectories=scale.mismatch_trajectories,
                    horizon=scale.horizon,
                    experiment="mismatch",
                    parameter=p,
                    values=sweep_values(scale, p),
                    sets=scale.mismatch_sets,
                )
                for p in EXPERIMENT[s]
            ]
        )
        for s in scenarios
        if s in EXPERIMENT
    ]
    depth = max((len(sweeps) for sweeps in per_scenario), default=0)
    return [sweeps[i] for i in range(depth) for sweeps in per_scenario if i < len(sweeps)]


def _chain(sweeps: list[Job]) -> list[Job]:
    """The first sweep, then the others each waiting for it."""
    return sweeps[:1] + [replace(j, after=sweeps[0]) for j in sweeps[1:]]


def _runtime_jobs(scale: Scale, scenarios: Sequence[str], methods: Sequence[str], gpu: bool, neural_methods):
    """Batch-1 throughput in every mode on CPU, and on GPU for the neural methods when ``gpu``."""
    jobs: list[Job] = []
    devices = ["cpu"] + (["cuda"] if gpu else [])
    for device in devices:
        for s in scenarios:
            for m in methods:
                if device == "cuda" and m not in neural_methods:
                    continue  # our classical filters are numpy: CPU only
                for mode in RUNTIME_MODES:
                    jobs.append(
                        Job(
                            "runtime",
                            s,
                            m,
                            seed=scale.seed,
                            steps=scale.runtime_steps,
                            warmup=scale.runtime_warmup,
                            device=device,
                            experiment="runtime",
                            mode=mode,
                        )
                    )
    return jobs
