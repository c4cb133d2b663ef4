"""What the live node tests share (test/test_nodes_*.py; their fixtures ``plugin``, ``cart``, ``domain`` and
``nodes`` are in conftest.py): the test scenario, a small controlled system written to a plugin file so
that the nodes (separate processes) load it through their ``plugins`` parameter (observations carry a
control u_{k-1}), and the node processes of one test.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
from pathlib import Path


from neural_estimator.nodes.launch import (
    isolated_env,
    node_command,
    start_node,
)


PLUGIN = textwrap.dedent(
    '''
    """A cart pushed by a force (test scenario with a control input)."""
    from dataclasses import dataclass

    import numpy as np

    from neural_estimator.scenarios import Scenario, register_scenario


    @dataclass(frozen=True)
    class CartConfig:
        dt: float = 0.05
        horizon: int = 40
        noise_scale: float = 1.0
        obs_noise_std: float = 0.1


    class NodeCart(Scenario):
        name = "nodecart"
        Config = CartConfig
        state_names = ("position", "velocity")
        state_units = ("m", "m/s")
        obs_names = ("position",)
        obs_units = ("m",)
        control_names = ("force",)
        control_units = ("N",)

        def f(self, x, u):
            dt = self.config.dt
            return np.stack([x[..., 0] + dt * x[..., 1], x[..., 1] + dt * u[..., 0]], axis=-1)

        def h(self, x):
            return x[..., :1]

        def process_cov(self):
            return np.diag([1e-6, 1e-3])

        def obs_cov_nominal(self):
            return np.array([[self.config.obs_noise_std ** 2]])

        def prior(self):
            return np.zeros(2), np.eye(2)

        def sample_controls(self, rng, n, horizon):
            return rng.standard_normal((n, horizon, 1))


    register_scenario(NodeCart, replace=True)
    '''
)


class Nodes:
    """Node processes of one test; stopped (SIGINT, then SIGKILL) at the end."""

    def __init__(self, domain: int, log_dir: Path) -> None:
        self.env = isolated_env(domain)
        self.log_dir = log_dir
        self.procs: dict[str, subprocess.Popen] = {}

    def start(self, module: str, name: str, extra_args: tuple[str, ...] = (), **params) -> subprocess.Popen:
        cmd = node_command(sys.executable, module, name, params) + list(extra_args)  # extra ROS args (remaps)
        proc = start_node(cmd, self.log_dir / f"{name}.log", self.env)
        self.procs[name] = proc
        return proc

    def log(self, name: str) -> str:
        return (self.log_dir / f"{name}.log").read_text(errors="replace")

    def wait(self, name: str, timeout: float) -> int:
        try:
            return self.procs[name].wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            raise AssertionError(f"{name} still running after {timeout} s; log:\n{self.log(name)}") from None

    def stop_all(self) -> None:
        for p in self.procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for p in self.procs.values():
            try:
                p.wait(timeout=5)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
