"""The training protocol: losses, determinism, resume, early stopping, the stopping rules, the
bounded-context validation variant, the cap on trajectory length.
"""

import dataclasses
import json
import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from neural_estimator.data import simulate
from neural_estimator.methods.interface import previous_controls
from neural_estimator.methods.registry import EstimatorError
from neural_estimator.models import build_model
from neural_estimator.serving.load import load_neural_estimator
from neural_estimator.serving.neural import NeuralEstimator
from neural_estimator.serving.normalization import Normalizer
from neural_estimator.training.loop import train
from neural_estimator.training.loss import state_error, weighted_loss
from neural_estimator.training.recipe import TrainConfig, TrainingError
from neural_estimator.scenarios import make_scenario
from training_cases import (
    tiny_config,
    weights,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tiny tensors: one intra-op thread


# ---- training -------------------------------------------------------------------------------------
def test_wrapped_and_weighted_loss():
    mask = torch.tensor([True, False])
    e = state_error(torch.tensor([[math.pi - 0.01, 1.0]]), torch.tensor([[-math.pi + 0.01, 0.5]]), mask)
    assert e[0, 0].item() == pytest.approx(-0.02, abs=1e-6) and e[0, 1].item() == pytest.approx(0.5)
    pred, target = torch.randn(3, 5, 2), torch.randn(3, 5, 2)
    w = torch.ones(3, 5)
    loss = weighted_loss(pred, target, w, torch.zeros(2, dtype=torch.bool))
    assert loss.item() == pytest.approx((pred - target).square().mean().item(), rel=1e-6)
    w[:, :2] = 0.0  # the warm-up steps do not count
    loss = weighted_loss(pred, target, w, torch.zeros(2, dtype=torch.bool))
    assert loss.item() == pytest.approx((pred - target)[:, 2:].square().mean().item(), rel=1e-6)


def test_loss_in_state_units_weighs_components_as_rmse_does():
    from neural_estimator.training.loss import component_weights

    std = np.array([20.0, 2.0, 0.01])
    assert component_weights("normalised", std, "cpu") is None
    c = component_weights("state", std, "cpu")
    assert c.tolist() == pytest.approx((std**2 / np.mean(std**2)).tolist(), rel=1e-6)
    pred, target = torch.randn(3, 5, 3, dtype=torch.float64), torch.randn(3, 5, 3, dtype=torch.float64)
    w = torch.rand(3, 5, dtype=torch.float64)
    loss = weighted_loss(pred, target, w, torch.zeros(3, dtype=torch.bool), c.double())
    raw = ((pred - target) * torch.as_tensor(std)).square()  # the errors in the states' own units
    expected = (w.unsqueeze(-1) * raw).sum() / (w.sum() * 3) / float(np.mean(std**2))
    assert loss.item() == pytest.approx(expected.item(), rel=1e-9)
    ones = weighted_loss(pred, target, w, torch.zeros(3, dtype=torch.bool), torch.ones(3, dtype=torch.float64))
    assert ones.item() == pytest.approx(weighted_loss(pred, target, w, torch.zeros(3, dtype=torch.bool)).item())
    with pytest.raises(TrainingError, match="loss_units must be one of normalised, state, got 'raw'"):
        TrainConfig(loss_units="raw")
    assert TrainConfig().loss_units == "state" and TrainConfig().recipe()["loss_units"] == "state"
    # a recipe without the field is one written before it existed: normalised, so old states still match
    assert "loss_units" not in TrainConfig(loss_units="normalised").recipe()


def test_training_in_state_units_records_it_and_differs(oscillator, tmp_path):
    cfg = tiny_config(tmp_path / "cache", epochs=2)
    a = train(oscillator, "gru", tmp_path / "a", replace(cfg, loss_units="normalised"), progress=False)
    b = train(oscillator, "gru", tmp_path / "b", cfg, progress=False)
    card = json.loads((b / "card.json").read_text())["training"]
    assert card["recipe"]["loss_units"] == "state" and "loss_units=state" in card["loss"]
    assert "loss_units" not in json.loads((a / "card.json").read_text())["training"]["recipe"]
    assert not all(torch.equal(weights(a)[k], weights(b)[k]) for k in weights(a))


@pytest.mark.slow
def test_training_learns_is_deterministic_and_writes_a_card(oscillator, tmp_path):
    cfg = tiny_config(tmp_path / "cache", epochs=4, eval_trajectories=5)
    a = train(oscillator, "gru", tmp_path / "a", cfg, progress=False)
    b = train(oscillator, "gru", tmp_path / "b", cfg, progress=False)
    wa, wb = weights(a), weights(b)
    assert all(torch.equal(wa[k], wb[k]) for k in wa)
    c = train(oscillator, "gru", tmp_path / "c", replace(cfg, init_seed=1), progress=False)
    assert not all(torch.equal(wa[k], weights(c)[k]) for k in wa)
    card = json.loads((a / "card.json").read_text())
    hist = card["training"]["history"]
    assert len(hist) == 4
    assert hist[-1]["val_loss"] < hist[0]["val_loss"] and hist[-1]["train_loss"] < hist[0]["train_loss"]
    assert card["validation_loss"] == min(h["val_loss"] for h in hist)
    assert card["data"] == {
        "seed": 0,
        "index": 0,
        "data_ratio": 20.0,
        "train_trajectories": 12,
        "train_length": 60,
        "val_trajectories": 6,
        "windows_per_epoch": 48,
    }
    assert card["init_seed"] == 0 and card["training"]["recipe"]["lr"] == 2e-3
    assert card["training"]["stopped"] == "max epochs" and card["metrics"]["rmse"] > 0
    assert card["normalization"]["dy"] == 1 and card["created"]
    # no pickle anywhere: the checkpoint and its resume state are safetensors and JSON, and the step graph
    assert {p.suffix for p in a.rglob("*") if p.is_file()} == {".json", ".safetensors", ".onnx"}
    est = load_neural_estimator("gru", oscillator, a)
    assert est.run(np.zeros((1, 7, 1))).x.shape == (1, 7, 2)
    # train wrote the batch-1 step beside the card: the per-message default serves it, equal to torch
    served = load_neural_estimator("gru", oscillator, a, backend="auto")
    assert served.backend == "onnxruntime" and type(served).__name__ == "OnnxEstimator"
    est.reset(1)
    served.reset(1)
    for y in np.linspace(-1.0, 1.0, 20):
        np.testing.assert_allclose(served.step(np.array([[y]])), est.step(np.array([[y]])), rtol=1e-5, atol=1e-6)


def test_angle_scenario_trains(spinner, tmp_path):
    out = train(spinner, "gru", tmp_path / "s", tiny_config(tmp_path / "cache", epochs=3), progress=False)
    hist = json.loads((out / "card.json").read_text())["training"]["history"]
    assert all(math.isfinite(h["val_loss"]) for h in hist) and hist[-1]["val_loss"] < hist[0]["val_loss"]


@pytest.mark.slow
def test_resume_matches_an_uninterrupted_run(oscillator, tmp_path):
    cfg = tiny_config(tmp_path / "cache", epochs=4)
    full = train(oscillator, "gru", tmp_path / "full", cfg, progress=False)
    part = tmp_path / "part"
    train(oscillator, "gru", part, replace(cfg, epochs=2), progress=False)
    assert json.loads((part / "resume" / "state.json").read_text())["run"]["epoch"] == 2
    train(oscillator, "gru", part, replace(cfg, resume=True), progress=False)
    for name in ("", "resume"):
        wf, wp = weights(full / name), weights(part / name)
        assert all(torch.equal(wf[k], wp[k]) for k in wf)
    hf = json.loads((full / "card.json").read_text())["training"]["history"]
    hp = json.loads((part / "card.json").read_text())["training"]["history"]
    assert [h["val_loss"] for h in hf] == [h["val_loss"] for h in hp] and len(hp) == 4
    with pytest.raises(TrainingError, match=r"other settings: lr=0\.002 \(resume state\) vs 0\.001 \(now\)"):
        train(oscillator, "gru", part, replace(cfg, resume=True, lr=1e-3), progress=False)


def test_early_stopping_on_a_plateau(oscillator, tmp_path):
    # lr so small that float32 weights never change: the validation loss is exactly flat
    cfg = tiny_config(tmp_path / "cache", epochs=20, patience=2, lr=1e-30)
    out = train(oscillator, "gru", tmp_path / "flat", cfg, progress=False)
    tr = json.loads((out / "card.json").read_text())["training"]
    assert tr["epochs_run"] == 3 and tr["best_epoch"] == 1
    assert tr["stopped"].startswith("early stopping")
    # resumed with a larger patience, it goes on until that patience runs out too
    train(oscillator, "gru", out, replace(cfg, patience=4, resume=True), progress=False)
    tr = json.loads((out / "card.json").read_text())["training"]
    assert tr["epochs_run"] == 5 and tr["best_epoch"] == 1 and tr["stopped"].startswith("early stopping")


def test_config_is_checked():
    with pytest.raises(TrainingError, match="window must be in"):
        TrainConfig(window=600)
    with pytest.raises(TrainingError, match="warmup must be in"):
        TrainConfig(window=10, warmup=10)
    with pytest.raises(TrainingError, match="classical filter"):
        train("oscillator", "ekf", "/nonexistent", TrainConfig(), progress=False)
    with pytest.raises(TrainingError, match=r"gru has no hyperparameter\(s\) \['hiden'\]"):
        train("oscillator", "gru", "/nonexistent", TrainConfig(model_overrides={"hiden": 8}), progress=False)


@pytest.mark.slow
def test_compiled_step_equals_eager_step(oscillator, tmp_path):
    """compile_step serves the same estimates (float32 round-off) through torch.compile."""

    data = simulate(oscillator, 8, 40, seed=0)
    norm = Normalizer.from_data(oscillator, data)
    torch.manual_seed(0)
    model = build_model("gru", oscillator)
    eager = NeuralEstimator(oscillator, model, norm, "gru")
    compiled = NeuralEstimator(oscillator, model, norm, "gru", compile_step="true")
    a, b = eager.run(data.y[:2], data.u[:2]).x, np.empty((2, 40, 2))
    compiled.reset(2)
    for k in range(40):
        b[:, k] = compiled.step(data.y[:2, k])
    np.testing.assert_allclose(a, b, atol=1e-5)
    with pytest.raises(EstimatorError, match="compile_step must be true or false"):
        NeuralEstimator(oscillator, model, norm, "gru", compile_step="maybe")


# ---- bounded-context validation (a variant of the recipe, not the paper's) --------------------------
def test_val_context_recipe_is_checked_and_recorded_only_when_set():
    assert "val_context" not in TrainConfig().recipe() and "val_context_copies" not in TrainConfig().recipe()
    r = TrainConfig(val_context=100, val_context_copies=4).recipe()
    assert (r["val_context"], r["val_context_copies"]) == (100, 4)
    with pytest.raises(TrainingError, match="val_context must be >= 0"):
        TrainConfig(val_context=-1)
    with pytest.raises(TrainingError, match="must not exceed val_context"):
        TrainConfig(val_context=3, val_context_copies=4)


def test_val_context_validates_bounded_and_the_model_serves_bounded(tmp_path, spinner, monkeypatch):
    import neural_estimator.training.loop as training

    calls = []
    real = training.bounded_forward

    def spy(model, z, length, copies):
        calls.append((z.shape[1], length, copies))
        return real(model, z, length, copies)

    monkeypatch.setattr(training, "bounded_forward", spy)
    cfg = tiny_config(tmp_path / "cache", epochs=1, eval_trajectories=4)
    plain = train(spinner, "gru", tmp_path / "plain", cfg, progress=False)
    assert calls == []
    cfg_bounded = replace(cfg, val_context=10, val_context_copies=2)
    bounded = train(spinner, "gru", tmp_path / "bounded", cfg_bounded, progress=False)
    assert calls and all(c[1:] == (10, 2) and c[0] == cfg.train_length for c in calls)
    a, b = (json.loads((d / "card.json").read_text()) for d in (plain, bounded))
    # the same training (validation draws nothing), another validation loss
    assert a["training"]["history"][0]["train_loss"] == b["training"]["history"][0]["train_loss"]
    assert a["validation_loss"] != b["validation_loss"]
    assert b["metrics"]["set"]["context"] == 10 and "context" not in a["metrics"]["set"]
    assert "bounded to 10 steps" in b["training"]["validation"]
    est = load_neural_estimator("gru", spinner, checkpoint=bounded)
    assert (est.context, est.context_copies) == (10, 2)  # as it was validated
    # train wrote its step.onnx (the two copies at batch 2): the per-message default serves it as torch does
    served = load_neural_estimator("gru", spinner, checkpoint=bounded, backend="auto")
    assert type(served).__name__ == "OnnxEstimator" and (served.context, served.context_copies) == (10, 2)
    data = simulate(spinner, 1, 35, 3)
    y, u = data.y[0], previous_controls(data.u)[0]
    served.reset(1)
    est.reset(1)
    for k in range(35):  # every copy restarts three or four times
        a, b = est.step(y[k : k + 1], u[k : k + 1]), served.step(y[k : k + 1], u[k : k + 1])
        np.testing.assert_allclose(b, a, rtol=1e-5, atol=1e-5 * (1.0 + np.abs(a).max()))
    assert load_neural_estimator("gru", spinner, checkpoint=bounded, context=0).context == 0
    assert load_neural_estimator("gru", spinner, checkpoint=plain).context == 0
    assert load_neural_estimator("gru", spinner, checkpoint=plain, context=10).context_copies == 10
    with pytest.raises(TrainingError, match="sets gpt2's attention window decode_chunk"):
        cfg_conflict = replace(cfg, val_context=10, model_overrides={"decode_chunk": 20})
        train(spinner, "gpt2", tmp_path / "g", cfg_conflict, progress=False)


def test_val_context_of_an_attention_model_is_its_window(tmp_path, spinner):
    """GPT-2 with val_context=L: the model is built, validated, scored and served with attention
    window L (the paper's 256 otherwise); with L >= the training windows its training is the paper's."""
    cfg = tiny_config(tmp_path / "cache", epochs=1, eval_trajectories=4, model_overrides={"n_embd": 8})
    plain = train(spinner, "gpt2", tmp_path / "plain", cfg, progress=False)
    bounded = train(spinner, "gpt2", tmp_path / "bounded", replace(cfg, val_context=8), progress=False)
    a, b = (json.loads((d / "card.json").read_text()) for d in (plain, bounded))
    assert a["architecture"]["config"]["decode_chunk"] == 256 and b["architecture"]["config"]["decode_chunk"] == 8
    assert "its attention window" in b["training"]["validation"] and b["metrics"]["set"]["context"] == 8
    assert cfg.window > 8  # here the window binds in training too: another run
    assert a["training"]["history"][0]["train_loss"] != b["training"]["history"][0]["train_loss"]
    est = load_neural_estimator("gpt2", spinner, checkpoint=bounded)
    assert est.context == 8 and est.model.cfg.decode_chunk == 8
    wide = replace(cfg, val_context=cfg.window)  # the window never binds in training: the same training
    same = train(spinner, "gpt2", tmp_path / "same", wide, progress=False)
    c = json.loads((same / "card.json").read_text())
    assert c["training"]["history"][0]["train_loss"] == a["training"]["history"][0]["train_loss"]


def test_converged_rule():
    from neural_estimator.training.stopping import converged, lr_reductions

    hist = [{"lr": lr} for lr in (2e-3, 1e-3, 1e-3, 5e-4, 2.5e-4)]
    assert lr_reductions(hist, 2e-3) == 3 and converged(None, hist, 2e-3)
    assert not converged("max epochs", hist[:3], 2e-3)
    assert converged("early stopping: no lower validation loss in 30 epochs", [], 2e-3)


def _history(vals, lrs):
    return [{"epoch": i + 1, "val_loss": v, "lr": lr} for i, (v, lr) in enumerate(zip(vals, lrs))]


def test_plateau_rule_stops_flat_curves_after_three_halvings_only():
    from neural_estimator.training.stopping import plateau_rule

    stop = plateau_rule(2e-3, epochs=4, tol=0.01)
    halved = [2e-3] * 2 + [1e-3] * 2 + [5e-4] * 2 + [2.5e-4] * 2  # 3 reductions within 8 epochs
    flat = _history([1.0, 0.8, 0.6, 0.5, 0.5, 0.499, 0.5, 0.4996], halved)
    assert "plateau" in stop(flat) and "3 learning-rate reductions" in stop(flat)
    assert stop(flat[:7]) is None  # fewer than 2 x 4 epochs
    assert stop(_history([v for v in (1.0, 0.8, 0.6, 0.5, 0.5, 0.499, 0.5, 0.4996)], [2e-3] * 4 + [1e-3] * 4)) is None
    # still falling by more than 1 % window on window
    assert stop(_history([1.0, 0.8, 0.6, 0.5, 0.49, 0.48, 0.47, 0.46], halved)) is None
    # a lucky first epoch, then a curve coming down from a high: improving, not flat (a rule against
    # the best so far, 0.5, would stop it)
    lucky = _history([0.5, 0.9, 0.88, 0.85, 0.8, 0.75, 0.7, 0.65, 0.6], [2e-3, 1e-3, 5e-4] + [2.5e-4] * 6)
    assert plateau_rule(2e-3, epochs=3, tol=0.01)(lucky) is None
    # rising after an early best: the last window is worse than the one before, so it is a plateau
    assert stop(_history([0.5, 0.4, 0.45, 0.5, 0.6, 0.7, 0.8, 0.9], halved)) is not None
    with pytest.raises(TrainingError, match="plateau rule"):
        plateau_rule(2e-3, epochs=0)
    with pytest.raises(TrainingError, match="plateau rule"):
        plateau_rule(2e-3, tol=1.5)


def test_train_ends_where_stop_when_says_and_a_resume_without_it_goes_on(tmp_path, spinner):
    cfg = tiny_config(tmp_path / "cache", epochs=4, eval_trajectories=4, keep_resume=True)
    seen = []

    def stop_when(history):
        seen.append(len(history))
        return "stopped by the test rule" if len(history) == 2 else None

    out = train(spinner, "gru", tmp_path / "run", cfg, progress=False, stop_when=stop_when)
    card = json.loads((out / "card.json").read_text())
    assert seen == [1, 2] and card["training"]["stopped"] == "stopped by the test rule"
    assert card["training"]["epochs_run"] == 2 and card["metrics"]["set"]["trajectories"] == 4
    # resumed without the rule: the rule's stop does not hold, training continues to the epoch budget
    cfg = dataclasses.replace(cfg, resume=True)
    train(spinner, "gru", tmp_path / "run", cfg, progress=False)
    card = json.loads((out / "card.json").read_text())
    assert card["training"]["epochs_run"] == 4 and card["training"]["stopped"] == "max epochs"


def test_training_caps_trajectories_at_the_scenarios_longest_informative_length(tmp_path):
    quad = make_scenario("quadrotor", horizon=40)  # the quadrotor's limit is its horizon
    assert quad.longest_training_trajectory == 40 and make_scenario("lorenz96").longest_training_trajectory is None
    out = train(
        quad, "gru", tmp_path / "q", tiny_config(tmp_path / "cache", epochs=1, eval_trajectories=3), progress=False
    )
    card = json.loads((out / "card.json").read_text())
    assert card["data"]["train_length"] == 40 and card["training"]["recipe"]["train_length"] == 40
