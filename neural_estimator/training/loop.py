"""Training a neural estimator with the paper's protocol, readable top to bottom.

Paper, "Neural Estimators and Training": "Inputs are noisy observations, while supervised targets
are clean simulator states." "The default training setting uses a data-to-parameter ratio of
approximately 20:1 ... Training samples are random length-100 sub-trajectories extracted from
longer trajectories of length 500. Each training dataset has an independent validation set of
8,000 trajectories for early stopping. Because chunking samples interior and endpoint timesteps with
different frequencies, we weight each timestep loss by the inverse of its sampling frequency."
Appendix "Hyperparameter Details": "AdamW with learning rate 2e-3, weight decay 1e-5, and gradient
clipping with maximum norm 1.0. A ReduceLROnPlateau scheduler with decay factor 0.5 and patience 3
... up to 500 epochs with batch size 64. Early stopping with patience 30 is applied based on
validation performance. The first 10 timesteps are ignored during loss computation as a warmup
period, and validation is performed after each epoch."

What :func:`train` does, in order:

1. Data (:mod:`neural_estimator.data.protocol`, cached): training set ``data_index`` of
   ``data_seed`` (length-500 trajectories holding ratio x 100k steps: 20:1 -> 4,000 x 500) and its
   validation set (8,000 x 500).
2. Normalisation statistics from the training set (:mod:`~neural_estimator.serving.normalization`).
3. The model, initialised under ``torch.manual_seed(init_seed)``, or from a trained checkpoint's
   weights with ``init_from`` (fine-tuning; :mod:`~neural_estimator.training.warm_start`).
4. Each epoch: ``windows_per_epoch`` random length-100 windows (default: as many as make the
   training set's timesteps once, 20,000 at 20:1) in batches of 64. Loss, with e = x_hat_n - x_n the
   error in normalised units (angular components wrapped to (-pi, pi], as the metrics wrap them)
   and w_bt = inverse sampling frequency of the window's timestep x warm-up mask
   (``ChunkSampler.loss_weights``):

       L_train = sum_{b,t,d} w_bt c_d e_btd^2 / (sum_d c_d sum_{b,t} w_bt)

   with c_d the component weights of ``loss_units`` (:func:`component_weights`): "state" (the
   default) c_d = sigma_d^2 / mean(sigma^2), the squared error in the states' own units up to one
   constant, as RMSE weighs the components; "normalised" c_d = 1. Recorded data with partial
   ground truth (``Trajectories.labelled`` m_bt): w_bt m_bt instead of w_bt, here and in L_val's
   mean (labelled steps only), and the state normalisation fitted on labelled steps.

5. Validation after each epoch (the paper does not define it; this is our definition): the model
   in eval mode runs every validation trajectory from t = 0 over its full length (500) and

       L_val = mean of c_d e_ntd^2 over trajectories n, timesteps t >= warm-up (10), components d
               (c_d scaled to mean 1).

   Full trajectories rather than windows: every timestep appears once, so no sampling weights are
   needed, and the model is judged the way it is evaluated, run from the start over a horizon five
   times its training windows, so early stopping favours stable filtering over short-window fit.
   Both losses estimate the same per-timestep normalised MSE.
6. ReduceLROnPlateau on L_val; the best model (lowest L_val so far) is written as a checkpoint
   (``model.safetensors`` + ``card.json``) in ``out_dir``; training stops after ``patience`` epochs
   without a strictly lower L_val, or at ``epochs``.
7. After every epoch a ``resume/`` directory holds everything needed to continue bit-for-bit:
   model, AdamW state, scheduler, RNG states, epoch, best, history (safetensors + JSON, no pickle).
   ``resume=True`` continues from it; a larger ``epochs`` extends a finished run.
8. The best model is rebuilt from its checkpoint and, if ``eval_trajectories`` > 0, measured on
   evaluation set 0 with :func:`neural_estimator.metrics.compute_metrics`; the card is completed,
   and its batch-1 step is exported beside it as ``step.onnx``
   (:func:`neural_estimator.serving.export.export_beside`), which the estimator nodes serve without torch.

Randomness: ``init_seed`` fixes the initial weights and dropout (torch's global RNG) and the window
draws (a numpy Generator); the data depend on ``data_seed`` and ``data_index`` only. On CPU two runs
with the same config give bit-identical weights, and an interrupted run resumed gives the weights of
an uninterrupted one. On CUDA the same holds up to nondeterministic kernels (cuDNN RNNs, atomics).
"""

