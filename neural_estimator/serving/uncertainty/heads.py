"""Gaussian covariance heads on the frozen trunk of a trained model: the estimate stays bit-identical.

Every architecture of :mod:`neural_estimator.models` ends in a read-out of its last hidden features
h_t (``features`` / ``step_features``): x_n = head(h_t) in normalised units. A covariance head is a
second read-out of the same features,

    a_t  = W h_t + b                                  (W: dx + dx (dx - 1) / 2 rows)
    L_t  = diag(u) A_t,  A_t lower-triangular, A_ii = exp(clamp(a_i)),  A_ij = a_ij (i > j)
    C_t  = D L_t L_t^T D,   D = diag(sqrt(s))         (s: the post-hoc calibration scale, 1 by default)

u is fixed at the per-component standard deviation of the errors the head is fitted on, so the
trained part A works in units where every error component has spread one (its diagonal and its
off-diagonal entries are commensurate, which keeps Adam's steps stable for any scale of error).

and, where the card says so (``shrink`` = rho > 0), C_t <- (1 - rho) C_t + rho diag(C_t), a shrinkage of
the correlations that bounds how thin the covariance can get (chosen on validation data where the
head's correlations reach +-0.9999 and the errors lie across the thin direction: the bearings
Filterformer). C_t is symmetric positive definite by construction, in normalised units (the estimator maps it to
state units as diag(sigma_x) C_t diag(sigma_x), see ``Normalizer.denormalize_covariance``). The head
is trained on the frozen trunk by the Gaussian negative log-likelihood of the trunk's own errors

    NLL = 1/2 || L_t^{-1} e_t ||^2 + sum_i log L_ii + (dx / 2) log 2 pi,  e_t = x_hat_t - x_t (normalised,
          angle components wrapped)

(:mod:`neural_estimator.serving.uncertainty.fit`), so the mean, its weights and the RMSE do not change at all
and the trunk's weight file (and its sha256 in the card) stays as it was. ``s`` is fitted afterwards
on other validation trajectories (:mod:`neural_estimator.metrics.consistency`).

:class:`GaussianModel` wraps a trunk and its head behind the interface the estimator already uses for
Filterformer (``forward_with_cov``, ``step_with_cov``); everything else passes through to the trunk.
The head is stored beside the weights as ``covariance_head.safetensors`` and described by the card's
``covariance_head`` entry (:func:`save_head`, :func:`load_head`); a card without it serves as before.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from neural_estimator.serving.card import canonical_safetensors, open_checkpoint_file, sha256_file

HEAD_FILE = "covariance_head.safetensors"
HEAD_FORM = "cholesky"
LOG_DIAG_RANGE = (-14.0, 10.0)  # clamp of log L_ii: variances of e^-28 .. e^20 in normalised units


class HeadError(ValueError):
    """A covariance head that cannot be built, stored or read; the message names the problem."""


class CholeskyHead(nn.Module):
    """h (..., H) -> covariance (..., n, n) = D L L^T D with L from a linear read-out (module docstring)."""

    def __init__(self, features: int, n: int) -> None:
        super().__init__()
        self.n = int(n)
        self.linear = nn.Linear(int(features), self.n + self.n * (self.n - 1) // 2)
        # L = v[..., place].view(n, n) with v = [exp(diag part), off-diagonal part, 0]: a gather, so the
        # head exports to ONNX (the estimator's onnxruntime backend) where an indexed assignment does not
        n = self.n
        place = torch.full((n, n), 2 * n + n * (n - 1) // 2 - n, dtype=torch.long)  # the trailing 0
        place[range(n), range(n)] = torch.arange(n)
        rows, cols = torch.tril_indices(n, n, offset=-1)
        place[rows, cols] = n + torch.arange(rows.numel())
        self.register_buffer("place", place.reshape(-1), persistent=False)
        self.register_buffer("unit", torch.ones(self.n))  # u: the fit's error std per component (fixed)
        self.register_buffer("scale", torch.ones(self.n))  # s: per-component variance scale (calibration)
        self.shrink = 0.0  # rho: C <- (1 - rho) C + rho diag(C), from the card (see the module docstring)
        nn.init.zeros_(self.linear.weight)
        nn.init.zeros_(self.linear.bias)

    def init_constant(self, std: Tensor) -> None:
        """Start from the constant diagonal covariance diag(std^2): u = std, zero weights."""
        with torch.no_grad():
            self.linear.weight.zero_()
            self.linear.bias.zero_()
            self.unit.copy_(std.to(self.unit))

    def factor(self, h: Tensor) -> Tensor:
        """diag(u) L (..., n, n), lower triangular with a positive diagonal, before the calibration scale."""
        a = F.linear(h, self.linear.weight, self.linear.bias)
        n = self.n
        v = torch.cat([torch.exp(a[..., :n].clamp(*LOG_DIAG_RANGE)), a[..., n:], a[..., :1] * 0.0], dim=-1)
        L = v[..., self.place].unflatten(-1, (n, n))
        return self.unit.unsqueeze(-1) * L

    def forward(self, h: Tensor) -> Tensor:
        """The covariance in float64: a product L L^T rounded to float32 is not positive semi-definite
        when two components are correlated beyond ~0.9999 (bearings: range along the line of
        sight), and a float64 product of the float32 factor is (the factor is what was fitted)."""
        L = (self.factor(h) * self.scale.sqrt().unsqueeze(-1)).double()  # D L
        C = L @ L.transpose(-1, -2)
        if self.shrink:  # off-diagonal entries times (1 - rho), the diagonal kept
            eye = torch.eye(self.n, dtype=C.dtype, device=C.device)
            C = C * ((1.0 - self.shrink) * (1.0 - eye) + eye)
        return C

    def onnx_form(self) -> nn.Module:
        """This head's covariance for one step in fewer ONNX Runtime operators (:class:`_CholeskyStepForm`)."""
        return _CholeskyStepForm(self)

    def nll(self, h: Tensor, e: Tensor) -> Tensor:
        """Mean Gaussian negative log-likelihood (without the constant) of errors e (K, n) at features h (K, H)."""
        L = self.factor(h)
        w = torch.linalg.solve_triangular(L, e.unsqueeze(-1), upper=False).squeeze(-1)  # L^-1 e
        return (0.5 * (w * w).sum(-1) + torch.log(torch.diagonal(L, dim1=-2, dim2=-1)).sum(-1)).mean()


