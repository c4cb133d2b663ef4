"""Training a hybrid (the scenario's f and h with a learned part: KalmanNet), the paper's recipe
adapted to a filter that must run from its prior.

A network of :mod:`neural_estimator.training.loop` reads any window of a trajectory from scratch; a
hybrid is a filter: its estimate at step k carries everything since k = 0, and it starts at the
prior mean m0 as it is served. So it trains on whole trajectories by truncated backpropagation
through time (TBPTT):

1. Each epoch takes every training trajectory once, in a random order (the run's numpy Generator,
   saved in the resume state), in batches of ``batch_size`` trajectories: 4,000 x 500 steps at
   20:1, the paper's 20,000 windows of 100 steps.
2. A batch runs from the prior (``model.init_state``) over its whole length in chunks of ``window``
   steps (100); after each chunk: loss, backward, clip, AdamW step, and the filter's state carried
   into the next chunk detached (gradients never reach back past a chunk). 63 batches x 5 chunks =
   315 optimiser steps per epoch at 20:1 (the networks: 313).
3. The loss of a chunk, with the warm-up (``warmup`` steps) counted from k = 0 only, where the
   filter starts from its prior (a later chunk continues a filter, it does not start one):

   - ``supervision="states"`` (the paper's): the networks' loss on the normalised state error,
     angles wrapped, components weighted by ``loss_units``
     (:func:`~neural_estimator.training.loss.weighted_loss`), labelled steps only;
   - ``supervision="observations"`` (KalmanNet's unsupervised loss; Revach et al., "Unsupervised
     Learned Kalman Filtering", EUSIPCO 2022): the mean square of the normalised residual of the
     next observation predicted before it is read, y_k - h(x_{k|k-1}) (angular observations
     wrapped; :meth:`~neural_estimator.models.kalmannet.KalmanNetModel.obs_residual_norm`). No state
     is read: a robot without motion capture can train it.

   An observation-trained hybrid takes its state statistics (its units and its guard's range)
   from 500 trajectories simulated from the model, not from the data's states
   (:func:`neural_estimator.training.observations.observation_normalizer`).
4. Validation: every validation trajectory from the prior over its full length in eval mode, the
   same kind of loss over steps t >= warmup (so an observation-trained model also selects its
   checkpoint without a state label). Scheduler, early stopping, checkpoints, the resume state and
   the card are the networks' (:class:`~neural_estimator.training.loop._Run`); the card records
   ``training.supervision``.
"""

from __future__ import annotations

import math

import torch

from neural_estimator.training.loop import _bar, _Run
from neural_estimator.training.loss import weighted_loss


