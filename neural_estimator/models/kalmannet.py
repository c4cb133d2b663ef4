"""KalmanNet: the scenario's f and h with a Kalman gain produced by a small GRU (a hybrid method).

Reference:
    G. Revach, N. Shlezinger, X. Ni, A. L. Escoriza, R. J. G. van Sloun, Y. C. Eldar (2022),
        "KalmanNet: Neural Network Aided Kalman Filtering for Partially Known Dynamics", IEEE Trans.
        Signal Processing 70, https://arxiv.org/abs/2107.10043. Section III keeps the
        (extended) Kalman filter's predict/update flow and replaces the gain computation by a
        recurrent network fed with difference features; its "Architecture 1" (a fully
        connected input layer, one GRU, a fully connected output layer producing K) is the one
        followed here. Its unsupervised variant (Revach et al., "Unsupervised Learned Kalman
        Filtering", https://arxiv.org/abs/2110.09005) trains on the observations alone, through
        h(x_{k|k-1}), which :meth:`KalmanNetModel.rollout` and
        :meth:`KalmanNetModel.obs_residual_norm` provide.

The filter (timing of :mod:`neural_estimator.methods.interface`: at step k the model reads
z_k = [y_k, u_{k-1}], normalised)::

    k = 0:   x_{0|-1} = m0                                  (the prior mean, no predict)
    k >= 1:  x_{k|k-1} = f(x_{k-1|k-1}, u_{k-1})            (the scenario's differentiable f)
    y_pred_k = h(x_{k|k-1});  e_k = y_k - y_pred_k           (angular observations wrapped: bearings)
    features (each divided by the normaliser's std, so O(1)):
        F1 = y_k - y_{k-1}                    observation difference        (0 at k = 0)
        F2 = e_k                              innovation
        F3 = x_{k-1|k-1} - x_{k-2|k-2}        forward evolution difference  (x_{-1|-1} = m0)
        F4 = x_{k-1|k-1} - x_{k-1|k-2}        forward update difference     (x_{-1|-2} = m0)
    a_k = ReLU(W_in [F1, F2, F3, F4] + b_in);  h_k = GRU(a_k, h_{k-1})
    K_n = K0 + W_2 ReLU(W_1 h_k + b_1) + b_2                 (dx x dy, in normalised units)
    K0 = alpha pinv(H_n),  H_n = diag(1/sigma_y) dh/dx(m0) diag(sigma_x)   (fixed, alpha = 0.5)
    K_k = diag(sigma_x) K_n diag(1 / sigma_y)                (the physical gain)
    x_{k|k} = x_{k|k-1} + K_k e_k,  angular states wrapped to (-pi, pi] (N-link's angles)

The state form (``gain_form="state"``, N-link's) corrects in the state space instead, through h
linearised at each prediction, so that the learned part need not follow the configuration::

    J_n = diag(1/sigma_y) dh/dx(x_{k|k-1}) diag(sigma_x)                 (per trajectory, autograd)
    delta_n = (J_n^T J_n + eps I)^{-1} J_n^T e_n    the least-squares state correction (eps = 1e-6)
    features: the four above and delta_n;  G_n = G0 + W_2 ReLU(W_1 h_k + b_1) + b_2   (dx x dx)
    x_{k|k} = x_{k|k-1} + diag(sigma_x) G_n delta_n

G0 carries the alpha-beta tracker's gains (alpha on the states h sees, beta = alpha^2 / (2 - alpha)
over one period on the states that move them, through the model's linearisation at m0; see
:meth:`KalmanNetModel._state_prior_gain`). Why: on N-link the observed positions turn with the
angles, so the gain on the raw innovation must rotate with the configuration, which the difference
features do not carry (1 h of training left it 11.4x the EKF); delta_n already holds the rotation,
and what is left to learn (how much of it to take, and the rates it implies) varies far less.

The gain is produced in normalised units (state and observation each divided by its training std)
so that a unit weight means the same on a kilometre-scale ballistic altitude and a radian: the
network's output is O(1) and well conditioned on every scenario.

Departures from the paper. (1) The features are scaled by the training-set standard deviations
(the authors' code L2-normalises each feature vector per step, which discards its magnitude: a
large innovation would look like a small one); (2) angular components are wrapped in the innovation,
the observation difference and the state differences; (3) the estimate is guarded: a non-finite
x_{k|k} component is replaced by the training mean, and every component is clamped to
mu_x +- 1e3 sigma_x (a physically generous range: the training states lie within a few sigma) so
that one bad step during training gives a large but finite estimate and loss, and the recurrence
(f of a runaway state: the ballistic drag's v^2 e^{-k a}) cannot overflow to NaN and poison the
batch; (4) an observation that is not finite (a dropped sensor reading) is not used: that stream
only predicts, x_{k|k} = x_{k|k-1}, and its GRU memory and last observation are kept, as the
filters do (see :attr:`KalmanNetModel.reads_missing_observations`); (5) the gain is a fixed
model-based part plus the network's: K0, half the least-squares correction through h linearised
at the prior mean, computed from the scenario's h (no noise level is read), and the network's part,
whose final layer starts at a tenth of PyTorch's default scale with a zero bias. An untrained model
is then a reasonable fixed-gain filter rather than the open loop or a random gain, and training
learns the correction (the paper's network outputs the whole gain). Why: started at K = 0 on
Lorenz 96, 40 Adam steps at lr 1e-3 drove some trajectories into the chaotic system's runaway and
the loss to 1e4-1e5; started at K0 the untrained model is at 0.0495 RMSE against the EKF's 0.0492
(50 trajectories x 100 steps; a probe, not a benchmark). K0 is only as good as the linearisation
at m0: on N-link (hanging prior, large swings) it hurts (docs/methods.md); ``prior_gain=0`` removes
it.

Covariance: none. KalmanNet tracks no error covariance (the learned gain replaces the Riccati
recursion that would carry one); any matrix reported from it would be invented.

Parameters (input layer 64, GRU 64, gain head 128 -> dx dy): 34,243 (ballistic), 34,500
(bearings), 48,804 (Lorenz 96), 39,524 (N-link; 39,908 in the state form), 36,818 (quadrotor);
test/test_kalmannet.py holds every scenario within the paper's budget of 100k.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

GAIN_FORMS = ("innovation", "state")
LEAST_SQUARES_EPS = 1e-6  # regularises J_n^T J_n in the state form (module docstring)
CLAMP_STDS = 1e3  # |x_{k|k} - mu_x| <= CLAMP_STDS sigma_x (see the module docstring, departure 3)


class HybridSystemError(ValueError):
    """A system the hybrid cannot be built for (no differentiable f and h)."""


def _wrap(a: Tensor) -> Tensor:
    """a wrapped to (-pi, pi]: pi - mod(pi - a, 2 pi) (derivative 1), as the scenarios wrap."""
    two_pi = 2.0 * math.pi
    m = torch.fmod(math.pi - a, two_pi)
    return math.pi - torch.where(m < 0, m + two_pi, m)


def _index_mask(n: int, idx: tuple[int, ...]) -> Tensor:
    m = torch.zeros(n, dtype=torch.bool)
    m[list(idx)] = True
    return m


@dataclass(frozen=True)
class KalmanNetConfig:
    d_in: int  # dy + du: z_k = [y_k, u_{k-1}]
    d_out: int  # dx
    hidden: int = 64  # GRU width
    in_width: int = 64  # the fully connected input layer's width
    head_width: int = 128  # the hidden layer of the gain head
    gain_init_scale: float = 0.1  # the gain layer's initial weights relative to PyTorch's default
    prior_gain: float = 0.5  # alpha of the fixed model-based gain K0 = alpha pinv(H_n) (0: none)
    gain_form: str = "innovation"  # "innovation": K e (the paper's); "state": G delta (module docstring)


class KalmanNetModel(nn.Module):
    """KalmanNet-style estimator (module docstring): ``forward(z)``, ``step``, ``rollout``.

    The step state is a tuple ``(x_post, x_post_prev, x_prior_prev, y_prev, started, h)``: the
    physical x_{k-1|k-1}, x_{k-2|k-2}, x_{k-1|k-2} (B, dx) held as offsets from the prior mean m0
    (x = m0 + offset), the last used physical observation (B, dy), a (B, 1) flag that is 0 before
    the first step (k = 0: no predict) and the GRU's hidden state (1, B, H). Every tensor of the
    starting state is zeros (the offsets make it so), which the exported ONNX step requires
    (:mod:`neural_estimator.models.onnx_step` resets its state buffers to one constant each).
    """

    reads_missing_observations = True  # the server passes NaN for an unusable y (predict only)

    def __init__(self, cfg: KalmanNetConfig, system: Any) -> None:
        super().__init__()
        dyn = _torch_dynamics(system)
        self.cfg = cfg
        dx, dy, du = int(system.dx), int(system.dy), int(system.du)
        if (cfg.d_in, cfg.d_out) != (dy + du, dx):
            raise HybridSystemError(
                f"kalmannet: config d_in={cfg.d_in}, d_out={cfg.d_out} do not match the system's "
                f"dy + du = {dy + du}, dx = {dx}"
            )
        self.dynamics = dyn
        self.dx, self.dy, self.du = dx, dy, du
        self.scenario_name = str(getattr(system, "name", "system"))
        self.dt = float(getattr(system, "dt", 0.0) or 0.0)  # the state form's G0 (beta / dt)
        import numpy as np  # the prior is numpy; torch owns the model

        # the served scenario's prior, as f and h are (not saved); float64, cast to the state's dtype
        # where used, so that a model moved to float64 has it to the last bit
        m0 = torch.as_tensor(np.asarray(system.prior()[0], dtype=np.float64), dtype=torch.float64)
        self.register_buffer("m0", m0, persistent=False)
        self.register_buffer("in_mean", torch.zeros(dy + du))
        self.register_buffer("in_std", torch.ones(dy + du))
        self.register_buffer("out_mean", torch.zeros(dx))
        self.register_buffer("out_std", torch.ones(dx))
        self.register_buffer("angle_states", _index_mask(dx, tuple(system.angle_states)), persistent=False)
        self.register_buffer("angle_obs", _index_mask(dy, tuple(getattr(system, "angle_obs", ()))), persistent=False)
        if cfg.gain_form not in GAIN_FORMS:
            raise HybridSystemError(f"kalmannet: gain_form {cfg.gain_form!r} is not one of {', '.join(GAIN_FORMS)}")
        self.state_form = cfg.gain_form == "state"
        n_feat = 2 * dy + 2 * dx + (dx if self.state_form else 0)  # + delta_n in the state form
        self.input_layer = nn.Linear(n_feat, cfg.in_width)
        self.gru = nn.GRU(cfg.in_width, cfg.hidden, batch_first=True)
        self.head = nn.Linear(cfg.hidden, cfg.head_width)
        self.gain_cols = dx if self.state_form else dy  # G is dx x dx, K is dx x dy
        self.gain = nn.Linear(cfg.head_width, dx * self.gain_cols)
        with torch.no_grad():  # the network's part starts near 0: the gain starts near K0 (departure 5)
            self.gain.weight.mul_(cfg.gain_init_scale)
            self.gain.bias.zero_()
        # K0 (dx x dy) or, in the state form, G0 = alpha I (dx x dx); normalised units (saved)
        self.register_buffer("gain_prior", torch.zeros(dx, self.gain_cols))
        self._set_prior_gain()

    # ---- normalisation ---------------------------------------------------------------------------
    def set_normalization(self, norm: Any) -> None:
        """Copy a :class:`~neural_estimator.serving.normalization.Normalizer`'s statistics into the
        buffers (saved with the weights), so the model maps normalised z to physical y, u and
        physical x back to normalised x. They take the model's dtype now: call it after a change
        of dtype (``model.double()``), not before, to keep them to float64's precision."""
        if (int(norm.dy), int(norm.du), int(norm.dx)) != (self.dy, self.du, self.dx):
            raise HybridSystemError(
                f"kalmannet: normalisation statistics are for dy={norm.dy}, du={norm.du}, dx={norm.dx}; "
                f"the model is for dy={self.dy}, du={self.du}, dx={self.dx}"
            )
        for name in ("in_mean", "in_std", "out_mean", "out_std"):
            buf = getattr(self, name)
            buf.copy_(torch.as_tensor(getattr(norm, name), dtype=buf.dtype, device=buf.device))
        self._set_prior_gain()  # K0 is in normalised units: it follows the statistics

    def _set_prior_gain(self) -> None:
        """K0 = alpha pinv(H_n), H_n = diag(1 / sigma_y) dh/dx(m0) diag(sigma_x): the least-squares
        correction of x that would explain a fraction alpha of an innovation, with h linearised at
        the prior mean (float64 autograd; pinv drops the directions h does not see, e.g. N-link's
        velocities). Not computed on torch's meta device (the checkpoint's size probe)."""
        if self.gain_prior.is_meta:
            return
        if self.state_form:
            self.gain_prior.copy_(self._state_prior_gain().to(self.gain_prior.dtype))
            return
        m0 = self.m0.detach().to("cpu", torch.float64)
        jac = torch.autograd.functional.jacobian(lambda x: self.dynamics.h(x), m0)  # (dy, dx)
        dy = self.dy
        y_std = self.in_std[:dy].detach().to("cpu", torch.float64)
        x_std = self.out_std.detach().to("cpu", torch.float64)
        h_n = jac.reshape(dy, self.dx) * x_std[None, :] / y_std[:, None]
        k0 = float(self.cfg.prior_gain) * torch.linalg.pinv(h_n)  # (dx, dy)
        self.gain_prior.copy_(k0.to(self.gain_prior.dtype))

    def _state_prior_gain(self) -> Tensor:
        """G0 of the state form (normalised units, float64): the alpha-beta tracker's gains carried
        through the model's own kinematics, no noise level read. With S the states h sees at m0 (the
        non-zero columns of J_n), U the rest and A_n = diag(1/sigma_x) (df/dx(m0) - I) diag(sigma_x) / dt
        the model's continuous-time linearisation::

            G0[S, S] = alpha I,   G0[U, S] = (beta / dt) pinv(A_n[S, U]),   beta = alpha^2 / (2 - alpha)

        (Benedict and Bordner's beta). A_n[S, U] says how fast the unseen states move the seen ones
        (N-link: the angular rates move the angles, A[S, U] = I), so G0[U, S] gives the rates that
        would have made the correction alpha-beta's share of delta over one period. With every state
        seen (Lorenz 96) G0 = alpha I."""
        x_std = self.out_std.detach().to("cpu", torch.float64)
        y_std = self.in_std[: self.dy].detach().to("cpu", torch.float64)
        m0 = self.m0.detach().to("cpu", torch.float64)
        jac_h = torch.autograd.functional.jacobian(lambda x: self.dynamics.h(x), m0).reshape(self.dy, self.dx)
        seen = (jac_h * x_std[None, :] / y_std[:, None]).abs().amax(dim=0) > 1e-9
        alpha = float(self.cfg.prior_gain)
        g0 = torch.zeros(self.dx, self.dx, dtype=torch.float64)
        idx_s, idx_u = seen.nonzero()[:, 0], (~seen).nonzero()[:, 0]
        g0[idx_s, idx_s] = alpha
        if alpha and not bool(seen.all()):
            u = torch.zeros(1, self.du, dtype=torch.float64) if self.du else None
            jac_f = torch.autograd.functional.jacobian(lambda x: self.dynamics.f(x[None], u)[0], m0)
            a_n = (jac_f - torch.eye(self.dx, dtype=torch.float64)) * x_std[None, :] / x_std[:, None] / self.dt
            beta = alpha * alpha / (2.0 - alpha)
            g0[idx_u[:, None], idx_s[None, :]] = beta / self.dt * torch.linalg.pinv(a_n[seen][:, ~seen])
        return g0

    # ---- the recurrence --------------------------------------------------------------------------
    def init_state(self, batch: int, device=None, dtype=None) -> tuple[Tensor, ...]:
        p = self.gain.weight
        device = p.device if device is None else device
        dtype = p.dtype if dtype is None else dtype

        def zeros(*shape: int) -> Tensor:
            return torch.zeros(*shape, device=device, dtype=dtype)

        return (
            zeros(batch, self.dx),  # x_{-1|-1} = m0: offset 0
            zeros(batch, self.dx),
            zeros(batch, self.dx),
            zeros(batch, self.dy),
            zeros(batch, 1),
            zeros(1, batch, self.cfg.hidden),
        )

    def step(self, z_t: Tensor, state: tuple[Tensor, ...]) -> tuple[Tensor, tuple[Tensor, ...]]:
        """One step: z_t (B, d_in) normalised -> (normalised x_{k|k} (B, dx), new state)."""
        x_n, _, new = self._step(z_t, state)
        return x_n, new

    def rollout(self, z: Tensor, state: tuple[Tensor, ...]) -> tuple[Tensor, Tensor, tuple[Tensor, ...]]:
        """T steps from ``state``: (normalised x_{k|k} (B, T, dx), normalised h(x_{k|k-1}) (B, T, dy),
        the state after the last step). The predicted observation at k is made before y_k is read."""
        xs, ys = [], []
        for t in range(z.shape[1]):
            x_n, y_pred_n, state = self._step(z[:, t], state)
            xs.append(x_n)
            ys.append(y_pred_n)
        if not xs:
            B = z.shape[0]
            return z.new_zeros(B, 0, self.dx), z.new_zeros(B, 0, self.dy), state
        return torch.stack(xs, dim=1), torch.stack(ys, dim=1), state

    def forward(self, z: Tensor) -> Tensor:
        """z (B, T, d_in) normalised -> normalised x_{k|k} (B, T, dx), from the prior at k = 0."""
        return self.rollout(z, self.init_state(z.shape[0], device=z.device, dtype=z.dtype))[0]

    def obs_residual_norm(self, y_pred_norm: Tensor, z: Tensor) -> Tensor:
        """y_k - y_pred_k in normalised units (B, T, dy), angular components wrapped (in radians
        before dividing by their std): the observation-only loss is its mean square."""
        dy = self.dy
        std = self.in_std[:dy]
        r = (z[..., :dy] - y_pred_norm) * std  # physical residual
        r = torch.where(self.angle_obs, _wrap(r), r)
        return r / std

    def _step(self, z_t: Tensor, state: tuple[Tensor, ...]) -> tuple[Tensor, Tensor, tuple[Tensor, ...]]:
        o_post, o_post_prev, o_prior_prev, y_prev, started, h = state
        dy = self.dy
        m0 = self.m0.to(o_post.dtype)
        x_post, x_post_prev, x_prior_prev = o_post + m0, o_post_prev + m0, o_prior_prev + m0
        y_std, y_mean = self.in_std[:dy], self.in_mean[:dy]
        y_n = z_t[..., :dy]
        seen = torch.isfinite(y_n).all(dim=-1, keepdim=True)  # (B, 1): a usable observation
        y = torch.where(seen, y_n, torch.zeros_like(y_n)) * y_std + y_mean
        u = z_t[..., dy:] * self.in_std[dy:] + self.in_mean[dy:] if self.du else None
        # predict (k >= 1); the prior mean at k = 0
        x_prior = torch.where(started > 0, self._guard(self.dynamics.f(x_post, u)), m0.expand_as(x_post))
        y_pred = self.dynamics.h(x_prior)
        innov = self._obs_diff(y, y_pred)
        d_obs = torch.where(started > 0, self._obs_diff(y, y_prev), torch.zeros_like(y))
        x_std = self.out_std
        innov_n = innov / y_std
        delta_n = self._least_squares_correction(x_prior, innov_n) if self.state_form else None
        feats = torch.cat(
            [
                d_obs / y_std,
                innov_n,
                self._state_diff(x_post, x_post_prev) / x_std,
                self._state_diff(x_post, x_prior_prev) / x_std,
                *((delta_n,) if self.state_form else ()),
            ],
            dim=-1,
        )
        feats = torch.nan_to_num(feats, nan=0.0, posinf=0.0, neginf=0.0)
        feats = torch.where(seen, feats, torch.zeros_like(feats))
        a = F.relu(F.linear(feats, self.input_layer.weight, self.input_layer.bias))
        h_new = self._gru_cell(a, h[0])
        k_n = self.gain(F.relu(self.head(h_new))).unflatten(-1, (self.dx, self.gain_cols)) + self.gain_prior
        # K_n e_n, or G_n delta_n in the state form; normalised state units
        dx_n = (k_n @ (delta_n if self.state_form else innov_n)[..., None])[..., 0]
        upd = x_prior + torch.where(seen, dx_n * x_std, torch.zeros_like(dx_n))
        upd = torch.where(self.angle_states, _wrap(upd), upd)
        x_new = self._guard(upd)
        new_state = (
            x_new - m0,
            o_post,
            x_prior - m0,
            torch.where(seen, y, y_prev),
            torch.ones_like(started),
            torch.where(seen, h_new, h[0])[None],
        )
        y_pred_n = (y_pred - y_mean) / y_std
        return (x_new - self.out_mean) / x_std, y_pred_n, new_state

    def _least_squares_correction(self, x_prior: Tensor, innov_n: Tensor) -> Tensor:
        """delta_n = (J_n^T J_n + eps I)^{-1} J_n^T e_n with J_n = diag(1/sigma_y) dh/dx(x_{k|k-1})
        diag(sigma_x): the normalised state correction that explains the innovation in the least-squares
        sense, h linearised at this step's prediction (per trajectory: torch.func's vmap of jacrev,
        differentiable for training). Directions h does not see (N-link's rates) get 0: their rows of
        J_n^T e_n are 0 and eps (1e-6, in normalised units where J_n is O(1)) keeps the system regular."""
        from torch.func import jacrev, vmap  # here: the innovation form never needs them

        lead = x_prior.shape[:-1]
        x = x_prior.reshape(-1, self.dx)
        jac = vmap(jacrev(self.dynamics.h))(x)  # (B, dy, dx)
        jac_n = jac * self.out_std[None, None, :] / self.in_std[: self.dy][None, :, None]
        jac_n = torch.nan_to_num(jac_n, nan=0.0, posinf=0.0, neginf=0.0)
        eye = torch.eye(self.dx, dtype=x.dtype, device=x.device)
        normal = jac_n.transpose(-1, -2) @ jac_n + LEAST_SQUARES_EPS * eye
        rhs = jac_n.transpose(-1, -2) @ torch.nan_to_num(innov_n.reshape(-1, self.dy, 1))
        return torch.linalg.solve(normal, rhs)[..., 0].reshape(*lead, self.dx)

    def _gru_cell(self, a: Tensor, h: Tensor) -> Tensor:
        g = self.gru
        return torch.gru_cell(a, h, g.weight_ih_l0, g.weight_hh_l0, g.bias_ih_l0, g.bias_hh_l0)

    def _guard(self, x: Tensor) -> Tensor:
        """Non-finite components to the training mean, then clamped to mu_x +- CLAMP_STDS sigma_x."""
        mean, span = self.out_mean, CLAMP_STDS * self.out_std
        x = torch.where(torch.isfinite(x), x, mean.expand_as(x))
        return torch.minimum(torch.maximum(x, mean - span), mean + span)

    def _obs_diff(self, a: Tensor, b: Tensor) -> Tensor:
        d = a - b
        return torch.where(self.angle_obs, _wrap(d), d)

    def _state_diff(self, a: Tensor, b: Tensor) -> Tensor:
        d = a - b
        return torch.where(self.angle_states, _wrap(d), d)

    @property
    def onnx_blocker(self) -> str | None:
        """Why this model's step cannot be exported to ONNX, or None: the system's f and h are probed
        once with torch's exporter (:func:`neural_estimator.models.onnx_step.unsupported_reason`;
        N-link's f solves its mass-matrix system with ``torch.linalg.solve``, which opset 17 lacks,
        so the N-link hybrid is served by torch; the other four export). The state form never
        exports: its per-step Jacobian of h is a torch.func transform."""
        if self.state_form:  # torch's exporter cannot trace torch.func's transforms
            return (
                "the state form's gain needs h's Jacobian at every step (torch.func.jacrev), "
                "which ONNX export cannot trace"
            )
        if "_onnx_blocker" not in self.__dict__:
            from neural_estimator.models.onnx_step import unsupported_reason

            dyn, x = self.dynamics, torch.zeros(1, self.dx) + self.m0.detach().cpu().float()
            u = torch.zeros(1, self.du)
            fn = (lambda a, b: (dyn.f(a, b), dyn.h(a))) if self.du else (lambda a: (dyn.f(a, None), dyn.h(a)))
            args = (x, u) if self.du else (x,)
            self.__dict__["_onnx_blocker"] = unsupported_reason(fn, args, f"{self.scenario_name}'s f or h")
        return self.__dict__["_onnx_blocker"]

    def extra_repr(self) -> str:
        return f"scenario={self.scenario_name!r}, dx={self.dx}, dy={self.dy}, du={self.du}"


def _torch_dynamics(system: Any) -> Any:
    """The system's differentiable f and h, or a one-line HybridSystemError."""
    getter = getattr(system, "torch_dynamics", None)
    dyn = getter() if callable(getter) else None
    if dyn is None:
        name = getattr(system, "name", type(system).__name__)
        raise HybridSystemError(
            f"kalmannet needs the system's differentiable f and h (scenario.torch_dynamics()); "
            f"{name!r} has none (recorded data without a model, or only its dimensions)"
        )
    if not hasattr(system, "prior") or not hasattr(system, "angle_states"):
        raise HybridSystemError(f"kalmannet needs the scenario's prior and angle_states; {system!r} has none")
    return dyn
