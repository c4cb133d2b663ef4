"""Fitting a covariance head on the frozen trunk of a trained model, and its calibration scale.

Data (validation role only, never a set a table reports; see :mod:`neural_estimator.data.protocol`):

    head set         role "val", index HEAD_INDEX, at the model's data seed     the NLL fit
    calibration set  role "val", index CALIBRATION_INDEX, same seed            the scale s

Both are whole trajectories at the scenario's horizon, run the way the model is served (its bounded
context or attention window included), with the first ``warmup`` steps left out as in training and
evaluation. The trunk runs once per set (its features are cached), so a fit costs one forward pass
and a few thousand Adam steps of a linear layer.

Steps (:func:`fit_covariance_head`):

1. features h_t and estimates x_hat_t of the served model on both sets (the estimate is the
   model's own, bit for bit);
2. errors e_t = wrap(x_hat_t - x_t) / sigma_x in normalised units;
3. the head starts from the constant covariance diag(std(e)^2) and is trained by the Gaussian NLL
   (:meth:`~neural_estimator.serving.uncertainty.heads.CholeskyHead.nll`) with Adam, minibatches of (n, t);
4. on the calibration set (trajectories the outlier rule of the metrics keeps), the scale s of
   :func:`~neural_estimator.metrics.consistency.fit_scale` (target ``band``: the smallest calibration error
   with the 95 % coverage in [0.92, 0.97]; ``coverage``: exactly 0.95) is stored in the head, and
   the set's figures before and after it are recorded (``calibrate_head``; the script's
   ``--recalibrate`` refits the scale alone).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch

from neural_estimator import metrics as M
from neural_estimator.data import protocol
from neural_estimator.methods.interface import previous_controls
from neural_estimator.serving.context import bounded_forward
from neural_estimator.metrics import consistency as C
from neural_estimator.serving.uncertainty.heads import CholeskyHead, GaussianModel

HEAD_INDEX = 101
CALIBRATION_INDEX = 102


@dataclass(frozen=True)
class FitSettings:
    head_trajectories: int = 256
    calibration_trajectories: int = 128
    steps: int = 2000
    batch: int = 8192
    lr: float = 1e-3
    weight_decay: float = 1e-4
    seed: int = 0
    scale_target: str = "band"


def served_features(est, Y: np.ndarray, U: np.ndarray, chunk: int = 64) -> tuple[torch.Tensor, np.ndarray]:
    """(features (N, T, H) float32, estimates (N, T, dx)) of the served model of ``est`` (a
    NeuralEstimator without a covariance head) over sequences Y (N, T, dy), U (N, T, du)."""
    model = est.model.trunk if isinstance(est.model, GaussianModel) else est.model
    Z, _ = est.normalizer.normalize_inputs(Y, previous_controls(U))
    feats, xs = [], []
    mean_of = model.mean_of if hasattr(model, "mean_of") else model.head
    model.eval()
    with torch.inference_mode():
        for b0 in range(0, Z.shape[0], chunk):
            z = torch.as_tensor(Z[b0 : b0 + chunk], dtype=est.dtype, device=est.device)
            if est.context_by_copies:
                h = bounded_forward(model.features, z, est.context, est.context_copies)
            else:
                h = model.features(z)
            feats.append(h.float().cpu())
            xs.append(est.normalizer.denormalize_states(mean_of(h).cpu().double().numpy()))
    return torch.cat(feats), np.concatenate(xs)


def normalised_errors(est, x: np.ndarray, x_hat: np.ndarray) -> np.ndarray:
    """e = wrap(x_hat - x) / sigma_x (N, T, dx)."""
    e = M.errors(x, x_hat, est.scenario.angle_states)
    return e / est.normalizer.out_std


def kept_trajectories(e: np.ndarray, labelled: np.ndarray | None = None) -> np.ndarray:
    """(N,) True for the trajectories the metrics' outlier rule keeps (finite, not outliers);
    ``labelled`` (N, T): each trajectory's MSE over its labelled steps (partial ground truth)."""
    with np.errstate(over="ignore", invalid="ignore"):
        if labelled is None:
            Mn = np.mean(e * e, axis=(1, 2))
        else:
            Mn = np.where(labelled[..., None], e * e, 0.0).sum(axis=(1, 2)) / np.maximum(labelled.sum(axis=1), 1)
    return ~M.outlier_mask(np.where(np.isfinite(Mn), Mn, np.inf))


