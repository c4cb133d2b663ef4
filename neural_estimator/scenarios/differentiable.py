"""The five systems' f and h in torch: differentiable, batched, float64 capable.

``scenario.torch_dynamics()`` returns one of the classes below (None for a scenario without a
differentiable form: a user's, recorded data), so that a method can backpropagate through the
system's equations (a KalmanNet-style hybrid: the system's f and h with a learned gain)::

    dyn = make_scenario("nlink").torch_dynamics()
    x = torch.zeros(8, dyn.dx, dtype=torch.float64, requires_grad=True)
    dyn.f(x, None).sum().backward()

``f(x, u)``: (..., dx), (..., du) -> (..., dx); ``h(x)``: (..., dx) -> (..., dy), on any leading
axes, in the dtype and on the device of ``x`` (float64 for the numpy form's numbers; float32 works,
with float32's round-off). The arithmetic is the numpy form's, operation for operation: the same
integrator (RK4 in ``substeps`` steps of ``dt / substeps``, or the quadrotor's Euler step), the same
order of operations, the same wrapping of angles (``pi - mod(pi - a, 2 pi)``, whose derivative is 1),
so the two agree to round-off (the tests hold them to 1e-10 in float64, and the autograd Jacobians to
the scenarios' analytic ones, which the EKF uses, to 1e-8). The constants are read from the
scenario's config when the object is made.

Only this module of :mod:`neural_estimator.scenarios` imports torch; the scenarios import it inside
``torch_dynamics()``, so they stay usable without torch.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

Tensor = torch.Tensor


def wrap_angle(a: Tensor) -> Tensor:
    """:func:`neural_estimator.core.angles.wrap_angle` in torch: pi - mod(pi - a, 2 pi), in (-pi, pi].

    numpy's float mod is fmod, plus the divisor where the remainder is negative; the same here (not
    torch.remainder, whose a - b floor(a / b) rounds differently). Its derivative is 1 (off the
    measure-zero jumps)."""
    two_pi = 2.0 * math.pi
    m = torch.fmod(math.pi - a, two_pi)
    return math.pi - torch.where(m < 0, m + two_pi, m)


def rk4(field: Callable[[Tensor], Tensor], x: Tensor, h: float, substeps: int) -> Tensor:
    """:func:`neural_estimator.scenarios._integrate.rk4` in torch, the same operations in the same order."""
    for _ in range(substeps):
        k1 = field(x)
        k2 = field(x + 0.5 * h * k1)
        k3 = field(x + 0.5 * h * k2)
        k4 = field(x + h * k3)
        x = x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
    return x


class TorchDynamics:
    """A scenario's f and h on torch tensors (see the module docstring); subclasses implement them."""

    def __init__(self, scenario: Any) -> None:
        self.scenario = scenario
        self.config = scenario.config
        self.dx, self.dy, self.du = scenario.dx, scenario.dy, scenario.du

    def f(self, x: Tensor, u: Tensor | None = None) -> Tensor:
        """x_{k+1} = f(x_k, u_k) without noise; (..., dx), (..., du) -> (..., dx)."""
        raise NotImplementedError

    def h(self, x: Tensor) -> Tensor:
        """h(x_k) without noise; (..., dx) -> (..., dy)."""
        raise NotImplementedError

    @staticmethod
    def _tensor(value: Any, like: Tensor) -> Tensor:
        """A numpy constant as a tensor in ``like``'s dtype and device."""
        return torch.as_tensor(np.asarray(value, dtype=np.float64), dtype=like.dtype, device=like.device)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.scenario.name!r})"


class BallisticTorch(TorchDynamics):
    """:class:`~neural_estimator.scenarios.ballistic.Ballistic`: RK4 of the drag dynamics, range to the radar."""

    def _field(self, x: Tensor) -> Tensor:
        cfg = self.config
        a, v, c = x[..., 0], x[..., 1], x[..., 2]
        above = a > 0.0
        # E(a) = min(exp(-k a), 1) as the numpy form writes it (no exp of a very negative altitude)
        e = torch.where(above, torch.exp(-cfg.k * torch.where(above, a, torch.zeros_like(a))), torch.ones_like(a))
        return torch.stack([-v, cfg.g - c * v * v * e, torch.zeros_like(c)], dim=-1)

    def f(self, x: Tensor, u: Tensor | None = None) -> Tensor:
        cfg = self.config
        return rk4(self._field, x, cfg.dt / cfg.substeps, cfg.substeps)

    def h(self, x: Tensor) -> Tensor:
        cfg = self.config
        d = x[..., 0] - cfg.a_ref
        return torch.sqrt(cfg.r0**2 + d * d)[..., None]


