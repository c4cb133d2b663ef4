"""Neural estimators: normalisation, run == step, checkpoints (safetensors + JSON), training protocol."""

import dataclasses
import json
import math
import pickle
import shutil
from dataclasses import dataclass, replace

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from neural_estimator.data import simulate
from neural_estimator.methods.registry import EstimatorError, make_estimator
from neural_estimator.models import ARCHITECTURES, build_model
from neural_estimator.serving.checkpoint import save_checkpoint
from neural_estimator.serving.load import load_neural_estimator
from neural_estimator.serving.neural import NeuralEstimator, resolve_device
from neural_estimator.serving.normalization import Normalizer
from neural_estimator.training.loop import train
from neural_estimator.training.loss import state_error, weighted_loss
from neural_estimator.training.recipe import TrainConfig, TrainingError
from neural_estimator.scenarios import Scenario, make_scenario, register_scenario
from conftest import load_script

ARCHS = sorted(ARCHITECTURES)
TOL = 1e-5  # run vs a loop of step, float32 models


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tiny tensors: one intra-op thread


# ---- a small controlled system with an angular state (exercises u_{k-1} inputs and wrapping) ------
@dataclass(frozen=True)
class SpinnerConfig:
    dt: float = 0.1
    horizon: int = 80
    noise_scale: float = 1.0
    friction: float = 0.1
    process_noise_std: float = 0.05
    obs_noise_std: float = 0.1


@register_scenario
class Spinner(Scenario):
    """A rotor driven by a random torque: angle (wrapped) and rate, the angle observed."""

    name = "test_spinner"
    Config = SpinnerConfig
    state_names = ("angle", "rate")
    state_units = ("rad", "rad/s")
    obs_names = ("angle",)
    obs_units = ("rad",)
    control_names = ("torque",)
    control_units = ("N m",)
    angle_states = (0,)
    angle_obs = (0,)

    def f(self, x, u):
        c = self.config
        return np.stack([x[..., 0] + c.dt * x[..., 1], x[..., 1] + c.dt * (u[..., 0] - c.friction * x[..., 1])], -1)

    def h(self, x):
        return x[..., :1]

    def process_cov(self):
        return np.diag([1e-6, self.config.process_noise_std**2])

    def obs_cov_nominal(self):
        return np.array([[self.config.obs_noise_std**2]])

    def prior(self):
        return np.array([0.0, 2.0]), np.diag([1.0, 1.0])

    def sample_controls(self, rng, n, horizon):
        return 0.5 * rng.standard_normal((n, horizon, 1))


@pytest.fixture
def spinner():
    return Spinner()


def tiny_config(cache, **kw):
    base = dict(
        trajectories=12,
        val_trajectories=6,
        train_length=60,
        window=20,
        warmup=5,
        windows_per_epoch=48,
        batch_size=16,
        epochs=3,
        model_overrides={"hidden": 8},
        cache_dir=str(cache),
    )
    base.update(kw)
    return TrainConfig(**base)


def estimator_for(scenario, arch, data, seed=0, head=False):
    """A freshly initialised model of ``arch``; ``head``: with a random covariance head on its trunk."""
    torch.manual_seed(seed)
    norm = Normalizer.from_data(scenario, data)
    model = build_model(arch, scenario)
    if head:
        from neural_estimator.serving.uncertainty.heads import CholeskyHead, GaussianModel

        cov_head = CholeskyHead(model.features(torch.zeros(1, 1, norm.d_in)).shape[-1], scenario.dx)
        with torch.no_grad():
            cov_head.linear.weight.normal_(0.0, 0.1)
        model = GaussianModel(model, cov_head)
    return NeuralEstimator(scenario, model, norm, arch)


def weights(path):
    return load_file(str(path / "model.safetensors"))


# ---- normalisation --------------------------------------------------------------------------------
def test_normalizer_round_trip_and_statistics(spinner):
    data = simulate(spinner, 20, 50, seed=0)
    norm = Normalizer.from_data(spinner, data)
    from neural_estimator.methods.registry import previous_controls

    z, skipped = norm.normalize_inputs(data.y, previous_controls(data.u))
    assert z.shape == (20, 50, 2) and not skipped.any()
    np.testing.assert_allclose(z.reshape(-1, 2).mean(0), 0.0, atol=1e-12)
    np.testing.assert_allclose(z.reshape(-1, 2).std(0), 1.0, atol=1e-12)
    # angles: predicted in radians (mean 0, std 1), wrapped on the way out
    assert norm.out_mean[0] == 0.0 and norm.out_std[0] == 1.0 and norm.out_std[1] != 1.0
    xn = norm.normalize_states(data.x)
    np.testing.assert_allclose(norm.denormalize_states(xn), data.x, atol=1e-12)
    assert norm.denormalize_states(np.array([[3 * np.pi / 2, 0.0]]))[0, 0] == pytest.approx(-np.pi / 2)
    # JSON round trip is exact
    back = Normalizer.from_dict(json.loads(json.dumps(norm.to_dict())))
    for name in ("in_mean", "in_std", "out_mean", "out_std"):
        np.testing.assert_array_equal(getattr(back, name), getattr(norm, name))
    assert back.angle_states == (0,) and (back.dy, back.du) == (1, 1)
    # covariance maps back with diag(std) C diag(std)
    np.testing.assert_allclose(norm.denormalize_covariance(np.eye(2)), np.diag(norm.out_std**2))


