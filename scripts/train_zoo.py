"""Train the shipped model zoo with the paper's recipe, resumably, across as many runs as it takes.

Recipe (neural_estimator.training.recipe.TrainConfig defaults = the paper's): data ratio 20:1 (4,000
training trajectories x 500 steps), 20,000 random length-100 windows per epoch in batches of 64,
AdamW lr 2e-3 (weight decay 1e-5, clip 1.0), ReduceLROnPlateau factor 0.5 / patience 3, early
stopping patience 30, at most 500 epochs. One deviation, for CPU time: the validation set is
--val-trajectories (default 1,000) full-length trajectories instead of the paper's 8,000.

Each (scenario, model) trains on the scenario's constants (--preset; default the scenario's defaults) in
STATE/<scenario>-<method>/ (default STATE = zoo_training/ at the repository root), or in
STATE/<preset>/<scenario>-<method>/ when the former holds a training of other constants or the
preset is not the defaults (work_dir): the best checkpoint so far (model.safetensors + card.json) and resume/ (weights,
AdamW state, scheduler, RNG states, history; safetensors + JSON, no pickle; about 1.5 MB per
model), small enough to commit so that the next run, on any machine, continues where this one stopped.
Running the script again resumes every unfinished model from its last finished epoch.
Started once per core with the same arguments, the processes share the queue: each pair is
claimed by one of them (a lock file in its directory, see claimed()) and the others move on. Once a
model is finished its resume state is deleted, and its weights too where the zoo ships the same
file (prune; --prune does it for every finished training under STATE): the card keeps the
history and the recipe. See docs/training.md.

A model is finished when early stopping triggers, the plateau rule says so (below), the epoch
budget (--max-epochs) is spent, its wall-time budget (--model-hours, summed over all runs) is
spent, or --finish says so: that
finishes the selected unfinished models as they stand, without another epoch (for a run whose
validation loss has been flat at a learning rate halved many times, where waiting for the paper's
30-epoch early stopping costs an hour of CPU per model and changes nothing); the card says so.
A finished model is evaluated on --eval-trajectories trajectories of evaluation set 0 (the card's
metrics: a report, never a criterion) and installed into neural_estimator/serving/zoo/ with its card, which
records the budget and whether training converged (early stopping triggered, or the learning rate
reduced at least three times). It is not installed, and the shipped model stays (the script says
why), when its best epoch is its first (the recipe did not train it), or when the shipped model of
the same constants has the lower RMSE on the selection set: --eval-trajectories trajectories of
validation set SELECTION_INDEX (100) at the training's data seed, both models scored afresh. Model
selection never sees an evaluation set that a table reports (test/test_selection.py). A shipped
model of other constants (a recalibrated scenario) is replaced without a comparison; --no-compare
skips the comparison.

The plateau rule (a stated budget, on by default; --plateau-epochs 0 turns it off): a model is finished
once its learning rate has been reduced at least 3 times and its last --plateau-epochs (N = 10) epochs
did not lower the validation loss by --plateau-tol (1 %) against the N epochs before them
(training.stopping.plateau_rule). The paper waits 30 epochs without a new best; on this CPU that is
40-50 minutes per model on a flat curve. Replayed on the full-recipe histories so far, the rule ends
no run more than 1.1 % above its final best validation loss. Such a model is converged by the card's
rule, and the card says which rule stopped it.

Order: the --methods order (default Mamba-2, Mamba, GRU, LSTM, GPT-2, Filterformer), method-major:
every selected scenario gets the first method before any gets the second. A model that has not
started is not started where the zoo already ships one of the same constants (nothing invalidated
it; --retrain starts it anyway), so a plain run retrains exactly what a recalibration invalidated
and resumes what is in progress.
--hours bounds this invocation: no new epoch starts after it; the state stays resumable.

    python scripts/train_zoo.py --scenarios lorenz96 --methods mamba,mamba2 --hours 1
    python scripts/train_zoo.py --status        # what is finished, what is in progress
    python scripts/train_zoo.py --scenarios ballistic,quadrotor --methods mamba2,mamba,gru,lstm,gpt2,filterformer
                                                # the retraining after the v4 recalibration (resumable)
    python scripts/train_zoo.py --scenarios nlink --methods mamba2 --val-context 100   # a variant

--val-context N (not the paper's recipe) validates, and so chooses the checkpoint, with the model's
context bounded to N steps (the recurrent models by restarted copies, models.context, for states
that drift past the training windows: the N-link SSMs; GPT-2 and Filterformer by an attention
window of N instead of the paper's 256, which on ballistic and bearings lets them attend to more
steps than they were trained on; see the README); the card records it and the model then serves
bounded by default. Such variants train in zoo_training/context<N>/ and replace no shipped model
unless --zoo or --install is given.

--fallback-context N does the same for a full-recipe model that the zoo did not take (its validation
never beat its first epoch, or it lost to the shipped one): its bounded-context variant trains next,
in STATE/context<N>/, and is installed under the same rules.

--install installs the selected models that are already finished (no training), under the same rules
as at the end of a run (not its first epoch; lower RMSE than the shipped model on the same set
unless --no-compare): for a variant that finished in an earlier run, e.g.

    python scripts/train_zoo.py --scenarios bearings --methods gru --val-context 100 --install
"""