class BearingsTorch(TorchDynamics):
    """:class:`~neural_estimator.scenarios.bearings.Bearings`: constant velocity, the wrapped bearing."""

    def f(self, x: Tensor, u: Tensor | None = None) -> Tensor:
        t = float(self.config.dt)
        return torch.stack([x[..., 0] + t * x[..., 2], x[..., 1] + t * x[..., 3], x[..., 2], x[..., 3]], dim=-1)

    def h(self, x: Tensor) -> Tensor:
        return wrap_angle(torch.atan2(x[..., 1], x[..., 0]))[..., None]


class Lorenz96Torch(TorchDynamics):
    """:class:`~neural_estimator.scenarios.lorenz96.Lorenz96`: RK4 of the ring, H = I."""

    def _field(self, x: Tensor) -> Tensor:
        n = x.shape[-1]
        xp = torch.cat((x[..., -2:], x, x[..., :1]), dim=-1)  # index j + 2 holds X_j
        return (xp[..., 3 : n + 3] - xp[..., 0:n]) * xp[..., 1 : n + 1] - x + self.config.forcing

    def f(self, x: Tensor, u: Tensor | None = None) -> Tensor:
        cfg = self.config
        return rk4(self._field, x, cfg.dt / cfg.substeps, cfg.substeps)

    def h(self, x: Tensor) -> Tensor:
        return x.clone()


class NLinkTorch(TorchDynamics):
    """:class:`~neural_estimator.scenarios.nlink.NLinkPendulum`: RK4 of the Euler-Lagrange equations
    (the reference ``_field``: a batched linear solve), angles wrapped; the masses' positions."""

    def __init__(self, scenario: Any) -> None:
        super().__init__(scenario)
        self.n_links = scenario.n_links
        self._lengths, self._weights, self._grav = scenario._constants()

    def _field(self, x: Tensor) -> Tensor:
        n = self.n_links
        weights, grav = self._tensor(self._weights, x), self._tensor(self._grav, x)
        th, om = x[..., :n], x[..., n:]
        c, s = torch.cos(th), torch.sin(th)
        cj, ck, sj, sk = c[..., :, None], c[..., None, :], s[..., :, None], s[..., None, :]
        mass = weights * (cj * ck + sj * sk)  # (..., N, N)
        skew = weights * (sj * ck - cj * sk)
        rhs = -(skew * (om * om)[..., None, :]).sum(dim=-1) - grav * s
        acc = torch.linalg.solve(mass, rhs[..., None])[..., 0]
        return torch.cat([om, acc], dim=-1)

    def f(self, x: Tensor, u: Tensor | None = None) -> Tensor:
        cfg, n = self.config, self.n_links
        y = rk4(self._field, x, cfg.dt / cfg.substeps, cfg.substeps)
        return torch.cat([wrap_angle(y[..., :n]), y[..., n:]], dim=-1)

    def h(self, x: Tensor) -> Tensor:
        lengths = self._tensor(self._lengths, x)
        th = x[..., : self.n_links]
        px = torch.cumsum(lengths * torch.sin(th), dim=-1)
        pz = -torch.cumsum(lengths * torch.cos(th), dim=-1)
        return torch.stack([px, pz], dim=-1).reshape(x.shape[:-1] + (2 * self.n_links,))


class QuadrotorTorch(TorchDynamics):
    """:class:`~neural_estimator.scenarios.quadrotor.PlanarQuadrotor`: one Euler step, y = C x."""

    def f(self, x: Tensor, u: Tensor | None = None) -> Tensor:
        cfg = self.config
        if u is None:
            raise ValueError("quadrotor: f needs the controls u (..., 2)")
        tau = float(cfg.dt)
        px, pz, phi, vx, vz, rate = (x[..., i] for i in range(6))
        c, s = torch.cos(phi), torch.sin(phi)
        keep = 1.0 if cfg.integrate_phi_rate else 0.0
        return torch.stack(
            [
                px + (vx * c - vz * s) * tau,
                pz + (vx * s + vz * c) * tau,
                phi + rate * tau,
                vx + (vz * rate - cfg.g * s) * tau,
                vz + (-vx * rate - cfg.g * c + (u[..., 0] + u[..., 1]) / cfg.mass) * tau,
                keep * rate + (u[..., 0] - u[..., 1]) * cfg.arm * tau / cfg.inertia,
            ],
            dim=-1,
        )

    def h(self, x: Tensor) -> Tensor:
        return x @ self._tensor(self.config.c_matrix, x).T