class HybridRun(_Run):
    """One training run of a hybrid: the networks' run (optimiser, scheduler, stopping, resume,
    checkpoints, card) with the epoch and the validation of TBPTT from the prior (module docstring)."""

    def __init__(self, scenario, arch, window_key, sets, out_dir, device):
        super().__init__(scenario, arch, window_key, sets, out_dir, device)
        cfg = self.cfg
        self.observations = cfg.supervision == "observations"
        self.model.set_normalization(sets.norm)  # z -> physical y, u; physical x -> normalised (saved)
        self.steps_per_epoch = math.ceil(sets.n_train / cfg.batch_size)  # batches of whole trajectories
        self.chunks = math.ceil(cfg.train_length / cfg.window)
        self.n_windows = sets.n_train * self.chunks  # the windows an epoch trains on (the card's count)

    # ---- the loss of one chunk ----------------------------------------------------------------------
    def chunk_loss(self, x_n, y_pred_n, z, x, t0: int, labels) -> torch.Tensor:
        """The loss of steps t0 .. t0 + L - 1 (module docstring, 3); steps t < warmup weigh 0."""
        t = torch.arange(t0, t0 + z.shape[1], device=z.device)
        w = (t >= self.cfg.warmup).to(z.dtype).expand(z.shape[0], -1)  # (B, L)
        if self.observations:
            r2 = self.model.obs_residual_norm(y_pred_n, z).square().mean(dim=-1)  # (B, L)
            return (w * r2).sum() / w.sum().clamp_min(1.0)
        if labels is not None:  # partial ground truth: the labelled steps only
            w = w * labels
        if not bool(w.sum() > 0):
            return 0.0 * x_n.sum()  # no labelled step: a zero gradient, not 0 / 0
        return weighted_loss(x_n, x, w, self.angle_mask, self.comp_w)

    # ---- one epoch ------------------------------------------------------------------------------------
    def train_epoch(self, progress: bool) -> float:
        """Every training trajectory once, by TBPTT in chunks of ``window`` steps; the mean chunk loss."""
        cfg, model, sets = self.cfg, self.model, self.sets
        model.train()
        order = self.rng.permutation(sets.n_train)
        total, count = 0.0, 0
        inner = _bar(
            self.steps_per_epoch, progress, f"{self.scenario.name}/{self.arch} epoch {self.state['epoch'] + 1} training"
        )
        gov = self.threads
        for b in range(self.steps_per_epoch):
            rows = torch.as_tensor(order[b * cfg.batch_size : (b + 1) * cfg.batch_size], device=self.device)
            z_all, x_all = sets.Z_train[rows], (None if self.observations else sets.X_train[rows])
            labels = None if sets.L_train is None else sets.L_train[rows]
            state = model.init_state(z_all.shape[0])
            for t0 in range(0, z_all.shape[1], cfg.window):
                if gov is not None:
                    gov.before_step()
                z = z_all[:, t0 : t0 + cfg.window]
                x_n, y_pred_n, state = model.rollout(z, state)
                x = None if x_all is None else x_all[:, t0 : t0 + cfg.window]
                lab = None if labels is None else labels[:, t0 : t0 + cfg.window]
                loss = self.chunk_loss(x_n, y_pred_n, z, x, t0, lab)
                value = self.optimizer_step(loss, f"batch {b + 1}, step {t0}")
                if gov is not None:
                    gov.after_step()
                state = tuple(s.detach() for s in state)  # truncated: the next chunk continues the filter
                total += value
                count += 1
            inner.update(1)
            inner.set_postfix_str(f"loss {total / max(count, 1):.4g}")
        inner.close()
        return total / max(count, 1)

    @torch.no_grad()
    def estimate_loss(self, bar) -> float:
        """L_val: the chunk loss over whole validation trajectories from the prior, t >= warmup."""
        cfg, model, sets = self.cfg, self.model, self.sets
        model.eval()
        bar.set_description_str(f"{self.scenario.name}/{self.arch} epoch {self.state['epoch'] + 1} validation")
        total, weight = 0.0, 0.0
        for b0 in range(0, sets.Z_val.shape[0], cfg.val_batch_size):
            z = sets.Z_val[b0 : b0 + cfg.val_batch_size]
            x_n, y_pred_n, _ = model.rollout(z, model.init_state(z.shape[0]))
            x = None if self.observations else sets.X_val[b0 : b0 + cfg.val_batch_size]
            labels = None if sets.L_val is None else sets.L_val[b0 : b0 + cfg.val_batch_size]
            n = self._scored(z, labels)
            total += float(self.chunk_loss(x_n.double(), y_pred_n.double(), z.double(), _double(x), 0, labels)) * n
            weight += n
            bar.update(1)
        model.train()
        return total / weight if weight else math.inf

    def _scored(self, z: torch.Tensor, labels) -> float:
        """How many (trajectory, step) pairs the validation loss of a batch averages over."""
        steps = max(z.shape[1] - self.cfg.warmup, 0)
        if self.observations or labels is None:
            return float(z.shape[0] * steps)
        return float(labels[:, self.cfg.warmup :].sum())

    def card(self, metrics=None):
        card = super().card(metrics)
        training = card["training"]
        if self.observations:
            training["loss"] = (
                "mean over steps t >= warmup (from k = 0) of the normalised squared residual of the next "
                "observation predicted before it is read, y_k - h(x_{k|k-1}) (angular observations wrapped): "
                "no state label read"
            )
            training["validation"] = "the same over full-length validation trajectories from the prior, eval mode"
        else:
            training["loss"] += "; whole trajectories from the prior by TBPTT, warm-up from k = 0 only"
            training["validation"] = (
                f"mean e^2 over full-length validation trajectories from the prior, t >= {self.cfg.warmup}, eval mode"
            )
        training["tbptt"] = {"chunk": self.cfg.window, "chunks_per_trajectory": self.chunks}
        return card


def _double(x):
    return None if x is None else x.double()


__all__ = ["HybridRun"]