class _CholeskyStepForm(nn.Module):
    """:meth:`CholeskyHead.forward` for one step, h (1, H) -> C (1, n, n) float64, as few operators:
    exp(clamp) over the whole read-out a with a Where that keeps it on the diagonal entries only
    (instead of slicing a into its parts and concatenating them with a zero), one Gather of the
    n x n entries of L (those above the diagonal read any entry), and one product with a constant
    that is the row scale u_i sqrt(s_i) below and on the diagonal and 0 above it (instead of two
    row scalings and the gathered zero). Same L and C as the head's, to float32 rounding of the
    row scales."""

    def __init__(self, head: CholeskyHead) -> None:
        super().__init__()
        n, m = head.n, head.linear.out_features
        self.linear = head.linear
        diag = torch.zeros(m, dtype=torch.bool)
        diag[:n] = True  # a's first n entries are the log-diagonal
        place = head.place.view(n, n).clone()
        place[place >= m] = 0  # the trailing zero of v: read any entry, the mask zeroes it
        rows = (head.unit * head.scale.sqrt()).view(n, 1) * torch.ones(n, n).tril()  # u_i sqrt(s_i), i >= j
        self.register_buffer("diag", diag)
        self.register_buffer("place", place)
        self.register_buffer("rows", rows.detach().clone().float())
        eye = torch.eye(n, dtype=torch.float64)
        self.shrink = float(head.shrink)
        self.register_buffer("keep", (1.0 - self.shrink) * (1.0 - eye) + eye)  # C's entries kept under shrink

    def forward(self, h: Tensor) -> Tensor:
        a = self.linear(h)  # (1, m)
        v = torch.where(self.diag, torch.exp(a.clamp(*LOG_DIAG_RANGE)), a)
        L = (v[:, self.place] * self.rows).double()  # (1, n, n): D diag(u) A
        C = L @ L.transpose(-1, -2)
        return C * self.keep if self.shrink else C