from __future__ import annotations

import dataclasses
import math
import shutil
import time
from pathlib import Path
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from tqdm.auto import tqdm

from neural_estimator.data.protocol import ChunkSampler, dataset, training_trajectories
from neural_estimator.training.recipe import TrainConfig, TrainingError
from neural_estimator.training.recorded import recorded_sets
from neural_estimator.training.step import check_skipped, guarded_step
from neural_estimator.data.simulate import Trajectories, trajectories_digest
from neural_estimator.methods import table
from neural_estimator.methods.interface import check_method, previous_controls
from neural_estimator.metrics import EVALUATION_WARMUP, compute_labelled_metrics, to_json
from neural_estimator.models import ARCHITECTURES, build_model
from neural_estimator.models.onnx_step import OnnxError
from neural_estimator.serving.export import export_beside
from neural_estimator.serving.checkpoint import load_checkpoint, save_checkpoint
from neural_estimator.serving.context import bounded_forward
from neural_estimator.serving.neural import NeuralEstimator, resolve_device
from neural_estimator.serving.normalization import Normalizer
from neural_estimator.scenarios import Scenario, make_scenario
from neural_estimator.scenarios.model import model_scenario
from neural_estimator.training.loss import component_weights, state_error, weighted_loss
from neural_estimator.training.resume import RESUME_DIR, load_resume, save_resume
from neural_estimator.training.stopping import converged, lr_reductions
from neural_estimator.training.warm_start import warm_start
from neural_estimator.training.threads import ThreadGovernor


def train(
    scenario: Scenario | str,
    arch: str,
    out_dir: str | Path,
    config: TrainConfig | None = None,
    progress: bool = True,
    deadline: float | None = None,
    data: tuple[Trajectories, Trajectories] | None = None,
    stop_when: Callable[[list[dict[str, Any]]], str | None] | None = None,
    threads: ThreadGovernor | None = None,
) -> Path:
    """Train ``arch`` on ``scenario`` and write the best model as a checkpoint in ``out_dir``.

    Args:
        scenario: a scenario instance (its constants are recorded) or a registered name.
        arch: gru, lstm, gpt2, filterformer, mamba or mamba2.
        out_dir: the checkpoint directory (``model.safetensors``, ``card.json``, ``resume/``).
        config: the recipe (default: the paper's).
        progress: show progress bars: epochs (losses, learning rate), and inside each epoch the
            training batches (windows/s, time left) and the validation batches.
        deadline: a ``time.time()`` after which no new epoch starts; the run then returns with its
            resume state saved and the card marked "in progress" (no final evaluation). The zoo
            script uses it to spread training over several runs.
        data: (training, validation) trajectories to train on instead of simulating the scenario's
            (recorded data, with a :class:`~neural_estimator.robot.DataScenario`): the recipe's
            trajectories, train_length and val_trajectories then come from these sets, the card
            records their SHA-256, and the card's metrics are computed on the validation set.
        stop_when: called with the run's history after every epoch; a string it returns ends the
            run as early stopping does, with that string as the card's ``stopped`` (the zoo's
            :func:`plateau_rule`). Run control like ``deadline``, not part of the recipe.
        threads: chooses the thread count of each training step by measurement
            (:class:`~neural_estimator.training.threads.ThreadGovernor`); None: the count torch has.

    Returns ``out_dir``.
    """
    cfg = config or TrainConfig()
    if isinstance(scenario, str):
        scenario = make_scenario(scenario)
    arch, window_key = _checked_arch(arch, cfg)
    device = resolve_device(cfg.device)
    sets = _training_sets(scenario, cfg, data, device, progress)
    # a method with a recipe of its own names its run in the table (a hybrid: training/hybrid.py)
    run_class = table.resolve(table.spec(arch).training_run) if table.spec(arch).training_run else _Run
    run = run_class(scenario, arch, window_key, sets, Path(out_dir), device)
    run.threads = threads
    if _resuming(sets.cfg, run.out_dir):
        run.resume(stop_when)
    bar = _bar(sets.cfg.epochs, progress, f"{scenario.name}/{arch}", initial=run.state["epoch"], position=0)
    while run.state["epoch"] < sets.cfg.epochs and run.state["stopped"] is None:
        if deadline is not None and time.time() >= deadline:
            bar.close()  # out of time: the resume state and the best checkpoint so far stay for the next run
            return run.out_dir
        run.epoch(stop_when, progress, bar)
    bar.close()
    run.finish()
    return run.out_dir


