"""The filters' initialisation protocol: start from the prior (default, live) or at given means.

``reset(batch, initial_mean)`` replaces the prior mean m0 stream by stream and nothing else; the
offline protocol's ``init="truth"`` passes each trajectory's true x_0 there.
"""

import numpy as np
import pytest

from neural_estimator.data import simulate
from neural_estimator.methods.registry import CLASSICAL_METHODS, EstimatorError, make_estimator
from neural_estimator.evaluation import evaluate, run_method
from neural_estimator.scenarios import make_scenario

# Few particles / members keep the tests fast; the statistics checked do not need more.
SMALL = {"pf": {"n_particles": 64}, "enkf": {"n_members": 8}}


def _filter(method, scenario, seed=0):
    return make_estimator(method, scenario, seed=seed, threads=1, **SMALL.get(method, {}))


@pytest.mark.parametrize("method", CLASSICAL_METHODS)
def test_initial_state_is_centred_on_the_given_means(method):
    s = make_scenario("bearings")
    f = _filter(method, s)
    means = np.array([[100.0, 200.0, 1.0, -2.0], [-300.0, 50.0, 3.0, 4.0]])
    f.reset(2, initial_mean=means)
    if method in ("ekf", "ukf"):
        np.testing.assert_array_equal(f._m, means)
        np.testing.assert_array_equal(f._P, np.broadcast_to(f.P0, (2, 4, 4)))  # P0 unchanged
    else:
        X = f._X  # (2, N, 4) members / particles: centred on the given means, spread unchanged
        f.reset(2)  # the same draws around m0
        np.testing.assert_allclose(X - means[:, None, :], f._X - f.m0, atol=1e-9)


@pytest.mark.parametrize("method", CLASSICAL_METHODS)
def test_prior_start_is_unchanged_by_the_option(method):
    """initial_mean=None is the prior, bit for bit; initial_mean = m0 everywhere gives the same run."""
    s = make_scenario("bearings")
    data = simulate(s, 3, 15, seed=4)
    plain = _filter(method, s).run(data.y, data.u)
    m0 = np.broadcast_to(s.prior()[0], (3, s.dx))
    explicit = _filter(method, s).run(data.y, data.u, initial_mean=m0)
    np.testing.assert_array_equal(plain.x, explicit.x)


@pytest.mark.parametrize("method", CLASSICAL_METHODS)
def test_truth_start_removes_the_initial_error(method):
    """Started at the true x_0 the first estimates are far closer to the truth than from the prior
    (a wide prior, Gordon's x 1000, so that the prior's initial error is large)."""
    s = make_scenario("bearings", prior_std=(500.0, 300.0, 5.0, 10.0))
    data = simulate(s, 20, 3, seed=5)
    prior = run_method(_filter(method, s), data, 20, s.angle_states)[0]
    truth = run_method(_filter(method, s), data, 20, s.angle_states, init="truth")[0]
    e_prior = np.linalg.norm(prior[:, 0, :2] - data.x[:, 0, :2], axis=-1).mean()
    e_truth = np.linalg.norm(truth[:, 0, :2] - data.x[:, 0, :2], axis=-1).mean()
    assert e_truth < 0.5 * e_prior


def test_bad_initial_means_are_refused():
    f = _filter("ekf", make_scenario("bearings"))
    with pytest.raises(EstimatorError, match=r"initial_mean must be \(2, 4\)"):
        f.reset(2, initial_mean=np.zeros((3, 4)))
    with pytest.raises(EstimatorError, match="NaN or inf"):
        f.reset(1, initial_mean=np.full((1, 4), np.nan))


def test_evaluate_init_option_and_its_check(tmp_path):
    s = make_scenario("bearings")
    kw = dict(trajectories=6, horizon=10, sets=1, seed=2, cache_dir=False, progress=False, warmup=0)
    prior = evaluate(s, ["ekf"], **kw)["ekf"].reports[0].rmse
    truth = evaluate(s, ["ekf"], init="truth", **kw)["ekf"].reports[0].rmse
    assert truth < prior
    with pytest.raises(ValueError, match="init must be one of prior, truth"):
        evaluate(s, ["ekf"], init="true", **kw)


def test_live_path_starts_from_the_prior():
    """The live node's step() path never sees the truth: a fresh filter starts at m0."""
    s = make_scenario("bearings")
    data = simulate(s, 1, 4, seed=6)
    f = _filter("ekf", s)
    x = f.step(data.y[:, 0], data.u[:, 0])
    g = _filter("ekf", s)
    g.reset(1)
    np.testing.assert_array_equal(x, g.step(data.y[:, 0], data.u[:, 0]))
    np.testing.assert_array_equal(g._init_mean, s.prior()[0][None])