def test_normalizer_floor_and_unusable_observations():
    rng = np.random.default_rng(0)
    y, x = rng.normal(5.0, 2.0, (4, 10, 2)), rng.normal(size=(4, 10, 3))
    u = np.zeros((4, 10, 1))  # a control that never varies
    norm = Normalizer.fit(y, u, x)
    assert norm.in_std[2] == pytest.approx(1e-6)
    z, skipped = norm.normalize_inputs(np.array([[np.nan, 1.0], [5.0, 5.0]]), np.zeros((2, 1)))
    assert skipped.tolist() == [True, False]
    assert z[0].tolist() == [0.0, 0.0, 0.0] and np.all(np.isfinite(z))


# ---- the estimator: run equals a loop of step, past the training length -----------------------------
@pytest.mark.parametrize("head", [False, True], ids=["own", "covariance-head"])
@pytest.mark.parametrize("arch", ARCHS)
def test_run_equals_step_loop(arch, spinner, head):
    data = simulate(spinner, 6, 300, seed=1)
    est = estimator_for(spinner, arch, data, head=head)
    Y = data.y[:3].copy()
    Y[1, 40] = np.nan  # an unusable observation: the training mean in its place, in both forms
    out = est.run(Y, data.u[:3])
    assert out.x.shape == (3, 300, 2) and out.x.dtype == np.float64 and not out.diverged.any()
    est.reset(3)
    prev = np.zeros((3, 1))
    xs, covs = [], []
    for k in range(300):
        xs.append(est.step(Y[:, k], prev))
        prev = data.u[:3, k]
        if k == 40:
            assert est.skipped.tolist() == [False, True, False]
        if est.has_covariance:
            covs.append(est.covariance)
    assert np.abs(out.x - np.stack(xs, 1)).max() <= TOL
    assert np.all(np.abs(out.x[..., 0]) <= np.pi)  # the angle comes out wrapped
    assert est.has_covariance == (head or arch == "filterformer")
    if est.has_covariance:
        assert out.cov.shape == (3, 300, 2, 2)
        assert np.abs(out.cov - np.stack(covs, 1)).max() <= TOL * max(1.0, np.abs(out.cov).max())
        assert np.all(np.linalg.eigvalsh(out.cov) > 0)


def test_estimator_checks_inputs(oscillator):
    est = estimator_for(oscillator, "gru", simulate(oscillator, 4, 20, seed=0))
    est.step(np.zeros((3, 1)))  # a step before reset starts y's batch (the Estimator contract)
    assert est.batch == 3
    est.reset(2)
    with pytest.raises(EstimatorError, match=r"observation must be \(B, 1\)"):
        est.step(np.zeros((2, 3)))
    with pytest.raises(EstimatorError, match="batch of 1 observations, but reset for 2"):
        est.step(np.zeros((1, 1)))
    assert est.model.training is False
    if not torch.cuda.is_available():
        with pytest.raises(EstimatorError, match="sees no CUDA GPU"):
            resolve_device("cuda")
    with pytest.raises(EstimatorError, match="unknown device"):
        resolve_device("tpu9")


# ---- checkpoints ----------------------------------------------------------------------------------
def _save(tmp_path, scenario, arch, name="ckpt"):
    data = simulate(scenario, 4, 30, seed=0)
    est = estimator_for(scenario, arch, data)
    path = save_checkpoint(tmp_path / name, est.model, est.normalizer, {"scenario": scenario.describe()})
    return est, path, data


@pytest.mark.parametrize("arch", ARCHS)
def test_checkpoint_round_trip_gives_identical_outputs(arch, oscillator, tmp_path):
    est, path, data = _save(tmp_path, oscillator, arch)
    assert sorted(p.name for p in path.iterdir()) == ["card.json", "model.safetensors"]
    back = load_neural_estimator(arch, oscillator, path)
    a, b = est.run(data.y, data.u), back.run(data.y, data.u)
    np.testing.assert_array_equal(a.x, b.x)
    card = back.card
    assert card["method"] == arch and card["architecture"]["name"] == arch
    assert card["architecture"]["parameters"] == sum(p.numel() for p in est.model.parameters())
    assert card["scenario"] == oscillator.describe()
    assert {"torch", "numpy", "safetensors", "neural_estimator"} <= set(card["software"])
    # the card path works too, and so does the registry
    again = make_estimator(arch, oscillator, checkpoint=path / "card.json")
    np.testing.assert_array_equal(again.run(data.y, data.u).x, a.x)