# ---- what train() does, in order ----------------------------------------------------------------------
def _resuming(cfg: TrainConfig, out_dir: Path) -> bool:
    """Whether the run continues from ``out_dir/resume`` (``resume`` set and a resume state there)."""
    return cfg.resume and (Path(out_dir) / RESUME_DIR / "state.json").is_file()


def _checked_arch(arch: str, cfg: TrainConfig) -> tuple[str, str | None]:
    """(architecture, its attention-window hyperparameter or None); the recipe's one-line errors
    before any data are simulated."""
    arch = check_method(arch)
    if not table.has(arch, trainable=True):
        raise TrainingError(f"{arch!r} is a classical filter; train one of: {', '.join(table.names(trainable=True))}")
    window_key = table.spec(arch).window_key  # the attention models bound their context by their window
    if cfg.val_context and window_key and cfg.model_overrides.get(window_key, cfg.val_context) != cfg.val_context:
        raise TrainingError(
            f"val_context={cfg.val_context} sets {arch}'s attention window {window_key}, "
            f"which the model overrides set to {cfg.model_overrides[window_key]}: give one of them"
        )
    if cfg.supervision == "observations" and not table.has(arch, family="hybrid"):
        raise TrainingError(
            f"supervision 'observations' trains a hybrid through the system's h; {arch} learns from states"
        )
    if cfg.model_set and not table.has(arch, family="hybrid"):
        raise TrainingError(f"a model set gives a hybrid its f and h; {arch} reads no model, only the data")
    known = {f.name for f in dataclasses.fields(ARCHITECTURES[arch][0])} - {"d_in", "d_out"}
    unknown = sorted(set(cfg.model_overrides) - known)
    if unknown:
        raise TrainingError(f"{arch} has no hyperparameter(s) {unknown}; valid: {sorted(known)}")
    return arch, window_key


@dataclasses.dataclass
class _Sets:
    """The run's data: training and validation sets normalised, as tensors on the run's device."""

    cfg: TrainConfig  # the recipe, with the counts and lengths the data set
    norm: Normalizer
    Z_train: torch.Tensor  # (N, T, d_in) normalised inputs [y_k, u_{k-1}]
    X_train: torch.Tensor  # (N, T, dx) normalised states
    Z_val: torch.Tensor
    X_val: torch.Tensor
    n_train: int
    recorded: dict[str, str] | None  # the SHA-256 of recorded sets, None for simulated ones
    eval_data: Trajectories | None  # recorded data: the card's metrics on the validation set
    L_train: torch.Tensor | None = None  # (N, T) float 1/0: steps with ground truth (None: all)
    L_val: torch.Tensor | None = None


