"""The paper's experiments at one scale, expanded into independent jobs."""

from __future__ import annotations

from collections.abc import Sequence

from neural_estimator.reproduce.jobs import Job
from neural_estimator.reproduce.scales import Scale


def noise_reuses_accuracy(scale: Scale) -> bool:
    """The nominal point of the noise sweep is the accuracy experiment when their sizes agree."""
    return (scale.noise_trajectories, scale.noise_sets) == (scale.trajectories, scale.sets)


def plan_jobs(scale: Scale, scenarios: Sequence[str], methods: Sequence[str], gpu: bool = False) -> list[Job]:
    """Accuracy (every method on every evaluation set), the noise sweep (same, per noise scale;
    models trained at the nominal noise), data efficiency (train every neural architecture at every
    ratio, then evaluate each trained instance on every set), runtime (batch-1 step throughput on CPU, and on GPU for
    the neural methods when ``gpu``)."""
    from neural_estimator.estimators import NEURAL_METHODS

    jobs: list[Job] = []
    for s in scenarios:
        for m in methods:
            for j in range(scale.sets):
                jobs.append(Job("evaluate", s, m, seed=scale.seed, set_index=j, trajectories=scale.trajectories,
                                horizon=scale.horizon, experiment="accuracy"))
    for s in scenarios:
        for m in methods:
            for ns in scale.noise_scales:
                if ns == 1.0 and noise_reuses_accuracy(scale):
                    continue
                for j in range(scale.noise_sets):
                    jobs.append(Job("evaluate", s, m, seed=scale.seed, noise_scale=float(ns), set_index=j,
                                    trajectories=scale.noise_trajectories, horizon=scale.horizon, experiment="noise"))
    neural = [m for m in methods if m in NEURAL_METHODS]
    for s in scenarios:
        for m in neural:
            for ratio in scale.data_ratios:
                for i in range(scale.train_instances):
                    overrides = dict(scale.train_overrides)
                    n = scale.train_trajectories(ratio)
                    if n is not None:
                        overrides["trajectories"] = n
                    tj = Job("train", s, m, seed=scale.seed, data_ratio=float(ratio), instance=i,
                             train=tuple(sorted(overrides.items())), experiment="data_ratio")
                    jobs.append(tj)
                    for j in range(scale.sets):
                        jobs.append(Job("evaluate", s, m, seed=scale.seed, set_index=j,
                                        trajectories=scale.ratio_trajectories or scale.trajectories, horizon=scale.horizon,
                                        experiment="data_ratio", data_ratio=float(ratio), instance=i, train_job=tj))
    devices = ["cpu"] + (["cuda"] if gpu else [])
    for device in devices:
        for s in scenarios:
            for m in methods:
                if device == "cuda" and m not in NEURAL_METHODS:
                    continue  # our classical filters are numpy: CPU only
                jobs.append(Job("runtime", s, m, seed=scale.seed, steps=scale.runtime_steps, warmup=scale.runtime_warmup,
                                device=device, experiment="runtime"))
    return jobs