def test_a_model_whose_weights_share_one_buffer_saves_and_loads(oscillator, tmp_path):
    """cuDNN packs a GRU's weights into one buffer on a GPU; the same packing, made here by hand,
    must save (a plain copy) and load to the same outputs."""
    data = simulate(oscillator, 4, 30, seed=0)
    est = estimator_for(oscillator, "gru", data)
    before = est.run(data.y, data.u).x
    params = list(est.model.parameters())
    flat = torch.cat([p.detach().reshape(-1) for p in params])
    offset = 0
    for p in params:
        p.data = flat[offset : offset + p.numel()].view_as(p)
        offset += p.numel()
    assert params[0].untyped_storage().data_ptr() == params[-1].untyped_storage().data_ptr()
    path = save_checkpoint(tmp_path / "packed", est.model, est.normalizer, {"scenario": oscillator.describe()})
    np.testing.assert_array_equal(load_neural_estimator("gru", oscillator, path).run(data.y, data.u).x, before)
    assert params[0].untyped_storage().data_ptr() == flat.untyped_storage().data_ptr()  # the model untouched


def test_loading_never_unpickles(oscillator, tmp_path, monkeypatch):
    _, path, data = _save(tmp_path, oscillator, "gru")

    def forbidden(*args, **kwargs):
        raise AssertionError("a checkpoint load reached torch.load / pickle")

    monkeypatch.setattr(torch, "load", forbidden)
    monkeypatch.setattr(pickle, "load", forbidden)
    monkeypatch.setattr(pickle, "loads", forbidden)
    monkeypatch.setattr(pickle, "Unpickler", forbidden)
    load_neural_estimator("gru", oscillator, path).run(data.y, data.u)


def test_loading_refuses_the_wrong_checkpoint(oscillator, spinner, tmp_path):
    _, path, _ = _save(tmp_path, oscillator, "gru")
    with pytest.raises(
        EstimatorError,
        match=r"was trained on scenario 'oscillator' \(dx=2, dy=1, du=0\), "
        r"not 'test_spinner' \(dx=2, dy=1, du=1\)",
    ):
        load_neural_estimator("gru", spinner, path)
    with pytest.raises(EstimatorError, match="holds a 'gru' model, not 'lstm'"):
        load_neural_estimator("lstm", oscillator, path)
    with pytest.raises(EstimatorError, match=r"other constants: omega=1\.0 \(checkpoint\) vs 2\.0 \(requested\)"):
        load_neural_estimator("gru", make_scenario("oscillator", omega=2.0), path)
    # the evaluation-only constants may differ (the noise-robustness study)
    load_neural_estimator("gru", make_scenario("oscillator", noise_scale=3.0, horizon=50), path)
    # other dimensions under the same name
    card = json.loads((path / "card.json").read_text())
    card["scenario"]["state_names"].append("extra")
    (path / "card.json").write_text(json.dumps(card))
    with pytest.raises(EstimatorError, match=r"with dx=3, dy=1, du=0, but the requested one has dx=2, dy=1, du=0"):
        load_neural_estimator("gru", oscillator, path)


def test_loading_names_missing_and_corrupt_files(oscillator, tmp_path):
    _, path, _ = _save(tmp_path, oscillator, "gru")
    blob = (path / "model.safetensors").read_bytes()
    (path / "model.safetensors").write_bytes(blob[:-7] + b"garbage")
    with pytest.raises(EstimatorError, match="model.safetensors does not match the sha256"):
        load_neural_estimator("gru", oscillator, path)
    card = json.loads((path / "card.json").read_text())
    del card["weights"]["sha256"]
    (path / "card.json").write_text(json.dumps(card))
    broken = b"\x08\x00\x00\x00\x00\x00\x00\x00{broken}"
    # far smaller than the card's model: refused by its size before anything is allocated or parsed
    (path / "model.safetensors").write_bytes(broken)
    with pytest.raises(EstimatorError, match="weight file holds 16 bytes: card and weights do not belong"):
        load_neural_estimator("gru", oscillator, path)
    # the model's size but not a safetensors file: the parser's refusal, named
    (path / "model.safetensors").write_bytes(broken + bytes(len(blob)))
    with pytest.raises(EstimatorError, match="cannot read model.safetensors"):
        load_neural_estimator("gru", oscillator, path)
    (path / "model.safetensors").unlink()
    with pytest.raises(EstimatorError, match="weight file model.safetensors is missing"):
        load_neural_estimator("gru", oscillator, path)
    (path / "card.json").write_text('{"format": "neural_estimator.checkpoint", ')
    with pytest.raises(EstimatorError, match=r"card.json: checkpoint card is corrupt \(not valid JSON"):
        load_neural_estimator("gru", oscillator, path)
    (path / "card.json").unlink()
    with pytest.raises(EstimatorError, match="card.json: checkpoint card is missing"):
        load_neural_estimator("gru", oscillator, path)
    with pytest.raises(EstimatorError, match="does not exist"):
        load_neural_estimator("gru", oscillator, tmp_path / "nowhere")
    with pytest.raises(
        EstimatorError,
        match=r"no trained gru model ships for scenario 'oscillator'.*lacks card.json "
        r"and model.safetensors.*neural-estimator train --scenario oscillator "
        r"--model gru --out",
    ):
        make_estimator("gru", oscillator)


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
    from neural_estimator.data import simulate
    from neural_estimator.models import build_model
    from neural_estimator.serving.neural import NeuralEstimator
    from neural_estimator.serving.normalization import Normalizer

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