from __future__ import annotations

import argparse
import contextlib
import fcntl
import hashlib
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import torch

from neural_estimator.data.protocol import SELECTION_INDEX, dataset
from neural_estimator.methods import table
from neural_estimator.serving.checkpoint import load_checkpoint
from neural_estimator.serving.instances import instance_checkpoint, instance_number
from neural_estimator.serving.load import validated_context
from neural_estimator.training.loop import evaluate, train
from neural_estimator.training.recipe import TrainConfig
from neural_estimator.training.resume import RESUME_DIR
from neural_estimator.training.stopping import plateau_rule
from neural_estimator.training.threads import ThreadGovernor
from neural_estimator.core.runtime import tune_allocator
from neural_estimator.paper import PAPER_SCENARIOS
from neural_estimator.scenarios import EVALUATION_CONSTANTS, default_preset, make_scenario

ROOT = Path(__file__).resolve().parents[1]
ZOO = ROOT / "neural_estimator" / "serving" / "zoo"
STATE = ROOT / "zoo_training"
LOCK_NAME = "training.lock"  # see claimed(); not committed (.gitignore)
ORDER = ("mamba2", "mamba", "gru", "lstm", "gpt2", "filterformer")  # SSMs first, then recurrent, then attention
# Per (scenario, method) changes of the architecture's defaults, recorded in the recipe (model_overrides).
# N-link's hybrid starts without the fixed gain K0 (models/kalmannet.py): linearised at the hanging
# prior it hurts there (untrained RMSE 10.3 against the open loop's 3.4; after 150 AdamW steps the
# training loss was 0.73 started from K0 against 0.18 from prior_gain=0). Neither does the ballistic one:
# linearised at the prior's 90 km, K0 has the wrong sign once the body falls below the radar's
# altitude (30 km; d range / d altitude changes sign), and the full-recipe run from K0 ended its
# first epoch at a validation loss of 0.96 (altitude RMSE 9.1 km) against 0.0093 from prior_gain=0.
# The quadrotor's neither: on a probe (640 trajectories x 6 epochs) its validation loss jumped
# between epochs from K0 (0.06 to 0.39), less so without.
MODEL_OVERRIDES = {(s, "kalmannet"): {"prior_gain": 0.0} for s in ("ballistic", "quadrotor")}
# N-link's gain must follow the configuration (h's Jacobian turns with the angles), which a gain on the
# raw innovation learns poorly (11.4x the EKF after 1 h); the state form corrects through h linearised
# at each prediction and starts from the alpha-beta gains G0 (alpha 0.25). Untrained, on 100 trajectories
# of 500 steps: median trajectory RMSE 0.30 with 6 of 100 diverging (0.15: 0.46, 4; 0.4: 0.36, 4), against
# 3.9 (the open loop's) for the innovation form without K0.
MODEL_OVERRIDES[("nlink", "kalmannet")] = {"gain_form": "state", "prior_gain": 0.25}
# Per (scenario, method) changes of the recipe, recorded in the card's recipe like every field. The
# hybrids after Lorenz 96 train at lr 5e-4, not the paper's 2e-3 (a network's rate): at 2e-3 a
# chunk's loss ran away within the first epochs, on the quadrotor (training loss 18 then 2,106,
# validation loss 0.036 then 7.96 with prior_gain=0), the ballistic system (validation 0.0096 for
# three epochs, then 45,942) and bearings (training loss 175 and 50 in epochs 2 and 4); at 5e-4 the
# quadrotor's first two epochs had none (training loss 0.056, 0.037; validation 0.039, 0.023).
# N-link's needed more: at 5e-4 (state units, without K0) its first full-recipe epoch ended at a
# validation loss of 316 (the open loop's is about 2.5) with 252 of 315 steps skipped for a NaN
# gradient, its angular rates run away; at lr 1e-4 with the loss in normalised units a probe (640
# trajectories, 3 epochs) went 0.58, 0.42, 0.30 (the open loop's about 1.8 in those units), none skipped.
RECIPE_OVERRIDES = {(s, "kalmannet"): {"lr": 5e-4} for s in ("ballistic", "bearings", "quadrotor")}
RECIPE_OVERRIDES[("nlink", "kalmannet")] = {"lr": 1e-4, "loss_units": "normalised"}
OBSERVATIONS = "observations"  # --supervision observations: trained and installed apart (variants/observations/)
FINE_TUNE = "finetune"  # --fine-tune: trained in STATE/finetune/, from the shipped weights


