"""Simulation determinism, the .npz format, and the paper's data protocol (sizes, weights, masks)."""

import numpy as np
import pytest

from neural_estimator.data import (
    ChunkSampler,
    DataError,
    dataset,
    load_trajectories,
    save_estimates,
    save_trajectories,
    seed_stream,
    simulate,
    training_trajectories,
    warmup_mask,
    window_weights,
    windows_per_epoch,
)


def test_simulate_shapes_and_meta(oscillator):
    data = simulate(oscillator, 7, 30, seed=3)
    assert data.x.shape == (7, 30, 2) and data.y.shape == (7, 30, 1) and data.u.shape == (7, 30, 0)
    assert data.meta["scenario"] == "oscillator" and data.meta["seed"] == 3
    assert data.meta["config"]["obs_noise_std"] == 0.2
    # the observation noise is what the scenario states: y - h(x) has the R standard deviation
    big = simulate(oscillator, 400, 50, seed=1)
    resid = big.y[..., 0] - big.x[..., 0]
    assert abs(resid.std() - 0.2) < 0.01


def test_same_seed_same_bytes_different_seed_different(oscillator, tmp_path):
    a = save_trajectories(tmp_path / "a.npz", simulate(oscillator, 5, 20, seed=11))
    b = save_trajectories(tmp_path / "b.npz", simulate(oscillator, 5, 20, seed=11))
    c = save_trajectories(tmp_path / "c.npz", simulate(oscillator, 5, 20, seed=12))
    assert a.read_bytes() == b.read_bytes()
    assert a.read_bytes() != c.read_bytes()


def test_round_trip_and_estimate_file(oscillator, tmp_path):
    data = simulate(oscillator, 4, 10, seed=0)
    x_hat = data.x + 0.1
    x_hat[1, 5] = np.nan  # a diverged estimate is data, not an error
    path = save_estimates(tmp_path / "e.npz", data, x_hat, "ekf", P_hat=np.broadcast_to(np.eye(2), (4, 10, 2, 2)))
    back, extras = load_trajectories(path)
    np.testing.assert_array_equal(back.x, data.x)
    np.testing.assert_array_equal(extras["x_hat"], x_hat)
    assert extras["P_hat"].shape == (4, 10, 2, 2)
    assert back.meta["method"] == "ekf"


def test_bad_files_name_the_problem(oscillator, tmp_path):
    data = simulate(oscillator, 3, 5, seed=0)
    data.y[2, 1, 0] = np.nan
    path = save_trajectories(tmp_path / "nan.npz", data)
    with pytest.raises(DataError, match=r"nan.npz.*'y' contains NaN or inf in 1 trajectories \(first: 2\)"):
        load_trajectories(path)
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(DataError, match="junk.npz: not a readable"):
        load_trajectories(tmp_path / "junk.npz")
    with pytest.raises(DataError, match="no such file"):
        load_trajectories(tmp_path / "missing.npz")
    with pytest.raises(DataError, match="x_hat has shape"):
        save_estimates(tmp_path / "e.npz", simulate(oscillator, 3, 5), np.zeros((3, 4, 2)), "ukf")


def test_window_weights_exact_small_case():
    # T = 5, L = 3: starts {0, 1, 2}; coverage c = [1, 2, 3, 2, 1]; w = S L / (T c) = 9 / (5 c)
    w = window_weights(5, 3)
    np.testing.assert_allclose(w, [9 / 5, 9 / 10, 9 / 15, 9 / 10, 9 / 5])
    # a uniformly random window has expected total weight L
    starts = range(3)
    assert np.isclose(np.mean([w[s : s + 3].sum() for s in starts]), 3.0)
    # full-length window: every timestep covered once, weight 1
    np.testing.assert_allclose(window_weights(4, 4), np.ones(4))
    with pytest.raises(ValueError):
        window_weights(5, 6)


def test_weights_undo_sampling_frequency_empirically():
    """Summing weights over many sampled windows gives each timestep the same total weight."""
    sampler = ChunkSampler(n_trajectories=1, length=50, window=10, warmup=0)
    rng = np.random.default_rng(0)
    _, start = sampler.sample(rng, 200_000)
    total = np.zeros(50)
    np.add.at(total, start[:, None] + np.arange(10), sampler.loss_weights(start))
    assert total.std() / total.mean() < 0.02


def test_warmup_mask_and_gather():
    m = warmup_mask(100)
    assert m.shape == (100,) and not m[:10].any() and m[10:].all()
    sampler = ChunkSampler(3, 20, window=5, warmup=2)
    arr = np.arange(3 * 20).reshape(3, 20, 1).astype(float)
    (win,) = sampler.gather([arr], np.array([2, 0]), np.array([15, 3]))
    np.testing.assert_array_equal(win[..., 0], [[55, 56, 57, 58, 59], [3, 4, 5, 6, 7]])
    lw = sampler.loss_weights(np.array([0]))
    assert (lw[0, :2] == 0).all() and (lw[0, 2:] > 0).all()


def test_paper_sizes():
    # 20:1 with 100k parameters = 2,000,000 timesteps = 4,000 trajectories of 500 = 20,000 windows of 100
    assert training_trajectories(20) == 4000 and windows_per_epoch(20) == 20_000
    assert [training_trajectories(r) for r in (10, 5, 1)] == [2000, 1000, 200]


def test_seed_streams_are_independent_and_cached(oscillator, tmp_path):
    a = np.random.default_rng(seed_stream(0, "train", 0)).standard_normal(4)
    b = np.random.default_rng(seed_stream(0, "eval", 0)).standard_normal(4)
    c = np.random.default_rng(seed_stream(0, "eval", 1)).standard_normal(4)
    assert not np.allclose(a, b) and not np.allclose(b, c)
    with pytest.raises(ValueError, match="unknown dataset role"):
        seed_stream(0, "test")
    d1 = dataset(oscillator, "eval", 1, 6, 12, seed=5, cache_dir=tmp_path)
    assert len(list((tmp_path / "datasets").glob("*.npz"))) == 1
    d2 = dataset(oscillator, "eval", 1, 6, 12, seed=5, cache_dir=tmp_path)
    np.testing.assert_array_equal(d1.y, d2.y)
    d3 = dataset(oscillator, "eval", 1, 6, 12, seed=5, cache_dir=False)
    np.testing.assert_array_equal(d1.y, d3.y)