def _training_sets(
    scenario: Scenario, cfg: TrainConfig, data: tuple[Trajectories, Trajectories] | None, device, progress: bool
) -> _Sets:
    """Step 1-2: the training and validation sets (given, or simulated and cached) and the
    normalisation statistics of the training set."""
    if data is not None:
        cfg, train_data, val_data = recorded_sets(scenario, cfg, data)
        recorded = {"train_sha256": trajectories_digest(train_data), "val_sha256": trajectories_digest(val_data)}
        n_train = train_data.n
    else:
        longest = scenario.longest_training_trajectory
        if longest is not None and cfg.train_length > longest:  # e.g. the quadrotor: flights past its horizon
            if progress:
                print(
                    f"{scenario.name}: training trajectories of {longest} steps, not {cfg.train_length} "
                    "(longer ones are not informative for this scenario)",
                    flush=True,
                )
            cfg = dataclasses.replace(cfg, train_length=longest)
        recorded = None
        n_train = int(cfg.trajectories or training_trajectories(cfg.data_ratio, length=cfg.train_length))
        cache = cfg.cache_dir
        train_data = dataset(scenario, "train", cfg.data_index, n_train, cfg.train_length, cfg.data_seed, cache)
        val_data = dataset(
            scenario, "val", cfg.data_index, cfg.val_trajectories, cfg.train_length, cfg.data_seed, cache
        )
    if cfg.supervision == "observations":  # no state label read: the states' statistics are the model's
        from neural_estimator.training.observations import observation_normalizer

        norm = observation_normalizer(scenario, train_data, cfg)
    else:
        norm = Normalizer.from_data(scenario, train_data)

    def as_tensors(data) -> tuple[torch.Tensor, torch.Tensor]:
        z, _ = norm.normalize_inputs(data.y, previous_controls(data.u))  # (N, T, d_in)
        x = norm.normalize_states(data.x)  # (N, T, dx)
        return (
            torch.as_tensor(z, dtype=torch.float32, device=device),
            torch.as_tensor(x, dtype=torch.float32, device=device),
        )

    def label_mask(data) -> torch.Tensor | None:  # partial ground truth: the loss reads labelled steps only
        lab = getattr(data, "labelled", None)
        return None if lab is None else torch.as_tensor(lab, dtype=torch.float32, device=device)

    Z_train, X_train = as_tensors(train_data)
    Z_val, X_val = as_tensors(val_data)
    eval_data = val_data if recorded is not None else None
    L_train, L_val = label_mask(train_data), label_mask(val_data)
    return _Sets(cfg, norm, Z_train, X_train, Z_val, X_val, n_train, recorded, eval_data, L_train, L_val)


def _bar(total: int, progress: bool, desc: str | None = None, initial: int = 0, position: int = 1, **kw):
    """A tqdm bar: epochs (position 0), or the batches inside one epoch (position 1, not left behind)."""
    unit = "epoch" if position == 0 else "batch"
    extra = {} if position == 0 else {"leave": False}
    if desc is not None:
        extra["desc"] = desc
    kw = {"total": total, "initial": initial, "unit": unit, "position": position, "dynamic_ncols": True, **extra, **kw}
    return tqdm(disable=None if progress else True, **kw)


