"""A user-defined scenario: a damped oscillator observed through its position.

Registering it makes the name ``oscillator`` usable by every tool, for example

    neural-estimator simulate --plugin examples/custom_scenario.py --scenario oscillator \
        --trajectories 100 --out osc.npz
    neural-estimator evaluate --plugin examples/custom_scenario.py --scenario oscillator \
        --methods ekf,ukf --trajectories 200

The system is linear-Gaussian, so the Kalman filter is the exact posterior and the EKF and UKF
must reproduce it: the test suite uses this file for that known answer.

    x_{k+1} = A x_k + w_k,   A = [[1, dt], [-omega^2 dt, 1 - 2 zeta omega dt]]
    y_k     = x_{k,0} + v_k
"""

from dataclasses import dataclass

import numpy as np

from neural_estimator.scenarios import Scenario, register_scenario


@dataclass(frozen=True)
class OscillatorConfig:
    dt: float = 0.1  # s
    horizon: int = 200
    noise_scale: float = 1.0
    omega: float = 1.0  # rad/s, natural frequency
    zeta: float = 0.1  # damping ratio
    process_noise_std: float = 0.05  # on the velocity, per step
    obs_noise_std: float = 0.2  # m


@register_scenario
class Oscillator(Scenario):
    name = "oscillator"
    Config = OscillatorConfig
    state_names = ("position", "velocity")
    state_units = ("m", "m/s")
    obs_names = ("position",)
    obs_units = ("m",)

    def transition_matrix(self) -> np.ndarray:
        c = self.config
        return np.array([[1.0, c.dt], [-(c.omega**2) * c.dt, 1.0 - 2.0 * c.zeta * c.omega * c.dt]])

    def f(self, x, u):
        return x @ self.transition_matrix().T

    def h(self, x):
        return x[..., :1]

    def jac_f(self, x, u):
        return np.broadcast_to(self.transition_matrix(), x.shape[:-1] + (2, 2)).copy()

    def jac_h(self, x):
        return np.broadcast_to(np.array([[1.0, 0.0]]), x.shape[:-1] + (1, 2)).copy()

    def process_cov(self):
        return np.diag([1e-8, self.config.process_noise_std**2])

    def obs_cov_nominal(self):
        return np.array([[self.config.obs_noise_std**2]])

    def prior(self):
        return np.array([1.0, 0.0]), np.diag([0.5**2, 0.5**2])