# ---- the zoo script: resumable across runs, cards with budget and convergence ---------------------
def _train_zoo():
    return load_script("scripts/train_zoo.py")


@pytest.mark.slow
def test_train_zoo_resumes_unfinished_models_and_installs_finished_ones(tmp_path, monkeypatch):
    import time
    from types import SimpleNamespace

    import neural_estimator.training.loop as training

    monkeypatch.setenv("NEURAL_ESTIMATOR_CACHE", str(tmp_path / "cache"))
    zoo_script = _train_zoo()
    state, zoo = tmp_path / "state", tmp_path / "zoo"
    args = [
        "--scenarios",
        "test_spinner",
        "--methods",
        "gru",
        "--state",
        str(state),
        "--zoo",
        str(zoo),
        "--trajectories",
        "12",
        "--windows-per-epoch",
        "48",
        "--val-trajectories",
        "6",
        "--eval-trajectories",
        "4",
        "--max-epochs",
        "3",
        "--hours",
        "1",
        "--quiet",
    ]
    work = state / "test_spinner-gru"
    # first run: the session's time runs out after two epochs (train() reads the clock before each epoch)
    checks = iter([0.0, 0.0])  # read before each epoch: two epochs start, the third does not
    clock = SimpleNamespace(time=lambda: next(checks, 1e12), perf_counter=time.perf_counter)
    monkeypatch.setattr(training, "time", clock)
    monkeypatch.setattr(zoo_script.time, "time", lambda: 0.0)
    assert zoo_script.main(args) == 0
    run = zoo_script.resume_state(work)
    assert run["epoch"] == 2 and not zoo_script.finished(work) and not (zoo / work.name).exists()
    # the next run resumes from epoch 2 and finishes the epoch budget
    monkeypatch.undo()
    monkeypatch.setenv("NEURAL_ESTIMATOR_CACHE", str(tmp_path / "cache"))
    assert zoo_script.main(args) == 0
    card = json.loads((zoo / work.name / "card.json").read_text())
    t = card["training"]
    assert [h["epoch"] for h in t["history"]] == [1, 2, 3] and t["stopped"] == "max epochs"
    assert t["budget"]["max_epochs"] == 3 and t["budget"]["windows_per_epoch"] == 48
    assert t["converged"] is False and t["lr_reductions"] == 0
    assert card["metrics"]["set"]["trajectories"] == 4
    assert sorted(p.name for p in (zoo / work.name).iterdir()) == ["card.json", "model.safetensors", "step.onnx"]
    assert zoo_script.finished(work)
    # the resumed run equals an uninterrupted one
    ref = train(
        "test_spinner",
        "gru",
        tmp_path / "ref",
        TrainConfig(
            trajectories=12,
            windows_per_epoch=48,
            val_trajectories=6,
            epochs=3,
            eval_trajectories=4,
            cache_dir=str(tmp_path / "cache"),
        ),
        progress=False,
    )
    w_ref, w_zoo = weights(ref), weights(zoo / work.name)
    assert all(torch.equal(w_ref[k], w_zoo[k]) for k in w_ref)


def test_train_zoo_finish_installs_an_unfinished_model_as_it_stands(tmp_path, monkeypatch):
    import time
    from types import SimpleNamespace

    import neural_estimator.training.loop as training

    monkeypatch.setenv("NEURAL_ESTIMATOR_CACHE", str(tmp_path / "cache"))
    zoo_script = _train_zoo()
    state, zoo = tmp_path / "state", tmp_path / "zoo"
    args = ["--scenarios", "test_spinner", "--methods", "gru", "--state", str(state), "--zoo", str(zoo)]
    args += ["--trajectories", "12", "--windows-per-epoch", "48", "--val-trajectories", "6"]
    args += ["--eval-trajectories", "4", "--max-epochs", "50", "--quiet"]
    work = state / "test_spinner-gru"
    assert zoo_script.main([*args, "--finish"]) == 0  # not started: nothing to finish, nothing installed
    assert not work.exists() and not zoo.exists()
    checks = iter([0.0])  # one epoch starts, then the session's time is up
    monkeypatch.setattr(
        training, "time", SimpleNamespace(time=lambda: next(checks, 1e12), perf_counter=time.perf_counter)
    )
    monkeypatch.setattr(zoo_script.time, "time", lambda: 0.0)
    assert zoo_script.main([*args, "--hours", "1"]) == 0
    monkeypatch.undo()
    monkeypatch.setenv("NEURAL_ESTIMATOR_CACHE", str(tmp_path / "cache"))
    assert zoo_script.resume_state(work)["epoch"] == 1 and not zoo_script.finished(work)
    assert zoo_script.main([*args, "--finish"]) == 0
    card = json.loads((zoo / work.name / "card.json").read_text())
    t = card["training"]
    assert len(t["history"]) == 1 and t["stopped"].startswith("finished by hand (--finish) after 1 epochs")
    assert t["budget"]["max_epochs"] == 50 and card["metrics"]["set"]["trajectories"] == 4
    assert zoo_script.finished(work)


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


