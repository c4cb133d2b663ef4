"""Recorded (training, validation) sets checked against the scenario before a run starts.

A recording's dataset (:mod:`neural_estimator.robot.dataset`) gives the recipe its counts and
lengths. Its ground truth may be partial (a ``labelled`` mask) or absent: a recording with no state
topic, whose spec names the system's model, has no labelled step at all. A state-supervised run
has nothing to learn from there; only a hybrid trained on its observations does
(:mod:`neural_estimator.training.hybrid`), and the card then has no metrics (nothing to score).
"""

from __future__ import annotations

import dataclasses

from neural_estimator.data.simulate import Trajectories
from neural_estimator.scenarios import Scenario
from neural_estimator.training.recipe import TrainConfig, TrainingError

NO_LABELS = "no state labels: train a hybrid with --supervision observations"


def has_labels(data: Trajectories) -> bool:
    """Whether some step of ``data`` holds ground truth (a fully labelled set: mask None)."""
    return data.labelled is None or bool(data.labelled.any())


def recorded_sets(
    scenario: Scenario, cfg: TrainConfig, data: tuple[Trajectories, Trajectories]
) -> tuple[TrainConfig, Trajectories, Trajectories]:
    """Given (training, validation) sets checked against the scenario and the supervision; the
    recipe's counts and lengths from them (no card metrics where the validation set has no label)."""
    train_data, val_data = data
    for role, d in (("training", train_data), ("validation", val_data)):
        if (d.x.shape[2], d.y.shape[2], d.u.shape[2]) != (scenario.dx, scenario.dy, scenario.du):
            raise TrainingError(
                f"{role} data have dx={d.x.shape[2]}, dy={d.y.shape[2]}, du={d.u.shape[2]}; "
                f"the scenario has {scenario.dx}, {scenario.dy}, {scenario.du}"
            )
    if cfg.supervision != "observations" and not has_labels(train_data):
        raise TrainingError(f"the training data have {NO_LABELS}")
    if train_data.horizon < cfg.window:
        raise TrainingError(
            f"training trajectories have {train_data.horizon} steps, fewer than the window "
            f"({cfg.window}); pass a smaller --window or cut longer trajectories"
        )
    cfg = dataclasses.replace(
        cfg,
        trajectories=train_data.n,
        train_length=train_data.horizon,
        val_trajectories=val_data.n,
        eval_trajectories=min(cfg.eval_trajectories, val_data.n) if has_labels(val_data) else 0,
    )
    return cfg, train_data, val_data


__all__ = ["NO_LABELS", "has_labels", "recorded_sets"]
