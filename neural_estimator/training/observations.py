"""Training on observations alone: the normalisation of a model that reads no state label.

A hybrid trained on the observation-only loss (:mod:`neural_estimator.training.hybrid`) never reads
a state, not even for the statistics that set its units and its guard's range; this module gives it
those from the model instead (no import of the training loop: the loop calls it).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from neural_estimator.data.simulate import simulate
from neural_estimator.methods.interface import previous_controls
from neural_estimator.scenarios.model import model_scenario
from neural_estimator.serving.normalization import Normalizer

MODEL_STATISTICS_TRAJECTORIES = 500  # trajectories the model simulates for its state statistics


def observation_normalizer(scenario, data, cfg):
    """The normalisation of an observation-trained hybrid: the inputs' statistics from the training
    observations and controls, the states' (the hybrid's units and its guard's range) from
    trajectories simulated from the model (its f, process noise and prior; the recipe's model set
    where it has one), not from the data's
    states: it reads no state label, and a team that has a model can simulate it."""
    seed = np.random.SeedSequence(cfg.data_seed, spawn_key=(7, cfg.data_index))
    system = model_scenario(scenario, cfg.model_set)  # the team's model (a model set: not the data's)
    model = Normalizer.from_data(scenario, simulate(system, MODEL_STATISTICS_TRAJECTORIES, cfg.train_length, seed))
    inputs = Normalizer.fit(
        data.y, previous_controls(data.u), np.zeros(data.y.shape[:2] + (scenario.dx,)), scenario.angle_states
    )
    return dataclasses.replace(inputs, out_mean=model.out_mean, out_std=model.out_std)