def test_train_zoo_does_not_install_a_model_that_never_beat_its_first_epoch(tmp_path):
    zoo_script = _train_zoo()
    work = tmp_path / "s-m"
    work.mkdir()
    card = {"validation_loss": 0.5, "training": {"history": [{"val_loss": 0.5}, {"val_loss": 0.7}]}}
    (work / "card.json").write_text(json.dumps(card))
    assert "never went below its first epoch" in zoo_script.not_installable(work)
    card["validation_loss"] = 0.4
    card["training"]["history"].append({"val_loss": 0.4})
    (work / "card.json").write_text(json.dumps(card))
    assert zoo_script.not_installable(work) is None
    card = {"validation_loss": 0.5, "training": {"history": [{"val_loss": 0.5}]}}  # --finish after one epoch
    (work / "card.json").write_text(json.dumps(card))
    assert zoo_script.not_installable(work) is None


def test_train_zoo_prune_never_removes_the_weights_of_a_zoo_kept_inside_the_state(tmp_path, capsys):
    """``--prune --state S --zoo S/zoo``: the zoo's own folders carry cards too, and comparing one
    with itself must not count as "the zoo ships the same weights"."""
    zoo_script = _train_zoo()
    state, zoo = tmp_path / "v5", tmp_path / "v5" / "zoo"
    finished_card = json.dumps({"training": {"stopped": "plateau"}})
    for folder in (state / "s-m", zoo / "s-m"):
        folder.mkdir(parents=True)
        (folder / "card.json").write_text(finished_card)
        (folder / "model.safetensors").write_bytes(b"same weights")
    (state / "s-m" / "resume").mkdir()
    assert zoo_script.main(["--prune", "--state", str(state), "--zoo", str(zoo)]) == 0
    assert (zoo / "s-m" / "model.safetensors").read_bytes() == b"same weights"  # the shipped copy stays
    assert sorted(f.name for f in (state / "s-m").iterdir()) == ["card.json"]  # the training's copy goes
    assert "zoo/s-m: nothing to remove" in capsys.readouterr().out


@pytest.mark.slow
def test_train_zoo_keeps_the_shipped_model_unless_the_new_one_scores_lower_on_the_same_set(
    tmp_path, monkeypatch, capsys
):
    monkeypatch.setenv("NEURAL_ESTIMATOR_CACHE", str(tmp_path / "cache"))
    zoo_script = _train_zoo()
    zoo = tmp_path / "zoo"
    args = ["--scenarios", "test_spinner", "--methods", "gru", "--zoo", str(zoo)]
    args += ["--trajectories", "12", "--windows-per-epoch", "48", "--val-trajectories", "6"]
    args += ["--eval-trajectories", "4", "--max-epochs", "2", "--quiet"]
    assert zoo_script.main([*args, "--state", str(tmp_path / "a")]) == 0
    shipped = zoo / "test_spinner-gru"
    first = json.loads((shipped / "card.json").read_text())
    stamp = (shipped / "card.json").stat().st_mtime_ns  # install copies the card with its mtime
    # the installed model is the finished one; the training keeps only its card (history and recipe)
    work = tmp_path / "a" / "test_spinner-gru"
    assert first == json.loads((work / "card.json").read_text())
    assert sorted(f.name for f in work.iterdir()) == ["card.json"]  # resume state and shipped weights pruned
    assert first["training"]["history"] and first["training"]["recipe"]
    capsys.readouterr()
    assert zoo_script.main([*args, "--state", str(tmp_path / "a"), "--install"]) == 0
    assert "its weights were pruned: the zoo ships it" in capsys.readouterr().out
    # with a model of these constants shipped, a plain run in a fresh state starts nothing
    assert zoo_script.main([*args, "--state", str(tmp_path / "b")]) == 0
    assert "the zoo ships a model of these constants, nothing to retrain" in capsys.readouterr().out
    assert not (tmp_path / "b" / "test_spinner-gru").exists()
    # the same recipe again trains the same model: not lower, so the shipped one stays
    assert zoo_script.main([*args, "--state", str(tmp_path / "b"), "--retrain"]) == 0
    out = capsys.readouterr().out
    assert "is not below the shipped model's" in out and "selection set: validation set 100" in out
    # not installed: the training keeps no resume state (its weights only where they differ from the shipped ones)
    kept = {f.name for f in (tmp_path / "b" / "test_spinner-gru").iterdir()}
    assert "card.json" in kept and "resume" not in kept and kept <= {"card.json", "model.safetensors"}
    # the selection set (validation data) is not the card's evaluation set
    assert zoo_script.selection_rmse(shipped, make_scenario("test_spinner"), 4) != first["metrics"]["rmse"]
    assert (shipped / "card.json").stat().st_mtime_ns == stamp
    # --no-compare installs it regardless
    assert zoo_script.main([*args, "--state", str(tmp_path / "c"), "--no-compare", "--retrain"]) == 0
    assert "installed" in capsys.readouterr().out
    assert (shipped / "card.json").stat().st_mtime_ns != stamp