def recorded_scenario(work: Path) -> dict | None:
    """The scenario description a training directory was written for (its card, else its resume
    state), or None when nothing has been trained there."""
    for path in (work / "card.json", work / RESUME_DIR / "state.json"):
        if path.is_file():
            return json.loads(path.read_text()).get("scenario")
    return None


def same_constants(desc: dict, scenario) -> bool:
    """True when ``desc`` (a recorded description) has ``scenario``'s name and constants, up to the
    constants that may differ between training and use (noise scale, horizon)."""
    ours = scenario.describe()
    if desc.get("scenario") != ours["scenario"]:
        return False
    theirs_cfg, ours_cfg = desc.get("config", {}), ours["config"]
    keys = (set(theirs_cfg) | set(ours_cfg)) - set(EVALUATION_CONSTANTS)
    return all(theirs_cfg.get(k) == ours_cfg.get(k) for k in keys)


def work_dir(state: Path, scenario, method: str) -> Path:
    """Where (scenario, method) trains on ``scenario``'s constants.

    STATE/<preset>/<scenario>-<method>/ when it holds a training of these constants (e.g.
    zoo_training/v4/ballistic-mamba2/ for the recalibrated ballistic); else STATE/<scenario>-<method>/
    when that holds a training of these constants (every training made before presets existed lives
    there, on the constants of preset v3), or is empty and these are the scenario's default
    constants; else STATE/<preset>/<scenario>-<method>/. A training on other constants never meets
    another one's state, and one on a preset newer than the defaults (``v5``) stays in its folder
    when the defaults move to it.
    """
    legacy = state / f"{scenario.name}-{method}"
    preset = scenario.describe().get("preset")
    by_preset = state / (preset or "custom") / legacy.name
    recorded = {where: recorded_scenario(where) for where in (by_preset, legacy)}
    for where, desc in recorded.items():
        if desc is not None and same_constants(desc, scenario):
            return where
    if recorded[legacy] is None and preset in (None, default_preset(scenario.name)):
        return legacy
    return by_preset


@contextlib.contextmanager
def claimed(work: Path):
    """Hold the training in ``work`` for this process while the block runs; yields False, holding
    nothing, where another process holds it.

    An exclusive, non-blocking ``flock`` on WORK/training.lock: several train_zoo.py processes
    started with the same arguments (one per core) share the queue, each pair trained by exactly
    one of them, the others moving on to the next pair. The kernel releases the lock when its
    process exits or is killed, so a stopped run never leaves a pair locked.
    """
    work.mkdir(parents=True, exist_ok=True)
    with open(work / LOCK_NAME, "a+") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            yield False
            return
        try:
            yield True
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def prune(work: Path, zoo: Path | None = ZOO) -> list[str]:
    """Drop what a finished training no longer needs; returns the removed paths (relative to work).

    Kept: card.json, which holds the training's history (``training.history``, every epoch's losses,
    learning rate and seconds) and the recipe that reproduces it (``training.recipe``, ``data``,
    ``init_seed``, ``architecture``). Removed: resume/ (the last epoch's weights, the AdamW moments,
    the scheduler, the RNG states: only a training that goes on needs them) and model.safetensors
    where the zoo ships the very same weights, with the step.onnx exported from them (byte-identical
    weights; a model that was not installed, e.g.
    a --val-context variant, keeps its weights so that --install can still install it), and the
    lock file of :func:`claimed` (a process that opens it later finds the training finished).
    An unfinished training is left as it is: its resume state is what the next run continues from.
    """
    if not finished(work):
        return []
    removed = []
    if (work / RESUME_DIR).is_dir():
        shutil.rmtree(work / RESUME_DIR)
        removed.append(f"{RESUME_DIR}/")
    weights, shipped = work / "model.safetensors", (zoo / work.name / "model.safetensors") if zoo else None
    if (
        weights.is_file()
        and shipped is not None
        and shipped.is_file()
        and shipped.resolve() != weights.resolve()  # the zoo's own folder, where STATE holds the zoo
        and _sha256(weights) == _sha256(shipped)
    ):
        weights.unlink()
        removed.append("model.safetensors")
        if (work / "step.onnx").is_file():  # the graph of those weights: the zoo ships its own beside them
            (work / "step.onnx").unlink()
            removed.append("step.onnx")
    (work / LOCK_NAME).unlink(missing_ok=True)
    return removed


