"""The training recipe (:class:`TrainConfig`): the paper's settings as one frozen dataclass.

Kept free of torch, so that the command line can offer every field as a ``train`` flag without
importing it; :mod:`neural_estimator.training.loop` runs the recipe.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from neural_estimator.data.protocol import TRAIN_TRAJECTORY_LENGTH, VALIDATION_TRAJECTORIES, WARMUP_STEPS, WINDOW_LENGTH


LOSS_UNITS = ("normalised", "state")
SUPERVISION = ("states", "observations")  # what the loss reads: state labels, or the observations only (a hybrid)


class TrainingError(ValueError):
    """A training configuration or state that cannot be used; the message names the problem."""


@dataclass(frozen=True)
class TrainConfig:
    """The training recipe. Defaults are the paper's (Appendix "Hyperparameter Details")."""

    # data (paper, "Neural Estimators and Training")
    data_ratio: float = 20.0  # data-to-parameter ratio: 20, 10, 5 or 1 (x 100k nominal parameters)
    data_seed: int = 0  # seed of the data sets (training, validation, evaluation)
    data_index: int = 0  # which training set (the paper uses three per scenario: 0, 1, 2)
    trajectories: int | None = None  # training trajectories; None -> from data_ratio (20:1 -> 4,000)
    val_trajectories: int = VALIDATION_TRAJECTORIES  # 8,000
    train_length: int = TRAIN_TRAJECTORY_LENGTH  # length of training and validation trajectories (500)
    window: int = WINDOW_LENGTH  # training sub-trajectory length (100)
    warmup: int = WARMUP_STEPS  # leading steps of a window (and of a validation run) not in the loss
    # the units the loss (and the validation loss) weighs the state components in: "state" (the states'
    # own units, as the paper's RMSE counts them; the default) or "normalised" (each
    # component at unit variance, every model trained before); the paper does not say which, and on
    # ballistic and the quadrotor "state" gave 2.2x and 1.5x lower RMSE (experiments/loss_units.py)
    loss_units: str = "state"
    windows_per_epoch: int | None = None  # None -> N x train_length / window (the set's steps once)
    # "states": the paper's loss on state labels; "observations": a hybrid's loss on the next
    # observation predicted through h (no state label read; training/hybrid.py)
    supervision: str = "states"
    # model
    init_seed: int = 0  # initial weights, dropout and window draws
    # a checkpoint directory whose weights start the run instead of fresh ones (fine-tuning; the same
    # architecture and configuration; training.warm_start); None: the fresh initialisation of init_seed
    init_from: str | None = None
    model_overrides: dict[str, Any] = field(default_factory=dict)  # architecture config changes
    # a hybrid's model, other than the system that made the data (scenarios.model: {constant or Q/R:
    # value}): the team's situation, its f and h wrong; {} = the data's own constants
    model_set: dict[str, str] = field(default_factory=dict)
    # optimisation (appendix)
    batch_size: int = 64
    lr: float = 2e-3
    weight_decay: float = 1e-5
    grad_clip: float = 1.0  # max gradient norm
    lr_factor: float = 0.5  # ReduceLROnPlateau factor
    lr_patience: int = 3  # ReduceLROnPlateau patience (epochs)
    epochs: int = 500  # maximum number of epochs
    patience: int = 30  # early stopping: epochs without a lower validation loss
    # validation and evaluation
    val_batch_size: int = 500  # validation trajectories per forward pass (memory only)
    # > 0: validate (and so choose the checkpoint, and score the card) with the model's context bounded
    # to this many steps: GRU, LSTM, Mamba, Mamba-2 by val_context_copies copies restarted at staggered
    # steps (models.context); GPT-2 and Filterformer by their attention window, set to val_context
    # (models.ATTENTION_WINDOW; the same training when val_context >= window). The model then serves
    # bounded by default. 0: the paper's validation (recurrent models run continuously, attention
    # windows of 256). Not the paper's: for models whose estimates degrade past the training windows.
    val_context: int = 0
    val_context_copies: int = 4
    eval_trajectories: int = 0  # > 0: metrics of the best model on that many trajectories of eval set 0
    # runtime
    device: str = "cpu"  # cpu, cuda, cuda:N or auto
    resume: bool = False  # continue from out_dir/resume if it exists
    keep_resume: bool = True  # keep out_dir/resume after the run (lets a larger --epochs extend it)
    cache_dir: str | None = None  # dataset cache (None -> $NEURAL_ESTIMATOR_CACHE or ~/.cache/...)

    def __post_init__(self) -> None:
        positive = (
            "val_trajectories",
            "train_length",
            "window",
            "batch_size",
            "epochs",
            "patience",
            "val_batch_size",
            "lr_patience",
        )
        for name in positive:
            if int(getattr(self, name)) < 1:
                raise TrainingError(f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("trajectories", "windows_per_epoch"):
            v = getattr(self, name)
            if v is not None and int(v) < 1:
                raise TrainingError(f"{name} must be >= 1 (or None for the paper's), got {v}")
        if not self.data_ratio > 0:
            raise TrainingError(f"data_ratio must be positive, got {self.data_ratio}")
        if not 1 <= self.window <= self.train_length:
            raise TrainingError(f"window must be in [1, train_length={self.train_length}], got {self.window}")
        if not 0 <= self.warmup < self.window:
            raise TrainingError(f"warmup must be in [0, window={self.window}), got {self.warmup}")
        if not (self.lr > 0 and self.weight_decay >= 0 and self.grad_clip > 0 and 0 < self.lr_factor < 1):
            raise TrainingError("need lr > 0, weight_decay >= 0, grad_clip > 0 and 0 < lr_factor < 1")
        if self.loss_units not in LOSS_UNITS:
            raise TrainingError(f"loss_units must be one of {', '.join(LOSS_UNITS)}, got {self.loss_units!r}")
        if self.supervision not in SUPERVISION:
            raise TrainingError(f"supervision must be one of {', '.join(SUPERVISION)}, got {self.supervision!r}")
        if self.val_context < 0 or self.val_context_copies < 1:
            raise TrainingError(
                f"val_context must be >= 0 and val_context_copies >= 1, got {self.val_context}, "
                f"{self.val_context_copies}"
            )
        if self.val_context and self.val_context_copies > self.val_context:
            raise TrainingError(
                f"val_context_copies ({self.val_context_copies}) must not exceed val_context ({self.val_context})"
            )
        if self.eval_trajectories < 0:
            raise TrainingError(f"eval_trajectories must be >= 0, got {self.eval_trajectories}")

    def recipe(self) -> dict[str, Any]:
        """The settings that define the result, as a JSON-ready dict (recorded in cards and resume states).

        Left out: ``cache_dir``, ``resume`` and ``keep_resume`` (where and how, not what), and
        ``init_from`` when it is None, ``supervision`` when it is "states", ``loss_units`` when it is
        "normalised" and ``model_set`` when it is empty: every card and resume state written before
        the field existed was trained so, and a recipe without it still means that; likewise
        ``val_context`` and ``val_context_copies`` when the context is unbounded (0).
        """
        d = dataclasses.asdict(self)
        d["model_overrides"] = dict(self.model_overrides)
        d["model_set"] = {k: str(v) for k, v in self.model_set.items()}
        for key in ("cache_dir", "resume", "keep_resume"):
            d.pop(key)
        if d["loss_units"] == "normalised":
            d.pop("loss_units")
        if d["supervision"] == "states":
            d.pop("supervision")  # every recipe before the field existed trained on states
        if d["init_from"] is None:
            d.pop("init_from")  # a fresh initialisation, as every recipe before the field existed
        if not d["model_set"]:
            d.pop("model_set")  # the data's own model, as every recipe before the field existed
        if not d["val_context"]:
            d.pop("val_context")
            d.pop("val_context_copies")
        return d


# ---- losses -----------------------------------------------------------------------------------------