def train_head(h: torch.Tensor, e: torch.Tensor, settings: FitSettings, log=None) -> tuple[CholeskyHead, list[float]]:
    """A Cholesky head fitted by the Gaussian NLL to errors e (K, n) at features h (K, H)."""
    torch.manual_seed(settings.seed)
    head = CholeskyHead(h.shape[-1], e.shape[-1])
    head.init_constant(e.std(dim=0).clamp_min(1e-8))
    opt = torch.optim.AdamW(head.parameters(), lr=settings.lr, weight_decay=settings.weight_decay)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, settings.steps)
    gen = torch.Generator().manual_seed(settings.seed)
    K = h.shape[0]
    history = []
    head.train()
    for it in range(settings.steps):
        idx = torch.randint(0, K, (min(settings.batch, K),), generator=gen)
        loss = head.nll(h[idx], e[idx])
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        if it % 250 == 0 or it == settings.steps - 1:
            history.append(float(loss.detach()))
            if log:
                log(f"  step {it:5d}  NLL {history[-1]:.4f}")
    return head.eval(), history


def nees_of(head: CholeskyHead, h: torch.Tensor, e: np.ndarray, batch: int = 1 << 15) -> np.ndarray:
    """(K,) NEES of normalised errors e (K, n) under the head's covariances at features h (K, H)."""
    out = np.empty(e.shape[0])
    with torch.inference_mode():
        for b0 in range(0, e.shape[0], batch):
            cov = head(h[b0 : b0 + batch]).double().numpy()
            out[b0 : b0 + batch] = M.nees(e[None, b0 : b0 + batch], cov[None])[0]
    return out


def figures(eps: np.ndarray, dx: int) -> dict[str, float]:
    """Consistency figures of NEES values: median and mean NEES / dx, 95 % coverage, calibration error."""
    curve = C.coverage_curve(eps, dx)
    finite = eps[np.isfinite(eps)]
    return {
        "nees_median_per_dim": float(np.median(eps) / dx),
        "nees_mean_per_dim": float(finite.mean() / dx) if finite.size else float("inf"),
        "coverage95": float(curve[C.RELIABILITY_LEVELS.index(0.95)]),
        "calibration_error": C.calibration_error(curve),
    }


def _set(
    est, name: str, index: int, n: int, log=None, t0: float = 0.0, data=None
) -> tuple[torch.Tensor, np.ndarray, int]:
    """(features (K, H), normalised errors (K, dx), kept trajectories) of one validation set (or of
    recorded trajectories ``data``), the warm-up left out, the trajectories the metrics' outlier
    rule keeps only."""
    dx = est.scenario.dx
    seed = int((est.card.get("data") or {}).get("seed", 0))
    warmup = est.untrained_steps
    where = f"val index {index}" if data is None else "recorded data"
    if data is None:
        data = protocol.dataset(est.scenario, "val", index, n, seed=seed)
    h, x_hat = served_features(est, data.y, data.u)
    e = normalised_errors(est, data.x, x_hat)
    lab = getattr(data, "labelled", None)  # partial ground truth: no error where there is no truth
    keep = kept_trajectories(e, lab)
    if log:
        log(f"  {name} set: {where}, {keep.sum()}/{len(keep)} trajectories kept, {time.time() - t0:.0f} s")
    if lab is None:
        return h[keep, warmup:].reshape(-1, h.shape[-1]), e[keep, warmup:].reshape(-1, dx), int(keep.sum())
    sel = np.zeros(lab.shape, dtype=bool)
    sel[keep, warmup:] = True
    sel &= lab
    return h[torch.as_tensor(sel)], e[sel], int(keep.sum())