@pytest.mark.slow
def test_train_zoo_val_context_trains_a_variant_that_replaces_no_shipped_model_until_installed(
    tmp_path, monkeypatch, capsys
):
    monkeypatch.setenv("NEURAL_ESTIMATOR_CACHE", str(tmp_path / "cache"))
    zoo_script = _train_zoo()
    monkeypatch.setattr(zoo_script, "ZOO", tmp_path / "zoo")  # the default zoo, were it used
    args = ["--scenarios", "test_spinner", "--methods", "gru", "--state", str(tmp_path / "s")]
    args += ["--trajectories", "12", "--windows-per-epoch", "48", "--val-trajectories", "6"]
    args += ["--eval-trajectories", "4", "--max-epochs", "1", "--quiet", "--val-context", "10"]
    assert zoo_script.main(args) == 0
    assert "not installed without --zoo" in capsys.readouterr().out and not (tmp_path / "zoo").exists()
    card = json.loads((tmp_path / "s" / "test_spinner-gru" / "card.json").read_text())
    assert card["training"]["recipe"]["val_context"] == 10 and card["metrics"]["set"]["context"] == 10
    # --install puts the finished variant into the shipped zoo without training it again
    stamp = (tmp_path / "s" / "test_spinner-gru" / "card.json").stat().st_mtime_ns
    assert zoo_script.main([*args, "--install"]) == 0
    assert "installed" in capsys.readouterr().out
    shipped = json.loads((tmp_path / "zoo" / "test_spinner-gru" / "card.json").read_text())
    assert shipped == card and (tmp_path / "s" / "test_spinner-gru" / "card.json").stat().st_mtime_ns == stamp
    # installed again, the same model does not score lower than itself: the shipped one stays
    assert zoo_script.main([*args, "--install"]) == 0
    assert "is not below the shipped model's" in capsys.readouterr().out
    # a model that has not finished (here: never started) is not installed
    lstm = ["--state", str(tmp_path / "s"), "--scenarios", "test_spinner", "--methods", "lstm"]
    assert zoo_script.main([*lstm, "--val-context", "10", "--install", "--quiet"]) == 0
    assert "not finished, nothing to install" in capsys.readouterr().out


def test_train_zoo_not_better_compares_rmse_only_when_both_exist():
    zoo_script = _train_zoo()
    assert zoo_script.not_better(0.5, None) is None  # nothing comparable ships
    assert zoo_script.not_better(0.5, 0.6) is None
    assert "0.5 is not below the shipped model's 0.4" in zoo_script.not_better(0.5, 0.4)
    assert "not below" in zoo_script.not_better(0.5, 0.5)  # a tie keeps the shipped model


@pytest.mark.slow
def test_train_zoo_finishes_a_model_on_the_plateau_rule(tmp_path, monkeypatch):
    monkeypatch.setenv("NEURAL_ESTIMATOR_CACHE", str(tmp_path / "cache"))
    zoo_script = _train_zoo()
    calls = []

    def fake_rule(initial_lr, epochs, tol):
        calls.append((initial_lr, epochs, tol))
        return lambda history: "plateau (test)" if len(history) == 2 else None

    monkeypatch.setattr(zoo_script, "plateau_rule", fake_rule)
    state, zoo = tmp_path / "state", tmp_path / "zoo"
    args = ["--scenarios", "test_spinner", "--methods", "gru", "--state", str(state), "--zoo", str(zoo)]
    args += ["--trajectories", "12", "--windows-per-epoch", "48", "--val-trajectories", "6"]
    args += ["--eval-trajectories", "4", "--max-epochs", "6", "--quiet"]
    assert zoo_script.main(args) == 0
    assert calls == [(2e-3, 10, 0.01)]  # the defaults: 10 epochs, 1 %
    t = json.loads((zoo / "test_spinner-gru" / "card.json").read_text())["training"]
    assert t["stopped"] == "plateau (test)" and t["epochs_run"] == 2
    assert zoo_script.finished(state / "test_spinner-gru")
    # --plateau-epochs 0: no rule at all
    calls.clear()
    assert (
        zoo_script.main(
            [
                *args,
                "--scenarios",
                "test_spinner",
                "--state",
                str(tmp_path / "s2"),
                "--plateau-epochs",
                "0",
                "--retrain",
            ]
        )
        == 0
    )
    assert calls == []
    t = json.loads((zoo / "test_spinner-gru" / "card.json").read_text())["training"]
    assert t["stopped"] == "max epochs" and t["epochs_run"] == 6


