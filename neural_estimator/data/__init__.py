"""Simulation, the dataset file format, and the paper's data protocol."""

from neural_estimator.data.io import DataError, load_npz, load_trajectories, save_estimates, save_npz, save_trajectories
from neural_estimator.data.protocol import (
    ChunkSampler,
    dataset,
    evaluation_sets,
    seed_stream,
    training_set,
    training_trajectories,
    validation_set,
    warmup_mask,
    window_weights,
    windows_per_epoch,
)
from neural_estimator.data.simulate import Trajectories, simulate

__all__ = [
    "ChunkSampler",
    "DataError",
    "Trajectories",
    "dataset",
    "evaluation_sets",
    "load_npz",
    "load_trajectories",
    "save_estimates",
    "save_npz",
    "save_trajectories",
    "seed_stream",
    "simulate",
    "training_set",
    "training_trajectories",
    "validation_set",
    "warmup_mask",
    "window_weights",
    "windows_per_epoch",
]