def calibrate_head(
    est, head: CholeskyHead, settings: FitSettings = FitSettings(), log=None, data=None
) -> dict[str, Any]:
    """Fit the head's calibration scale s on the calibration set (or recorded trajectories ``data``;
    its NEES with s = 1), store it in ``head.scale`` and return the card's ``calibration`` entry
    (scale, target, figures before and after)."""
    n = settings.calibration_trajectories
    h, e, kept = _set(est, "calibration", CALIBRATION_INDEX, n, log, time.time(), data)
    head.scale.fill_(1.0)
    eps = nees_of(head, h, e)
    dx = est.scenario.dx
    scale = C.fit_scale(eps, dx, settings.scale_target)
    head.scale.fill_(scale)
    return {
        "scale": scale,
        "target": settings.scale_target,
        "set": {"role": "val", "index": CALIBRATION_INDEX, "kept": kept} if data is None else {"recorded": kept},
        "before": figures(eps, dx),
        "after": figures(eps / scale, dx),
    }


def fit_covariance_head(
    est, settings: FitSettings = FitSettings(), log=None, head_data=None, calibration_data=None
) -> tuple[CholeskyHead, dict[str, Any]]:
    """Fit a head (and its calibration scale) for the served model ``est`` (module docstring).

    ``head_data``, ``calibration_data``: recorded trajectories (a robot's held-out data, see
    docs/robot.md) in place of the scenario's validation sets 101 and 102.

    Returns:
        The head and the card entry's ``fit`` information (sets, settings, NLL history, the
        calibration scale and the calibration set's figures before and after it).
    """
    t0 = time.time()
    seed = int((est.card.get("data") or {}).get("seed", 0))
    h_fit, e_fit, n_fit = _set(est, "head", HEAD_INDEX, settings.head_trajectories, log, t0, head_data)
    head, history = train_head(h_fit, torch.as_tensor(e_fit, dtype=torch.float32), settings, log)
    calibration = calibrate_head(est, head, settings, log, calibration_data)
    recorded = head_data is not None
    info = {
        "fitted_on": {
            "head": {"recorded": n_fit}
            if recorded
            else {"role": "val", "index": HEAD_INDEX, "seed": seed, "trajectories": settings.head_trajectories},
            "calibration": {"recorded": calibration["set"].get("recorded")}
            if calibration_data is not None
            else {"role": "val", "index": CALIBRATION_INDEX, "seed": seed},
            "horizon": est.scenario.horizon,
            "warmup": est.untrained_steps,
            "context": est.context,
        },
        "settings": asdict(settings),
        "nll_history": history,
        "calibration": calibration,
        "seconds": round(time.time() - t0, 1),
    }
    return head, info


SHRINK_INDEX = 103
SHRINK_GRID = (0.0, 0.001, 0.003, 0.01, 0.03, 0.1)


def choose_shrink(est, head: CholeskyHead, n: int = 1000, log=None) -> dict[str, Any]:
    """The smallest correlation shrinkage rho of :data:`SHRINK_GRID` whose mean NEES / dx on a larger
    validation set (role "val", index :data:`SHRINK_INDEX`, ``n`` trajectories) is within
    :data:`~neural_estimator.metrics.consistency.NEES_BAND` (the last one if none is); returns the card's
    ``shrink`` record with every candidate's figures. ``head.shrink`` is left at the choice."""
    h, e, kept = _set(est, "shrink", SHRINK_INDEX, n, log, time.time())
    dx, tried = est.scenario.dx, []
    for rho in SHRINK_GRID:
        head.shrink = rho
        tried.append({"shrink": rho, **figures(nees_of(head, h, e), dx)})
    ok = [t for t in tried if C.NEES_BAND[0] <= t["nees_mean_per_dim"] <= C.NEES_BAND[1]]
    best = ok[0] if ok else tried[-1]
    head.shrink = best["shrink"]
    return {"value": best["shrink"], "set": {"role": "val", "index": SHRINK_INDEX, "kept": kept}, "candidates": tried}