def test_every_shipped_model_is_full_recipe_and_converged_by_its_own_curve():
    """The zoo's bar: every shipped model had the paper's budget (20,000 windows per epoch) and converged,
    and its card's "converged" follows from its own history: early stopping (patience epochs after the
    best one, none lower) or >= 3 learning-rate reductions."""
    from pathlib import Path

    from neural_estimator.training.stopping import converged, lr_reductions

    zoo = Path(__file__).resolve().parents[1] / "neural_estimator" / "serving" / "zoo"
    cards = sorted(zoo.glob("*/card.json"))
    for path in cards:
        card = json.loads(path.read_text())
        t = card["training"]
        for key in ("converged", "budget", "lr_reductions", "convergence_rule", "history", "stopped"):
            assert key in t, f"{path}: training.{key} missing"
        hist, lr0 = t["history"], t["recipe"]["lr"]
        assert t["lr_reductions"] == lr_reductions(hist, lr0), path
        if t["stopped"].startswith("early stopping"):  # the curve must show it
            patience = t["recipe"]["patience"]
            best = min(range(len(hist)), key=lambda i: hist[i]["val_loss"])
            assert len(hist) - 1 - best >= patience, f"{path}: early stopping without {patience} epochs after the best"
        assert t["converged"] == converged(t["stopped"], hist, lr0), path
        assert t["budget"]["windows_per_epoch"] >= 20000, f"{path}: not the paper's 20,000 windows per epoch"
        assert t["converged"], f"{path}: shipped before it converged"
    assert len(cards) == 30  # five scenarios x six methods


def test_train_zoo_finishes_a_model_whose_wall_budget_is_spent(tmp_path, monkeypatch):
    monkeypatch.setenv("NEURAL_ESTIMATOR_CACHE", str(tmp_path / "cache"))
    zoo_script = _train_zoo()
    state, zoo = tmp_path / "state", tmp_path / "zoo"
    args = [
        "--scenarios",
        "test_spinner",
        "--methods",
        "gru",
        "--state",
        str(state),
        "--zoo",
        str(zoo),
        "--trajectories",
        "12",
        "--windows-per-epoch",
        "48",
        "--val-trajectories",
        "6",
        "--eval-trajectories",
        "4",
        "--quiet",
    ]
    real_prune = zoo_script.prune
    monkeypatch.setattr(zoo_script, "prune", lambda work, zoo=None: [])  # keep the resume state this once
    assert zoo_script.main(args + ["--max-epochs", "1"]) == 0  # one epoch, finished on its epoch budget
    monkeypatch.setattr(zoo_script, "prune", real_prune)
    work = state / "test_spinner-gru"
    shutil.rmtree(zoo / work.name)
    card = json.loads((work / "card.json").read_text())
    card["training"]["stopped"] = "in progress"  # as if that run had been cut off after its first epoch
    (work / "card.json").write_text(json.dumps(card))
    assert zoo_script.main(args + ["--max-epochs", "5", "--model-hours", "1e-9"]) == 0
    t = json.loads((zoo / work.name / "card.json").read_text())["training"]
    assert t["stopped"] == "wall budget spent (1e-09 h)" and t["epochs_run"] == 1
    assert t["budget"]["max_epochs"] == 5 and t["converged"] is False


def test_training_caps_trajectories_at_the_scenarios_longest_informative_length(tmp_path):
    from neural_estimator.scenarios import make_scenario

    quad = make_scenario("quadrotor", horizon=40)  # the quadrotor's limit is its horizon
    assert quad.longest_training_trajectory == 40 and make_scenario("lorenz96").longest_training_trajectory is None
    out = train(
        quad, "gru", tmp_path / "q", tiny_config(tmp_path / "cache", epochs=1, eval_trajectories=3), progress=False
    )
    card = json.loads((out / "card.json").read_text())
    assert card["data"]["train_length"] == 40 and card["training"]["recipe"]["train_length"] == 40


def test_train_zoo_leaves_a_pair_that_another_process_holds_and_takes_it_once_released(tmp_path, monkeypatch, capsys):
    """Two train_zoo.py processes on one queue: a pair whose lock another process holds is skipped
    (nothing trained, nothing written but the lock file); once that process is gone (killed: the
    kernel drops its lock) the pair trains."""
    import subprocess
    import sys

    monkeypatch.setenv("NEURAL_ESTIMATOR_CACHE", str(tmp_path / "cache"))
    zoo_script = _train_zoo()
    state, zoo = tmp_path / "state", tmp_path / "zoo"
    work = state / "test_spinner-gru"
    work.mkdir(parents=True)
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import fcntl, sys, time\n"
            f"h = open({str(work / zoo_script.LOCK_NAME)!r}, 'a+')\n"
            "fcntl.flock(h, fcntl.LOCK_EX)\nprint('held', flush=True)\ntime.sleep(120)\n",
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    args = ["--scenarios", "test_spinner", "--methods", "gru", "--state", str(state), "--zoo", str(zoo)]
    args += ["--trajectories", "12", "--windows-per-epoch", "48", "--val-trajectories", "6"]
    args += ["--eval-trajectories", "4", "--max-epochs", "1", "--quiet"]
    try:
        assert holder.stdout.readline().strip() == "held"
        with zoo_script.claimed(work) as mine:
            assert mine is False
        assert zoo_script.main(args) == 0
        assert "test_spinner-gru: another train_zoo.py process is training it, skipped" in capsys.readouterr().out
        assert sorted(p.name for p in work.iterdir()) == [zoo_script.LOCK_NAME] and not zoo.exists()
    finally:
        holder.kill()
        holder.wait()
    assert zoo_script.main(args) == 0
    assert zoo_script.finished(work) and (zoo / work.name / "model.safetensors").is_file()
    with zoo_script.claimed(work) as mine:  # released at the end of the training
        assert mine is True


