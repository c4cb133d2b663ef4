"""The paper's experiments at one scale, expanded into independent jobs."""

from __future__ import annotations

from collections.abc import Sequence

from neural_estimator.paper.reproduce.jobs import RUNTIME_MODES, Job
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
    scale: Scale, scenarios: Sequence[str], methods: Sequence[str], gpu: bool = False, init: str = "prior"
) -> list[Job]:
    """Accuracy (every method on every evaluation set), the noise sweep (same, per noise scale;
    models trained at the nominal noise), data efficiency (train every neural architecture at every
    ratio, then evaluate each trained instance on every set), runtime (batch-1 throughput on CPU, and on GPU for
    the neural methods when ``gpu``, in both modes: step by step and whole sequences per call).

    With ``scale.main_from_training`` (the paper scale) the accuracy and noise experiments evaluate
    each neural architecture's ``train_instances`` models trained at 20:1 (the same trainings as the
    data-efficiency experiment's 20:1 point) instead of the shipped model; each training is one job.

    ``init`` (``"prior"``, ``"truth"`` or ``"observation"``): how the classical filters of the accuracy and noise
    evaluations start (:func:`neural_estimator.evaluation.run_method`); neural methods ignore it.
    """
    from neural_estimator.methods import table

    jobs = _accuracy_jobs(scale, scenarios, methods, init, table.names(trainable=True))
    jobs += _noise_jobs(scale, scenarios, methods, init, table.names(trainable=True))
    trainings: dict[Job, None] = {}  # every train job once, in order
    for job in jobs:
        if job.train_job is not None:
            trainings.setdefault(job.train_job)
    jobs += _ratio_jobs(scale, scenarios, [m for m in methods if table.has(m, trainable=True)], trainings)
    jobs = list(trainings) + jobs  # trainings first (the engine submits them first anyway)
    return jobs + _runtime_jobs(scale, scenarios, methods, gpu, table.names(trainable=True))


def _models(scale: Scale, s: str, m: str, neural_methods) -> list[Job | None]:
    """What an accuracy or noise evaluation of ``m`` evaluates: the shipped model (None) or trainings."""
    if m in neural_methods and scale.main_from_training:
        return [train_job(scale, s, m, MAIN_RATIO, i) for i in range(scale.train_instances)]
    return [None]


def _accuracy_jobs(scale: Scale, scenarios: Sequence[str], methods: Sequence[str], init: str, neural_methods):
    """Every method on every evaluation set of every scenario."""
    jobs: list[Job] = []
    for s in scenarios:
        for m in methods:
            for tj in _models(scale, s, m, neural_methods):
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
                            instance=tj.instance if tj else 0,
                        )
                    )
    return jobs


def _noise_jobs(scale: Scale, scenarios: Sequence[str], methods: Sequence[str], init: str, neural_methods):
    """The accuracy evaluation per noise scale (the nominal one left out where it is the accuracy run)."""
    jobs: list[Job] = []
    for s in scenarios:
        for m in methods:
            for ns in scale.noise_scales:
                if ns == 1.0 and noise_reuses_accuracy(scale):
                    continue
                for tj in _models(scale, s, m, neural_methods):
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
                                instance=tj.instance if tj else 0,
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