def resume_state(work: Path) -> dict | None:
    """The run record of an unfinished model (epoch, history, ...), or None if it has not started."""
    path = work / RESUME_DIR / "state.json"
    return json.loads(path.read_text())["run"] if path.is_file() else None


def finished(work: Path) -> bool:
    """True once the model's card says training ended (early stopping, epoch or wall budget)."""
    card = work / "card.json"
    if not card.is_file():
        return False
    return json.loads(card.read_text())["training"]["stopped"] != "in progress"


def used_seconds(work: Path) -> float:
    run = resume_state(work)
    return sum(h["seconds"] for h in run["history"]) if run else 0.0


def install(work: Path, zoo: Path) -> Path:
    """Copy the finished checkpoint (weights, card and the exported step.onnx where train wrote one;
    not the resume state) into the zoo."""
    dest = zoo / work.name
    tmp = dest.with_name(dest.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    for name in ("model.safetensors", "card.json", "step.onnx"):
        if name == "step.onnx" and not (work / name).is_file():
            continue  # a model validated with a bounded context: torch serves it
        shutil.copy2(work / name, tmp / name)
    shutil.rmtree(dest, ignore_errors=True)
    tmp.rename(dest)
    return dest


def not_installable(work: Path) -> str | None:
    """Why a finished model must not replace the shipped one, or None: after more than one epoch its
    validation loss never went below its first epoch's (the best weights are epoch 1's: the recipe did
    not train it; the shipped models are held to the same rule by test/test_zoo.py)."""
    card = json.loads((work / "card.json").read_text())
    history = card["training"]["history"]
    first = history[0]["val_loss"]
    if len(history) > 1 and not card["validation_loss"] < first:
        return f"its validation loss never went below its first epoch's ({first:.4g}); the shipped model stays"
    return None


def selection_rmse(checkpoint: Path, scenario, trajectories: int, seed: int = 0, device: str = "cpu") -> float:
    """RMSE of the checkpoint in ``checkpoint`` (as it serves: bounded if it was validated so) on the
    selection set: the first ``trajectories`` of validation set :data:`SELECTION_INDEX` at ``seed``.

    A validation set, not an evaluation set: the evaluation sets are what the tables report
    (evaluate, reproduce, the neural scoreboard), so choosing between models on one of them would
    select on the test set; and not a training's own validation set (index 0-2), on which the new
    model's best epoch was already chosen."""
    model, norm, card = load_checkpoint(checkpoint, device, scenario)
    data = dataset(scenario, "val", SELECTION_INDEX, trajectories, None, seed)
    metrics = evaluate(
        scenario,
        model,
        norm,
        card["architecture"]["name"],
        trajectories,
        seed,
        device,
        data=data,
        **validated_context(card),
    )
    return float(metrics["rmse"])


def comparable_shipped(work: Path, zoo: Path, scenario) -> Path | None:
    """The shipped model of this pair when it serves ``scenario``'s constants, else None (nothing
    ships there, or it was trained on other constants, e.g. preset v3 after a recalibration: it
    cannot serve these, so there is nothing to compare against)."""
    shipped = zoo / work.name
    card = shipped / "card.json"
    if not card.is_file() or not same_constants(json.loads(card.read_text())["scenario"], scenario):
        return None
    return shipped


def shipped_of(zoo: Path, work: Path, scenario) -> bool:
    """True when ``zoo`` ships this pair with a card of ``scenario``'s constants: a recalibration did
    not invalidate it, so a plain run does not train it again."""
    return comparable_shipped(work, zoo, scenario) is not None


def install_if_better(
    work: Path, zoo: Path, scenario, compare: bool = True, device: str = "cpu", trajectories: int = 1000
) -> bool:
    """Install the finished model of ``work`` into ``zoo`` unless :func:`not_installable` says why not
    or, with ``compare``, the shipped model of the same constants scores a lower RMSE on the selection
    set (:func:`selection_rmse`, validation data only); print which, with both figures. Returns
    whether it was installed."""
    why = not_installable(work)
    figures = ""
    shipped = comparable_shipped(work, zoo, scenario) if compare and why is None else None
    if shipped is not None:
        seed = json.loads((work / "card.json").read_text()).get("data", {}).get("seed", 0)
        new = selection_rmse(work, scenario, trajectories, seed, device)
        old = selection_rmse(shipped, scenario, trajectories, seed, device)
        figures = (
            f" (selection set: validation set {SELECTION_INDEX}, seed {seed}, {trajectories} trajectories; "
            f"RMSE {new:.4g} against the shipped model's {old:.4g})"
        )
        why = not_better(new, old)
    if why:
        print(f"{work.name}: not installed: {why}{figures}", flush=True)
        return False
    dest = install(work, zoo)
    print(f"installed {dest}{figures}", flush=True)
    fit_head(dest, zoo)
    return True


def fit_head(dest: Path, zoo: Path) -> None:
    """Give a model installed in the package's zoo (the shipped model or a trained instance,
    zoo/instances/i<K>/) its covariance head (scripts/fit_covariance_heads.py, a fresh process: the
    weights are untouched); a failure is reported, never fatal to the training."""
    scenario, method = dest.name.rsplit("-", 1)
    if not table.has(method, family="neural"):
        print(f"{dest.name}: no covariance head (a {table.spec(method).family} method reports none)", flush=True)
        return
    cmd = [
        sys.executable,
        str(ROOT / "scripts" / "fit_covariance_heads.py"),
        "--scenarios",
        scenario,
        "--methods",
        method,
    ]
    instance = instance_number(dest)
    if instance:  # a trained instance, zoo/instances/i<K>/: its own head, on the same validation sets
        cmd += ["--instance", str(instance)]
    if instance_checkpoint(scenario, method, instance, ZOO).resolve() != dest.resolve():
        print(
            f"{dest.name}: no covariance head fitted outside the package's zoo (run: {' '.join(cmd[1:])})", flush=True
        )
        return
    rc = subprocess.run(cmd, check=False).returncode
    outcome = "fitted" if rc == 0 else f"NOT fitted (exit {rc}; rerun: {' '.join(cmd[1:])})"
    print(f"{dest.name}: covariance head {outcome}", flush=True)


def not_better(new: float, shipped: float | None) -> str | None:
    """Why a finished model must not replace the shipped one by its selection-set RMSE, or None: it
    must be lower than the shipped model's on the same validation trajectories."""
    if shipped is None or new < shipped:
        return None
    return f"its RMSE {new:.4g} is not below the shipped model's {shipped:.4g}; the shipped model stays"


def installed_note(work: Path, zoo: Path | None) -> str:
    """Whether the shipped model of the pair is this training's (same card), for a pruned training."""
    shipped = (zoo / work.name / "card.json") if zoo else None
    if shipped is not None and shipped.is_file() and shipped.read_text() == (work / "card.json").read_text():
        return f"the zoo ships it ({shipped.parent})"
    return "the zoo does not ship it; train it again to install it"


def status_line(work: Path) -> str:
    if finished(work):
        card = json.loads((work / "card.json").read_text())
        t = card["training"]
        rmse = (card.get("metrics") or {}).get("rmse")
        return (
            f"{work.name}: finished ({t['stopped']}), {t['epochs_run']} epochs, converged={t.get('converged')}, "
            f"best val {card['validation_loss']:.4g}, RMSE {rmse}"
        )
    run = resume_state(work)
    if run is None:
        return f"{work.name}: not started"
    h = run["history"][-1] if run["history"] else {}
    return (
        f"{work.name}: in progress, {run['epoch']} epochs ({used_seconds(work) / 3600:.2f} h), "
        f"best val {run['best']:.4g} at epoch {run['best_epoch']}, lr {h.get('lr')}"
    )


def run_pair(a: argparse.Namespace, scenario, method: str, work: Path, zoo: Path | None, stop_at: float | None) -> None:
    """Train (scenario, method) in ``work`` to the end or to the run's budget, then install and
    prune what finished; skipped when finished, when the zoo ships a model of these constants (no
    --retrain), when the run's hours are spent, or when another process holds it (:func:`claimed`)."""
    if finished(work):
        return
    if resume_state(work) is None and not a.retrain and zoo is not None and shipped_of(zoo, work, scenario):
        print(
            f"{work.name}: not started: the zoo ships a model of these constants, nothing to retrain "
            "(--retrain trains one anyway)",
            flush=True,
        )
        return
    if stop_at is not None and time.time() >= stop_at:
        print(f"{work.name}: not started in this run (--hours spent)", flush=True)
        return
    if a.finish and resume_state(work) is None:
        print(f"{work.name}: not started, nothing to finish", flush=True)
        return
    with claimed(work) as mine:
        if not mine:
            print(f"{work.name}: another train_zoo.py process is training it, skipped", flush=True)
            return
        if finished(work):  # by that other process, since the check above
            return
        left = 3600 * a.model_hours - used_seconds(work)
        deadline = time.time() + left if stop_at is None else min(stop_at, time.time() + left)
        recipe = dict(
            val_trajectories=a.val_trajectories,
            trajectories=a.trajectories,
            windows_per_epoch=a.windows_per_epoch,
            device=a.device,
            eval_trajectories=a.eval_trajectories,
            loss_units=a.loss_units,
            supervision=a.supervision,
            model_overrides=dict(MODEL_OVERRIDES.get((scenario.name, method), {})),
            val_context=a.val_context,
            val_context_copies=a.val_context_copies,
            resume=True,
            keep_resume=True,
            **instance_seeds(a.instance),
        )
        recipe.update(RECIPE_OVERRIDES.get((scenario.name, method), {}))
        if a.lr is not None:
            recipe["lr"] = a.lr
        if a.fine_tune:
            start = comparable_shipped(work, zoo, scenario) if zoo is not None else None
            if start is None:
                print(f"{work.name}: not started: the zoo ships no model of these constants to fine-tune", flush=True)
                return
            recipe["init_from"] = str(start)
        cfg = TrainConfig(epochs=a.max_epochs, **recipe)
        t0 = time.time()
        if not a.finish:
            stop_when = plateau_rule(cfg.lr, a.plateau_epochs, a.plateau_tol) if a.plateau_epochs else None
            governor = ThreadGovernor(a.threads) if a.threads > 1 else None  # see `train --threads`
            train(
                scenario,
                method,
                work,
                cfg,
                progress=not a.quiet,
                deadline=deadline,
                stop_when=stop_when,
                threads=governor,
            )
        run = resume_state(work)
        if not finished(work) and (a.finish or used_seconds(work) >= 3600 * a.model_hours):
            # finish as it stands: evaluate the best model, final card saying why it stopped
            cfg = TrainConfig(epochs=run["epoch"], **recipe)
            train(scenario, method, work, cfg, progress=False)
            card = json.loads((work / "card.json").read_text())  # say why it stopped, and the real budget
            if a.finish:
                card["training"]["stopped"] = (
                    f"finished by hand (--finish) after {run['epoch']} epochs, {used_seconds(work) / 3600:.2f} h"
                )
            else:
                card["training"]["stopped"] = f"wall budget spent ({a.model_hours:g} h)"
            card["training"]["budget"]["max_epochs"] = a.max_epochs
            (work / "card.json").write_text(json.dumps(card, indent=2) + "\n")
        if finished(work) and zoo is None:
            print(f"{work.name}: finished in {work} (a --val-context variant: not installed without --zoo)")
        elif finished(work):
            install_if_better(work, zoo, scenario, not a.no_compare, a.device, a.eval_trajectories)
        if finished(work):
            prune(work, zoo)
        print(f"{status_line(work)} [{time.time() - t0:.0f} s this run]", flush=True)


def instance_seeds(instance: int) -> dict:
    """The recipe's seeds of trained instance ``instance``: training (and validation) set
    ``data_index = instance`` at data seed 0 and ``init_seed = instance``. Instance 0 is the shipped
    model (data set 0, initialisation 0); the paper trains 3 data sets x 5 initialisations and reports
    medians, so instances 1 and 2 take the paper's other two data sets with their own initialisation."""
    if instance < 0:
        raise ValueError(f"--instance must be >= 0, got {instance}")
    return {"data_index": instance, "init_seed": instance}


def instance_paths(instance: int, state: Path | None, zoo: Path | None) -> tuple[Path, Path]:
    """Where instance ``instance`` (>= 1) trains and is installed: STATE/instances/i<K>/ and
    neural_estimator/serving/zoo/instances/i<K>/ unless --state / --zoo say otherwise."""
    name = f"i{instance}"
    return (state or STATE / "instances" / name), (zoo or ZOO / "instances" / name)


def not_shipped(work: Path) -> bool:
    """A finished training whose model the zoo does not ship: its weights are still in ``work``
    (:func:`prune` removes them only where the zoo holds the very same file)."""
    return finished(work) and (work / "model.safetensors").is_file()


def run_fallback(a, scenario, method: str, work: Path, state: Path, zoo: Path, stop_at: float | None) -> None:
    """Train and install the bounded-context variant of a full-recipe model the zoo did not take
    (--fallback-context N): the zoo's rule for variants (docs/training.md, "Why some models are
    bounded-context variants"). Its state is STATE/context<N>/, as with --val-context N; resumed
    like any training, and a no-op once it has finished."""
    n = a.fallback_context
    variant_work = work_dir(state / f"context{n}", scenario, method)
    if not finished(variant_work):
        print(f"{work.name}: not in the zoo; training its bounded-context variant (context {n})", flush=True)
    run_pair(argparse.Namespace(**{**vars(a), "val_context": n}), scenario, method, variant_work, zoo, stop_at)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenarios", default=",".join(PAPER_SCENARIOS))
    p.add_argument(
        "--preset",
        default=None,
        help="scenario constants to train on (default: each scenario's defaults, preset v4; v3: the "
        "constants of the earlier zoo)",
    )
    p.add_argument("--methods", default=",".join(ORDER))
    p.add_argument("--max-epochs", type=int, default=500, help="epoch budget per model (paper: 500)")
    p.add_argument(
        "--model-hours",
        type=float,
        default=24.0,
        help="wall-time budget per model, summed over runs; then it is finished as it stands",
    )
    p.add_argument(
        "--plateau-epochs",
        type=int,
        default=10,
        help="finish a model once its lr was reduced >= 3 times and its last N epochs did not lower the "
        "validation loss by --plateau-tol against the N before (0: off, only the paper's early stopping)",
    )
    p.add_argument("--plateau-tol", type=float, default=0.01, help="relative improvement of the plateau rule")
    p.add_argument("--hours", type=float, default=None, help="stop starting epochs after this long (this run)")
    p.add_argument("--val-trajectories", type=int, default=1000, help="validation set (paper: 8000)")
    p.add_argument("--trajectories", type=int, default=None, help="training trajectories (default: 20:1 -> 4000)")
    p.add_argument("--windows-per-epoch", type=int, default=None, help="default: the set's steps once (20:1 -> 20000)")
    p.add_argument("--eval-trajectories", type=int, default=1000, help="card metrics of a finished model")
    p.add_argument(
        "--loss-units",
        default=TrainConfig.loss_units,
        choices=("state", "normalised"),
        help="units the loss weighs the state components in (default: state, as RMSE; see the README)",
    )
    p.add_argument(
        "--threads",
        type=int,
        default=1,
        help="at most this many torch and kernel threads, the count measured as `neural-estimator train --threads` "
        "does (1: bit-reproducible)",
    )
    p.add_argument("--device", default="cpu")
    p.add_argument(
        "--val-context",
        type=int,
        default=0,
        help="validate with the context bounded to N steps (restarted copies for GRU, LSTM, Mamba, Mamba-2; "
        "the attention window for GPT-2, Filterformer; not the paper's): a variant, trained in "
        "STATE/context<N>/ and installed nowhere unless --zoo is given",
    )
    p.add_argument("--val-context-copies", type=int, default=TrainConfig.val_context_copies)
    p.add_argument(
        "--fallback-context",
        type=int,
        default=0,
        help="where a finished full-recipe model is not installed (its validation never beat its first "
        "epoch, or it lost to the shipped one), train its bounded-context variant (context N, in "
        "STATE/context<N>/) and install that under the same rules",
    )
    p.add_argument(
        "--state",
        default=None,
        help="directory of the resumable training states (default zoo_training/, zoo_training/context<N>/ "
        "with --val-context)",
    )
    p.add_argument(
        "--zoo", default=None, help="where finished models are installed (default neural_estimator/serving/zoo/)"
    )
    p.add_argument(
        "--finish",
        action="store_true",
        help="finish the selected unfinished models as they stand (no more epochs): evaluate, install",
    )
    p.add_argument(
        "--no-compare",
        action="store_true",
        help="install a finished model even if the shipped one scores a lower RMSE on the same set",
    )
    p.add_argument(
        "--install",
        action="store_true",
        help="install the selected finished models (no training; a --val-context variant into the shipped zoo)",
    )
    p.add_argument("--status", action="store_true", help="print each model's state and exit")
    p.add_argument(
        "--retrain",
        action="store_true",
        help="start a model even where the zoo ships one of the same constants (default: only what a "
        "change of constants invalidated, or what never shipped, is trained)",
    )
    p.add_argument(
        "--prune",
        action="store_true",
        help="remove what every finished training under STATE no longer needs (resume state; weights the "
        "zoo ships identically) and exit; runs by itself after every training that finishes",
    )
    p.add_argument(
        "--instance",
        type=int,
        default=0,
        help="train instance K >= 1 of each selected pair (training set K, initialisation K; the shipped "
        "model is instance 0), in STATE/instances/i<K>/, installed into neural_estimator/serving/zoo/instances/i<K>/ "
        "with no comparison against the shipped model: every instance is kept, for medians over instances",
    )
    p.add_argument(
        "--supervision",
        choices=("states", OBSERVATIONS),
        default="states",
        help="what a hybrid's loss reads: states (default), or observations only (no state label: trained in "
        "STATE/observations/, installed into neural_estimator/serving/zoo/variants/observations/, never "
        "replacing the state-trained model; evaluate reaches it with --checkpoint kalmannet=DIR)",
    )
    p.add_argument(
        "--fine-tune",
        action="store_true",
        help="start each selected pair from the zoo's shipped model of the pair (its weights, a fresh optimiser; "
        "the card's training.init_from) in STATE/finetune/; installed only where it beats the shipped model",
    )
    p.add_argument("--lr", type=float, default=None, help="learning rate instead of the pair's (e.g. a fine-tune's)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    a = p.parse_args(argv)
    if a.fine_tune and (a.instance or a.val_context or a.supervision == OBSERVATIONS):
        p.error(
            "--fine-tune starts from the shipped model; it does not go with --instance, --val-context or --supervision"
        )
    if a.lr is not None and not a.lr > 0:
        p.error(f"--lr must be positive, got {a.lr}")
    if a.supervision == OBSERVATIONS:
        bad = [m for m in a.methods.split(",") if m.strip() and not table.has(m.strip(), family="hybrid")]
        if bad:
            p.error(f"--supervision observations trains hybrids (through the system's h); not {', '.join(bad)}")
        if a.instance or a.val_context:
            p.error("--supervision observations does not go with --instance or --val-context")
    if a.fallback_context and a.val_context:
        p.error("--fallback-context follows a full-recipe training; it does not go with --val-context")
    if a.instance < 0:
        p.error(f"--instance must be >= 0, got {a.instance}")
    if a.instance and (a.val_context or a.fallback_context):
        p.error("--instance trains the full recipe; it does not go with --val-context or --fallback-context")
    torch.set_num_threads(a.threads)
    tune_allocator()
    state = Path(a.state) if a.state else STATE / f"context{a.val_context}" if a.val_context else STATE
    # a variant replaces no shipped model unless asked to
    zoo = Path(a.zoo) if a.zoo else ZOO if a.install or not a.val_context else None
    if a.supervision == OBSERVATIONS:  # a variant of its own: never compared with, nor replacing, the shipped one
        state = Path(a.state) if a.state else STATE / OBSERVATIONS
        zoo = Path(a.zoo) if a.zoo else ZOO / "variants" / OBSERVATIONS
        a.no_compare = True
    if a.fine_tune:  # its own state; the shipped model is retrained from its own weights
        state = Path(a.state) if a.state else STATE / FINE_TUNE
        a.retrain = True
    if a.instance:  # its own state and zoo folder; every instance is kept, none compared
        state, zoo = instance_paths(a.instance, Path(a.state) if a.state else None, Path(a.zoo) if a.zoo else None)
        a.no_compare = True
    methods = [m.strip() for m in a.methods.split(",") if m.strip()]
    scenarios = [s.strip() for s in a.scenarios.split(",") if s.strip()]
    stop_at = time.time() + 3600 * a.hours if a.hours else None
    if a.prune:  # every training under STATE, whatever its constants (v3 ones included)
        for card in sorted(state.rglob("card.json")):
            work = card.parent
            removed = prune(work, zoo or ZOO)
            what = (
                f"removed {', '.join(removed)}"
                if removed
                else ("nothing to remove" if finished(work) else "in progress, kept")
            )
            print(f"{work.relative_to(state)}: {what}")
        return 0
    for method in methods:  # method-major: every scenario gets Mamba before any gets Mamba-2, and so on
        for scenario_name in scenarios:
            scenario = make_scenario(scenario_name, preset=a.preset)
            work = work_dir(state, scenario, method)
            if a.status:
                print(status_line(work).replace(work.name, str(work.relative_to(state)), 1))
                continue
            if a.install:
                if finished(work) and not (work / "model.safetensors").is_file():
                    print(f"{work.name}: finished, its weights were pruned: {installed_note(work, zoo)}", flush=True)
                elif finished(work):
                    install_if_better(work, zoo, scenario, not a.no_compare, a.device, a.eval_trajectories)
                else:
                    print(f"{work.name}: not finished, nothing to install ({status_line(work)})", flush=True)
                continue
            run_pair(a, scenario, method, work, zoo, stop_at)
            if a.fallback_context and zoo is not None and not_shipped(work):
                run_fallback(a, scenario, method, work, state, zoo, stop_at)
    return 0


if __name__ == "__main__":
    sys.exit(main())