class GaussianModel(nn.Module):
    """A trained model (the trunk, unchanged) with a covariance head on its last features.

    ``forward``/``step`` are the trunk's own (the same estimate, bit for bit); ``forward_with_cov``
    and ``step_with_cov`` add the head's covariance. Other attributes come from the trunk.
    """

    def __init__(self, trunk: nn.Module, head: CholeskyHead) -> None:
        super().__init__()
        if not hasattr(trunk, "features") or not hasattr(trunk, "step_features"):
            raise HeadError(f"{type(trunk).__name__} exposes no features for a covariance head")
        self.trunk = trunk
        self.cov_head = head

    def __getattr__(self, name: str) -> Any:
        try:
            return super().__getattr__(name)
        except AttributeError:
            return getattr(self._modules["trunk"], name)

    def mean_of(self, h: Tensor) -> Tensor:
        return self.trunk.mean_of(h) if hasattr(self.trunk, "mean_of") else self.trunk.head(h)

    def forward(self, z: Tensor) -> Tensor:
        return self.trunk(z)

    def forward_with_cov(self, z: Tensor) -> tuple[Tensor, Tensor]:
        h = self.trunk.features(z)
        return self.mean_of(h), self.cov_head(h)

    def init_state(self, batch: int, device=None, dtype=None) -> Any:
        return self.trunk.init_state(batch, device=device, dtype=dtype)

    def step(self, z_t: Tensor, state: Any) -> tuple[Tensor, Any]:
        return self.trunk.step(z_t, state)

    def step_with_cov(self, z_t: Tensor, state: Any) -> tuple[Tensor, Tensor, Any]:
        h, state = self.trunk.step_features(z_t, state)
        return self.mean_of(h), self.cov_head(h), state

    def onnx_form(self) -> GaussianModel:
        """What the batch-1 ONNX graph is traced from: the head's step form (:class:`_CholeskyStepForm`)
        on the trunk's step form where the trunk has one (``models/onnx_forms.py``), the trunk itself
        elsewhere. Defined here so that the trunk's form is never taken without the head."""
        from neural_estimator.models.onnx_step import step_form

        return GaussianModel(step_form(self.trunk), self.cov_head.onnx_form())


# ---- storage ----------------------------------------------------------------------------------------
def save_head(directory: str | Path, head: CholeskyHead, info: dict[str, Any]) -> dict[str, Any]:
    """Write ``covariance_head.safetensors`` into a checkpoint directory; returns the card entry
    (``file``, ``sha256``, ``form``, ``features``, ``n`` and the given ``info``: how it was fitted,
    its calibration scale and figures). The caller puts it in the card as ``covariance_head``."""
    from safetensors.torch import save_file

    directory = Path(directory)
    tmp = directory / (HEAD_FILE + ".tmp")
    tensors = {k: v.detach().cpu().contiguous().float() for k, v in head.state_dict().items()}
    save_file(tensors, str(tmp), metadata={"format": "neural_estimator.covariance_head", "form": HEAD_FORM})
    canonical_safetensors(tmp)
    os.replace(tmp, directory / HEAD_FILE)
    return {
        "file": HEAD_FILE,
        "sha256": sha256_file(directory / HEAD_FILE),
        "form": HEAD_FORM,
        "features": head.linear.in_features,
        "n": head.n,
        **info,
    }


def load_head(directory: str | Path, entry: dict[str, Any], n: int) -> CholeskyHead:
    """The head a card's ``covariance_head`` entry describes (safetensors only; checked against the card).

    Raises:
        HeadError: a missing, corrupt or mismatched head file.
    """
    from safetensors.torch import load_file

    directory = Path(directory)
    name = entry.get("file", HEAD_FILE)
    # a regular file inside the checkpoint, within the weight-file bound: never a link followed
    open_checkpoint_file(directory, name, "covariance head file", HeadError).close()
    path = directory / name
    shrink = entry.get("shrink", 0.0)
    if isinstance(shrink, bool) or not isinstance(shrink, (int, float)) or not 0.0 <= shrink < 1.0:
        raise HeadError(f"checkpoint {directory}: the covariance head's shrink must be in [0, 1), got {shrink!r}")
    if entry.get("form", HEAD_FORM) != HEAD_FORM:
        raise HeadError(f"checkpoint {directory}: unknown covariance head form {entry.get('form')!r}")
    if entry.get("sha256") and sha256_file(path) != entry["sha256"]:
        raise HeadError(f"checkpoint {directory}: {name} does not match the sha256 in the card")
    features, n_card = int(entry.get("features", 0)), int(entry.get("n", n))
    if n_card != n or features < 1:
        raise HeadError(f"checkpoint {directory}: covariance head for n={n_card}, features={features}; model has n={n}")
    head = CholeskyHead(features, n)
    try:
        head.load_state_dict(load_file(str(path)), strict=True)
    except Exception as exc:  # safetensors and torch raise their own types
        raise HeadError(f"checkpoint {directory}: cannot read {name}: {exc}") from None
    head.shrink = float(shrink)
    return head.eval()


def attach_head(model: nn.Module, directory: str | Path, entry: dict[str, Any]) -> GaussianModel:
    """``model`` with the covariance head of its checkpoint's card entry (on the model's device and
    dtype, eval mode).

    Raises:
        EstimatorError: the head cannot be read (the message names the checkpoint and the problem).
    """
    from neural_estimator.methods.interface import EstimatorError

    n = int(getattr(model.cfg, "d_out"))
    try:
        head = load_head(directory, entry, n)
        gm = GaussianModel(model, head)
    except HeadError as exc:
        raise EstimatorError(str(exc)) from None
    p = next(model.parameters())
    return gm.to(device=p.device, dtype=p.dtype).eval()