class _Run:
    """Steps 3-8 of one training run: the model, its optimiser and scheduler, the window draws, and
    the run's record (``state``: epoch, best, history; what the resume state holds)."""

    def __init__(self, scenario: Scenario, arch: str, window_key: str | None, sets: _Sets, out_dir: Path, device):
        cfg = sets.cfg
        self.scenario, self.arch, self.window_key, self.sets, self.cfg = scenario, arch, window_key, sets, cfg
        self.out_dir, self.device = out_dir, device
        self.sampler = ChunkSampler(sets.n_train, cfg.train_length, cfg.window, cfg.warmup)
        self.n_windows = int(cfg.windows_per_epoch or math.ceil(sets.n_train * cfg.train_length / cfg.window))
        self.steps_per_epoch = math.ceil(self.n_windows / cfg.batch_size)
        self.angle_mask = torch.zeros(scenario.dx, dtype=torch.bool, device=device)
        self.angle_mask[list(scenario.angle_states)] = True
        self.comp_w = component_weights(cfg.loss_units, sets.norm.out_std, device)  # None: normalised units
        self.window_cols = np.arange(cfg.window)
        # step 3: the model under torch.manual_seed(init_seed) (initial weights and dropout)
        torch.manual_seed(cfg.init_seed)
        overrides = {**cfg.model_overrides, **({window_key: cfg.val_context} if cfg.val_context and window_key else {})}
        self.system = model_scenario(scenario, cfg.model_set)  # the f and h a hybrid runs (a model set: not the data's)
        self.model = build_model(arch, self.system, **overrides).to(device)
        self.optimizer = torch.optim.AdamW(self.model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
        self.scheduler = torch.optim.lr_scheduler.ReduceLROnPlateau(
            self.optimizer, mode="min", factor=cfg.lr_factor, patience=cfg.lr_patience
        )
        self.rng = np.random.default_rng(np.random.SeedSequence(cfg.init_seed, spawn_key=(1,)))  # window draws
        self.threads: ThreadGovernor | None = None  # run control (train()'s threads), not part of the recipe
        self.state: dict[str, Any] = {
            "epoch": 0,
            "best": math.inf,
            "best_epoch": 0,
            "bad_epochs": 0,
            "stopped": None,
            "history": [],
        }
        # a warm start (fine-tuning): a trained checkpoint's weights instead of the fresh ones, before a
        # hybrid's run sets its normalisation; its record travels in the run record (and so the resume
        # state), and a run that resumes takes it from there: the checkpoint may have changed since
        if cfg.init_from and not _resuming(cfg, out_dir):
            self.state["init_from"] = warm_start(self.model, cfg.init_from, self.system, sets.norm)
        self.identity = {
            "scenario": scenario.describe(),
            "arch": arch,
            "config": cfg.recipe(),
            **({"recorded": sets.recorded} if sets.recorded else {}),
        }

    def resume(self, stop_when) -> None:
        """Step 7: continue from ``resume/``, bit for bit."""
        run = self.state = load_resume(
            self.out_dir / RESUME_DIR, self.identity, self.model, self.optimizer, self.scheduler, self.rng
        )
        if run["stopped"] and run["stopped"].startswith("early stopping"):
            if run["bad_epochs"] < self.cfg.patience:
                run["stopped"] = None  # resumed with a larger patience: early stopping no longer applies
        elif run["stopped"] and stop_when is None:
            run["stopped"] = None  # stopped by a stop_when rule that this run does not apply

    # ---- one epoch: get a batch, estimate the loss, step; validate; checkpoint ----
    def get_batch(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        idx, start = self.sampler.sample(self.rng, self.cfg.batch_size)  # (B,), (B,)
        rows = torch.as_tensor(idx[:, None], device=self.device)  # (B, 1)
        cols = torch.as_tensor(start[:, None] + self.window_cols[None, :], device=self.device)  # (B, L)
        w = torch.as_tensor(self.sampler.loss_weights(start), dtype=torch.float32, device=self.device)  # (B, L)
        if self.sets.L_train is not None:  # unlabelled steps: weight 0 (their x is a placeholder)
            w = w * self.sets.L_train[rows, cols]
        return self.sets.Z_train[rows, cols], self.sets.X_train[rows, cols], w

    def epoch(self, stop_when, progress: bool, bar) -> None:
        """Step 4-7: one epoch of training, its validation, the scheduler, the best checkpoint, the
        stopping rules and the resume state."""
        t0, self.skipped, self.attempted = time.perf_counter(), 0, 0
        train_loss = self.train_epoch(progress)
        check_skipped(self.skipped, self.attempted, self.state["epoch"] + 1, self.out_dir / RESUME_DIR)
        inner = _bar(math.ceil(self.sets.Z_val.shape[0] / self.cfg.val_batch_size), progress)
        val_loss = self.estimate_loss(inner)
        inner.close()
        self.scheduler.step(val_loss)
        run = self.state
        run["epoch"] += 1
        lr = self.optimizer.param_groups[0]["lr"]
        run["history"].append(
            {
                "epoch": run["epoch"],
                "train_loss": train_loss,
                "val_loss": val_loss,
                "lr": lr,
                "seconds": round(time.perf_counter() - t0, 3),
                **({"skipped_steps": self.skipped} if self.skipped else {}),
            }
        )
        if val_loss < run["best"]:
            run["best"], run["best_epoch"], run["bad_epochs"] = val_loss, run["epoch"], 0
            save_checkpoint(self.out_dir, self.model, self.sets.norm, self.card())
        else:
            run["bad_epochs"] += 1
            if run["bad_epochs"] >= self.cfg.patience:
                run["stopped"] = f"early stopping: no lower validation loss in {self.cfg.patience} epochs"
        if run["stopped"] is None and stop_when is not None:
            run["stopped"] = stop_when(run["history"])
        save_resume(self.out_dir / RESUME_DIR, self.identity, run, self.model, self.optimizer, self.scheduler, self.rng)
        bar.update(1)
        bar.set_postfix(
            {"train": f"{train_loss:.4g}", "val": f"{val_loss:.4g}", "best": f"{run['best']:.4g}", "lr": f"{lr:.2g}"}
        )

    def train_epoch(self, progress: bool) -> float:
        """Step 4: ``steps_per_epoch`` batches of windows; the mean training loss."""
        cfg, model, steps = self.cfg, self.model, self.steps_per_epoch
        model.train()
        train_loss = 0.0
        inner = _bar(  # inside the epoch: batches of windows, then validation batches (rate and time left)
            steps, progress, f"{self.scenario.name}/{self.arch} epoch {self.state['epoch'] + 1} training"
        )
        gov = self.threads
        for it in range(steps):
            if gov is not None:
                gov.before_step()
            z, x, w = self.get_batch()
            pred = model(z)
            if self.sets.L_train is not None and not bool(w.sum() > 0):  # a batch with no labelled step
                loss = 0.0 * pred.sum()  # no information: a zero gradient, not 0 / 0
            else:
                loss = weighted_loss(pred, x, w, self.angle_mask, self.comp_w)
            loss_value = self.optimizer_step(loss, f"step {it + 1}")
            if gov is not None:
                gov.after_step()
            train_loss += loss_value
            inner.update(1)
            if it % 10 == 9 or it == steps - 1:
                inner.set_postfix_str(
                    f"{cfg.batch_size * inner.n / max(inner.format_dict['elapsed'], 1e-9):.0f} windows/s, "
                    f"loss {train_loss / (it + 1):.4g}"
                )
        inner.close()
        return train_loss / steps

    def optimizer_step(self, loss: torch.Tensor, where: str) -> float:
        """One AdamW step on ``loss`` (training.step); its value, or a TrainingError where it is not finite."""
        value = loss.item()
        if not math.isfinite(value):
            raise TrainingError(
                f"training loss is {value} at epoch {self.state['epoch'] + 1}, {where}; the run diverged "
                f"(a lower --lr may help; the last good state is in {self.out_dir / RESUME_DIR})"
            )
        self.attempted += 1
        self.skipped += not guarded_step(loss, self.model, self.optimizer, self.cfg.grad_clip)
        return value

    @torch.no_grad()
    def estimate_loss(self, bar) -> float:
        """Step 5: L_val over the full-length validation trajectories, eval mode."""
        cfg, model, Z_val, X_val = self.cfg, self.model, self.sets.Z_val, self.sets.X_val
        model.eval()
        total, count = 0.0, 0
        bar.set_description_str(f"{self.scenario.name}/{self.arch} epoch {self.state['epoch'] + 1} validation")
        for b0 in range(0, Z_val.shape[0], cfg.val_batch_size):
            z = Z_val[b0 : b0 + cfg.val_batch_size]
            if cfg.val_context and not self.window_key:
                pred = bounded_forward(model, z, cfg.val_context, cfg.val_context_copies)
            else:  # an attention model's window, val_context when set, bounds it already
                pred = model(z)
            e = state_error(pred, X_val[b0 : b0 + cfg.val_batch_size], self.angle_mask)[:, cfg.warmup :]
            e2 = e.double().square()
            if self.comp_w is not None:  # the same component weights as the training loss (mean 1)
                e2 = e2 * self.comp_w.double()
            if self.sets.L_val is None:
                total += float(e2.sum())
                count += e.numel()
            else:  # partial ground truth: the labelled steps only
                lab = self.sets.L_val[b0 : b0 + cfg.val_batch_size, cfg.warmup :].double()
                total += float((e2 * lab.unsqueeze(-1)).sum())
                count += int(lab.sum()) * e.shape[-1]
            bar.update(1)
        model.train()
        return total / count if count else math.inf

    def finish(self) -> None:
        """Step 8: the best model rebuilt from its checkpoint, measured; the final card; step.onnx."""
        cfg, out_dir = self.cfg, self.out_dir
        if self.state["best_epoch"] == 0:
            raise TrainingError(f"no epoch gave a finite validation loss; nothing to save in {out_dir}")
        best_model, _, _ = load_checkpoint(out_dir, self.device, self.system)
        metrics = None
        if cfg.eval_trajectories:
            metrics = evaluate(
                self.scenario,
                best_model,
                self.sets.norm,
                self.arch,
                cfg.eval_trajectories,
                cfg.data_seed,
                self.device,
                cfg.cache_dir,
                data=self.sets.eval_data,
                context=cfg.val_context,
                context_copies=cfg.val_context_copies,
            )
        save_checkpoint(out_dir, best_model, self.sets.norm, self.card(metrics))
        try:  # the batch-1 step beside the card: the estimator nodes serve it without torch
            export_beside(out_dir, self.system)
        except OnnxError as exc:
            raise TrainingError(f"{out_dir}: the model is saved, but not its step.onnx: {exc}") from None
        if not cfg.keep_resume:
            shutil.rmtree(out_dir / RESUME_DIR, ignore_errors=True)

    def card(self, metrics: dict[str, Any] | None = None) -> dict[str, Any]:
        """The checkpoint's card: data, recipe, budget, history, validation loss, metrics."""
        cfg, run, recorded = self.cfg, self.state, self.sets.recorded
        return {
            "scenario": self.scenario.describe(),
            "data": {
                **(
                    {"source": "recorded", **recorded}
                    if recorded
                    else {"seed": cfg.data_seed, "index": cfg.data_index, "data_ratio": cfg.data_ratio}
                ),
                "train_trajectories": self.sets.n_train,
                "train_length": cfg.train_length,
                "val_trajectories": cfg.val_trajectories,
                "windows_per_epoch": self.n_windows,
            },
            "init_seed": cfg.init_seed,
            "training": {
                "recipe": cfg.recipe(),
                "supervision": cfg.supervision,
                "device": str(self.device),
                "steps_per_epoch": self.steps_per_epoch,
                "loss": "sum w e^2 / (dx sum w): w = inverse sampling frequency x warm-up mask, "
                "e = normalised error, angles wrapped"
                + (
                    ""
                    if self.comp_w is None
                    else "; each component weighted by sigma_d^2 / mean(sigma^2) (loss_units=state: the states' units)"
                ),
                "validation": f"mean e^2 over full-length validation trajectories, t >= {cfg.warmup}, eval mode"
                + (
                    ""
                    if not cfg.val_context
                    else f", context bounded to {cfg.val_context} steps (its attention window)"
                    if self.window_key
                    else f", context bounded to {cfg.val_context} steps ({cfg.val_context_copies} copies)"
                ),
                "epochs_run": run["epoch"],
                "best_epoch": run["best_epoch"],
                "stopped": run["stopped"] or ("max epochs" if run["epoch"] >= cfg.epochs else "in progress"),
                "budget": {
                    "max_epochs": cfg.epochs,
                    "early_stopping_patience": cfg.patience,
                    "windows_per_epoch": self.n_windows,
                    "val_trajectories": cfg.val_trajectories,
                    "wall_seconds": round(sum(h["seconds"] for h in run["history"]), 1),
                },
                "lr_reductions": lr_reductions(run["history"], cfg.lr),
                "converged": converged(run["stopped"], run["history"], cfg.lr),
                "convergence_rule": "early stopping triggered, or the learning rate reduced at least 3 times",
                "history": run["history"],
                **({"init_from": run["init_from"]} if run.get("init_from") else {}),
            },
            "validation_loss": run["best"],
            "metrics": metrics,
        }


def evaluate(
    scenario: Scenario,
    model: torch.nn.Module,
    normalizer: Normalizer,
    arch: str,
    trajectories: int,
    seed: int = 0,
    device: str | torch.device = "cpu",
    cache_dir: str | None = None,
    data: Trajectories | None = None,
    context: int = 0,
    context_copies: int = 4,
) -> dict[str, Any]:
    """Metrics of a model on the first ``trajectories`` of evaluation set 0 (scenario horizon), or of
    ``data`` (recorded data: the validation set), the first :data:`EVALUATION_WARMUP` steps not scored
    (as every evaluation; the card's ``set.warmup`` says so; cards without it scored every step);
    ``context`` > 0 runs it with its context bounded (the card's ``set.context`` says so)."""
    role = "eval" if data is None else "val (recorded)"
    data = (
        dataset(scenario, "eval", 0, trajectories, None, seed, cache_dir)
        if data is None
        else data.subset(slice(0, trajectories))
    )
    est = NeuralEstimator(
        scenario,
        model,
        normalizer,
        arch,
        device=device,
        covariance=False,
        context=context,
        context_copies=context_copies,
    )
    out = est.run(data.y, data.u)
    warmup = EVALUATION_WARMUP if data.horizon > EVALUATION_WARMUP else 0
    report = compute_labelled_metrics(  # compute_metrics, on the labelled steps where some have no truth
        data.x, out.x, scenario.angle_states, data.labelled, diverged=out.diverged, warmup=warmup
    )
    return {
        "set": {
            "role": role,
            "index": 0,
            "seed": seed,
            "trajectories": data.n,
            "horizon": data.horizon,
            "warmup": warmup,
            **({"context": context, "context_copies": context_copies} if context else {}),
        },
        **to_json(report.scalars()),
    }
