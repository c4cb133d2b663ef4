"""What the neural-estimator and training tests share (test/test_neural_estimator.py, test_training*.py,
test_train_zoo.py): the architectures, a small controlled system with an angular state (Spinner, registered
as test_spinner; the conftest's ``spinner`` fixture), a tiny training recipe and a fresh estimator per
architecture.
"""

from dataclasses import dataclass

import numpy as np
import torch
from safetensors.torch import load_file

from neural_estimator.methods import table
from neural_estimator.models import ARCHITECTURES, build_model
from neural_estimator.serving.neural import NeuralEstimator
from neural_estimator.serving.normalization import Normalizer
from neural_estimator.training.recipe import TrainConfig
from neural_estimator.scenarios import Scenario, register_scenario


ARCHS = sorted(n for n in ARCHITECTURES if table.has(n, family="neural"))  # the hybrid: test_kalmannet.py
TOL = 1e-5  # run vs a loop of step, float32 models


# ---- a small controlled system with an angular state (exercises u_{k-1} inputs and wrapping) ------
@dataclass(frozen=True)
class SpinnerConfig:
    dt: float = 0.1
    horizon: int = 80
    noise_scale: float = 1.0
    friction: float = 0.1
    process_noise_std: float = 0.05
    obs_noise_std: float = 0.1


@register_scenario
class Spinner(Scenario):
    """A rotor driven by a random torque: angle (wrapped) and rate, the angle observed."""

    name = "test_spinner"
    Config = SpinnerConfig
    state_names = ("angle", "rate")
    state_units = ("rad", "rad/s")
    obs_names = ("angle",)
    obs_units = ("rad",)
    control_names = ("torque",)
    control_units = ("N m",)
    angle_states = (0,)
    angle_obs = (0,)

    def f(self, x, u):
        c = self.config
        return np.stack([x[..., 0] + c.dt * x[..., 1], x[..., 1] + c.dt * (u[..., 0] - c.friction * x[..., 1])], -1)

    def h(self, x):
        return x[..., :1]

    def process_cov(self):
        return np.diag([1e-6, self.config.process_noise_std**2])

    def obs_cov_nominal(self):
        return np.array([[self.config.obs_noise_std**2]])

    def prior(self):
        return np.array([0.0, 2.0]), np.diag([1.0, 1.0])

    def sample_controls(self, rng, n, horizon):
        return 0.5 * rng.standard_normal((n, horizon, 1))


def tiny_config(cache, **kw):
    base = dict(
        trajectories=12,
        val_trajectories=6,
        train_length=60,
        window=20,
        warmup=5,
        windows_per_epoch=48,
        batch_size=16,
        epochs=3,
        model_overrides={"hidden": 8},
        cache_dir=str(cache),
    )
    base.update(kw)
    return TrainConfig(**base)


def estimator_for(scenario, arch, data, seed=0, head=False):
    """A freshly initialised model of ``arch``; ``head``: with a random covariance head on its trunk."""
    torch.manual_seed(seed)
    norm = Normalizer.from_data(scenario, data)
    model = build_model(arch, scenario)
    if head:
        from neural_estimator.serving.uncertainty.heads import CholeskyHead, GaussianModel

        cov_head = CholeskyHead(model.features(torch.zeros(1, 1, norm.d_in)).shape[-1], scenario.dx)
        with torch.no_grad():
            cov_head.linear.weight.normal_(0.0, 0.1)
        model = GaussianModel(model, cov_head)
    return NeuralEstimator(scenario, model, norm, arch)


def weights(path):
    return load_file(str(path / "model.safetensors"))