def test_train_zoo_fallback_context_trains_the_bounded_variant_of_a_model_the_zoo_did_not_take(
    tmp_path, monkeypatch, capsys
):
    """--fallback-context N: a finished full-recipe model the zoo does not take (here: its validation
    "never beat its first epoch") is followed by its bounded-context variant, trained in
    STATE/context<N>/ and installed; a second run finds both finished and trains nothing."""
    monkeypatch.setenv("NEURAL_ESTIMATOR_CACHE", str(tmp_path / "cache"))
    zoo_script = _train_zoo()
    real = zoo_script.not_installable
    # the full-recipe run is refused as a model whose best epoch was its first; the variant is judged as usual
    refused = "its validation loss never went below its first epoch's"
    monkeypatch.setattr(zoo_script, "not_installable", lambda w: refused if "context" not in str(w) else real(w))
    state, zoo = tmp_path / "s", tmp_path / "zoo"
    args = ["--scenarios", "test_spinner", "--methods", "gru", "--state", str(state), "--zoo", str(zoo)]
    args += ["--trajectories", "12", "--windows-per-epoch", "48", "--val-trajectories", "6"]
    args += ["--eval-trajectories", "4", "--max-epochs", "2", "--quiet", "--fallback-context", "10"]
    assert zoo_script.main(args) == 0
    out = capsys.readouterr().out
    assert "test_spinner-gru: not installed: its validation loss never went below" in out
    assert "test_spinner-gru: not in the zoo; training its bounded-context variant (context 10)" in out
    full, variant = state / "test_spinner-gru", state / "context10" / "test_spinner-gru"
    assert zoo_script.finished(full) and (full / "model.safetensors").is_file()  # kept: not shipped
    shipped = json.loads((zoo / "test_spinner-gru" / "card.json").read_text())
    assert shipped["training"]["recipe"]["val_context"] == 10 == shipped["metrics"]["set"]["context"]
    assert shipped == json.loads((variant / "card.json").read_text())
    # resumable and idempotent: nothing left to train
    assert zoo_script.main(args) == 0
    out = capsys.readouterr().out
    assert "training its bounded-context variant" not in out and "installed" not in out
    # the flag follows a full-recipe run only
    with pytest.raises(SystemExit):
        zoo_script.main([*args, "--val-context", "10"])


def test_train_zoo_instance_trains_on_its_own_data_set_and_seed_and_is_kept_beside_the_shipped_model(
    tmp_path, monkeypatch, capsys
):
    """--instance K: training set K and initialisation K (the card says so), its own state and zoo
    folders, installed with no comparison against the shipped model (every instance is kept)."""
    monkeypatch.setenv("NEURAL_ESTIMATOR_CACHE", str(tmp_path / "cache"))
    zoo_script = _train_zoo()
    assert zoo_script.instance_seeds(0) == {"data_index": 0, "init_seed": 0}  # the shipped model's recipe
    assert zoo_script.instance_paths(2, None, None) == (
        zoo_script.STATE / "instances" / "i2",
        zoo_script.ZOO / "instances" / "i2",
    )
    args = ["--scenarios", "test_spinner", "--methods", "gru", "--trajectories", "12"]
    args += ["--windows-per-epoch", "48", "--val-trajectories", "6", "--eval-trajectories", "4"]
    args += ["--max-epochs", "1", "--quiet"]
    zoo0, zoo1 = tmp_path / "zoo", tmp_path / "zoo-i1"
    assert zoo_script.main([*args, "--state", str(tmp_path / "s0"), "--zoo", str(zoo0)]) == 0
    assert zoo_script.main([*args, "--instance", "1", "--state", str(tmp_path / "s1"), "--zoo", str(zoo1)]) == 0
    assert "selection set" not in capsys.readouterr().out  # kept without a comparison
    c0 = json.loads((zoo0 / "test_spinner-gru" / "card.json").read_text())
    c1 = json.loads((zoo1 / "test_spinner-gru" / "card.json").read_text())
    assert (c0["data"]["index"], c0["init_seed"]) == (0, 0) and (c1["data"]["index"], c1["init_seed"]) == (1, 1)
    w0, w1 = weights(zoo0 / "test_spinner-gru"), weights(zoo1 / "test_spinner-gru")
    assert any(not torch.equal(w0[k], w1[k]) for k in w0)
    with pytest.raises(SystemExit):
        zoo_script.main([*args, "--instance", "1", "--val-context", "8"])
