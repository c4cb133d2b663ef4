"""The built-in scenarios: shapes, Jacobians, noise, overrides, registration and docs (what every
built-in needs), and the paper's five's known answers."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from neural_estimator.scenarios import (
    BUILTIN_SCENARIOS,
    ScenarioError,
    code_digest,
    complex_step_jacobian,
    make_scenario,
    psd_sqrt,
    scenario_class,
    scenario_from_description,
    scenario_names,
)
from neural_estimator.scenarios import nlink
from neural_estimator.scenarios._integrate import rk4
from neural_estimator.scenarios.lorenz96 import measure_climatology

# Set once: central differences with a relative step of 1e-6 are good to about 1e-8 relative;
# the exact Jacobians must match them to JAC_RTOL of the Jacobian's largest entry.
FD_STEP = 1e-6
JAC_RTOL = 1e-5

# Lorenz 96 spin-up shortened where a test only needs states, not states on the attractor.
FAST = {"lorenz96": {"spinup_steps": 20}}


def scenario(name: str, **overrides):
    return make_scenario(name, **{**FAST.get(name, {}), **overrides})


def prior_states(s, rng, shape):
    m0, p0 = s.prior()
    return m0 + rng.standard_normal(tuple(shape) + (s.dx,)) @ psd_sqrt(p0).T


def controls(s, rng, shape):
    n = int(np.prod(shape))
    return s.sample_controls(rng, n, 1)[:, 0].reshape(tuple(shape) + (s.du,))


def fd_jacobian(fn, x, residual):
    """Central differences (..., m, n), steps relative to |x_j|; differences through ``residual``."""
    n = x.shape[-1]
    cols = []
    for j in range(n):
        step = FD_STEP * max(1.0, float(np.abs(x[..., j]).max()))
        e = np.zeros(n)
        e[j] = step
        cols.append(residual(fn(x + e), fn(x - e)) / (2 * step))
    return np.stack(cols, axis=-1)


def assert_jacobian_close(jac, ref):
    scale = np.abs(ref).max(axis=(-2, -1), keepdims=True)
    assert np.all(np.abs(jac - ref) <= JAC_RTOL * scale), np.abs(jac - ref).max()


# ---- contract: shapes, dtypes, noise, overrides ---------------------------------------------------
@pytest.mark.parametrize("name", BUILTIN_SCENARIOS)
@pytest.mark.parametrize("batch", [(), (5,), (2, 3)])
def test_shapes_over_leading_axes(name, batch):
    s = scenario(name)
    rng = np.random.default_rng(0)
    x = prior_states(s, rng, batch)
    u = controls(s, rng, batch)
    assert s.f(x, u).shape == batch + (s.dx,)
    assert s.h(x).shape == batch + (s.dy,)
    assert s.jac_f(x, u).shape == batch + (s.dx, s.dx)
    assert s.jac_h(x).shape == batch + (s.dy, s.dx)
    for out in (s.f(x, u), s.h(x), s.jac_f(x, u), s.jac_h(x)):
        assert out.dtype == np.float64
    assert s.sample_initial(rng, 4).shape == (4, s.dx)
    assert s.sample_controls(rng, 4, 7).shape == (4, 7, s.du)
    m0, p0 = s.prior()
    assert m0.shape == (s.dx,) and p0.shape == (s.dx, s.dx)
    assert s.process_cov().shape == (s.dx, s.dx) and s.obs_cov().shape == (s.dy, s.dy)
    names = s.describe()
    assert len(names["state_units"]) == s.dx and len(names["obs_units"]) == s.dy
    assert len(names["control_units"]) == s.du


@pytest.mark.parametrize("name", BUILTIN_SCENARIOS)
def test_jacobians_match_central_differences(name):
    s = scenario(name)
    rng = np.random.default_rng(1)
    x = prior_states(s, rng, (6,))
    u = controls(s, rng, (6,))
    jf = fd_jacobian(lambda z: s.f(z, u), x, s.state_residual)
    jh = fd_jacobian(s.h, x, s.obs_residual)
    assert_jacobian_close(s.jac_f(x, u), jf)
    assert_jacobian_close(s.jac_h(x), jh)


@pytest.mark.parametrize(
    ("name", "overrides", "fn"),
    [
        ("ballistic", {}, "f"),
        ("lorenz96", {}, "f"),
        ("lorenz96", {"n_vars": 5}, "f"),  # band offsets -2 and +3 coincide modulo 5
        ("lorenz96", {"substeps": 3}, "f"),
        ("nlink", {}, "step_unwrapped"),
        ("nlink", {"n_links": 5}, "step_unwrapped"),
    ],
)
def test_tangent_jacobians_equal_complex_step(name, overrides, fn):
    """The fast tangent-propagated Jacobians against the slow complex-step reference (exact)."""
    s = scenario(name, **overrides)
    x = prior_states(s, np.random.default_rng(2), (4,))
    ref = complex_step_jacobian(lambda z, _u: getattr(s, fn)(z), x, np.zeros((4, 0)))
    np.testing.assert_allclose(s.jac_f(x, np.zeros((4, 0))), ref, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("name", BUILTIN_SCENARIOS)
def test_obs_cov_scales_with_noise_scale_squared(name):
    base = scenario(name).obs_cov()
    np.testing.assert_allclose(scenario(name, noise_scale=3.0).obs_cov(), 9.0 * base)
    np.testing.assert_allclose(scenario(name, noise_scale=0.5).obs_cov_nominal(), base)
    doubled = scenario(name, obs_noise_std=2.0 * scenario(name).config.obs_noise_std)
    np.testing.assert_allclose(doubled.obs_cov(), 4.0 * base)


@pytest.mark.parametrize("name", BUILTIN_SCENARIOS)
def test_overrides_and_unknown_names(name):
    s = scenario(name, obs_noise_std="0.125", horizon="17")  # strings as --set passes them
    assert s.config.obs_noise_std == 0.125 and s.horizon == 17
    with pytest.raises(ScenarioError) as err:
        scenario(name, no_such_constant=1.0)
    message = str(err.value)
    assert "no_such_constant" in message
    for valid in ("dt", "horizon", "noise_scale", "obs_noise_std"):
        assert valid in message
    with pytest.raises(ScenarioError):
        scenario(name, noise_scale=-1.0)


@pytest.mark.parametrize("name", BUILTIN_SCENARIOS)
def test_description_round_trips_through_json(name):
    s = scenario(name, noise_scale=2.0)
    desc = json.loads(json.dumps(s.describe()))
    again = scenario_from_description(desc)
    assert again.config == s.config
    x = prior_states(s, np.random.default_rng(3), (2,))
    np.testing.assert_array_equal(again.h(x), s.h(x))


# ---- what every built-in needs: its module, its registration, its docs line ----------------------------
SCENARIOS_PAGE = Path(__file__).resolve().parents[1] / "docs" / "scenarios.md"


def documented_scenarios(text: str) -> list[str]:
    """The names in the first column of the table of systems in docs/scenarios.md (``text``)."""
    table = text.split("| name | state x |", 1)[1].split("\n\n", 1)[0]
    return re.findall(r"^\| `([a-z0-9_]+)` \|", table, flags=re.M)


def assert_builtin(name: str, page: str) -> None:
    """``name`` is a built-in: its module in neural_estimator/scenarios/ (so its code is covered by the
    package version, not a plugin's digest), registered by name, one row in the docs' table."""
    cls = scenario_class(name)
    assert cls.__module__.startswith("neural_estimator.scenarios."), cls.__module__
    assert code_digest(cls) is None and name in scenario_names() and cls.name == name
    assert documented_scenarios(page).count(name) == 1, f"{name}: no row (or two) in docs/scenarios.md"


@pytest.mark.parametrize("name", BUILTIN_SCENARIOS)
def test_every_builtin_has_its_module_registration_and_docs_line(name):
    assert_builtin(name, SCENARIOS_PAGE.read_text())


def test_the_docs_table_lists_the_builtins_only():
    assert set(documented_scenarios(SCENARIOS_PAGE.read_text())) == set(BUILTIN_SCENARIOS)


@pytest.mark.parametrize("n_links", [1, 3])
def test_nlink_angles_stay_wrapped(n_links):
    s = make_scenario("nlink", n_links=n_links)
    rng = np.random.default_rng(4)
    x = prior_states(s, rng, (50,))
    x[:, list(s.angle_states)] += 7.0  # far outside (-pi, pi]
    nxt = s.f(x, controls(s, rng, (50,)))
    for state in (nxt, s.sample_initial(rng, 50)):
        ang = state[:, list(s.angle_states)]
        assert np.all((ang > -np.pi) & (ang <= np.pi))


# ---- ballistic -----------------------------------------------------------------------------------
def test_ballistic_is_free_fall_above_the_atmosphere():
    s = make_scenario("ballistic")
    dt, g = s.dt, s.config.g
    x = np.array([2000.0, 6.0, 1.5])  # exp(-k a) ~ 1e-143: no drag
    np.testing.assert_allclose(s.f(x), [2000.0 - 6.0 * dt - 0.5 * g * dt**2, 6.0 + g * dt, 1.5], rtol=0, atol=1e-12)
    np.testing.assert_allclose(s.h(np.array([30.0, 0.0, 0.0])), [s.config.r0])
    np.testing.assert_allclose(s.h(np.array([70.0, 0.0, 0.0])), [50.0])  # 3-4-5 triangle


def test_ballistic_horizon_ends_before_ground_impact():
    """The docstring's choice of dt (preset v3): noise-free prior draws are still airborne at step
    500, decelerated to the terminal speed."""
    s = make_scenario("ballistic", preset="v3")
    x = s.sample_initial(np.random.default_rng(5), 2000)
    for _ in range(s.horizon):
        x = s.f(x)
    assert x[:, 0].min() > 0.5
    assert np.percentile(x[:, 1], 99) < 0.15  # decelerated from 3-9 km/s to near sqrt(g / c) = 0.08


def test_ballistic_v4_horizon_stays_high_in_the_atmosphere():
    """The docstring's choice of dt (v4): 5 s of re-entry, every body still above 40 km, where the
    drag has not yet slowed the bodies much (so the filters cannot pin the drag coefficient down)."""
    s = make_scenario("ballistic")
    x0 = s.sample_initial(np.random.default_rng(5), 2000)
    x = x0
    for _ in range(s.horizon):
        x = s.f(x)
    assert x[:, 0].min() > 40.0
    assert np.median(np.abs(x[:, 1] - x0[:, 1]) / x0[:, 1]) < 0.05


def test_ballistic_jacobian_below_ground():
    s = make_scenario("ballistic")
    x = np.array([[-1.0, 0.08, 1.5], [0.01, 0.08, 1.5]])  # E(a) = 1 and just above its kink
    jf = fd_jacobian(lambda z: s.f(z), x, s.state_residual)
    assert_jacobian_close(s.jac_f(x), jf)


# ---- bearings ------------------------------------------------------------------------------------
def test_bearings_observation_in_half_open_interval():
    s = make_scenario("bearings")
    x = np.array([[-100.0, 0.0, 0, 0], [-100.0, -0.0, 0, 0], [0.0, 100.0, 0, 0], [100.0, 0.0, 0, 0], [0.0, -5.0, 0, 0]])
    np.testing.assert_allclose(s.h(x)[:, 0], [np.pi, np.pi, np.pi / 2, 0.0, -np.pi / 2])
    y = s.h(prior_states(s, np.random.default_rng(6), (1000,)))
    assert np.all((y > -np.pi) & (y <= np.pi))
    assert s.angle_obs == (0,) and s.angle_states == ()


def test_bearings_constant_velocity_and_noise():
    s = make_scenario("bearings", accel_noise_std=2.0)
    np.testing.assert_allclose(s.f(np.array([1.0, 2.0, 3.0, -4.0])), [4.0, -2.0, 3.0, -4.0])
    q = s.process_cov()
    # x and y axes: sigma^2 [[T^4/4, T^3/2], [T^3/2, T^2]], no cross-axis terms.
    np.testing.assert_allclose(q[np.ix_([0, 2], [0, 2])], 4.0 * np.array([[0.25, 0.5], [0.5, 1.0]]))
    assert q[0, 1] == 0 and q[2, 3] == 0
    assert s.state_names == ("px", "py", "vx", "vy")


def principal_root(vals, R):
    """The analytic principal square root of R diag(vals) R^T."""
    return (R * np.sqrt(vals)) @ R.T


def test_psd_sqrt_of_a_singular_covariance_is_its_unique_principal_root():
    """A repeated eigenvalue leaves LAPACK free to return any basis of its eigenspace (and different
    CPUs do): psd_sqrt must give the one root that does not depend on that choice, so the same seed
    simulates the same noise everywhere."""
    rng = np.random.default_rng(3)
    for vals in ([0.0, 0.0, 2.0, 2.0], [0.0, 1.0, 1.0, 1.0, 5.0]):
        vals = np.array(vals)
        for _ in range(5):
            R, _ = np.linalg.qr(rng.standard_normal((vals.size, vals.size)))
            cov = (R * vals) @ R.T
            L = psd_sqrt(cov)
            np.testing.assert_allclose(L, principal_root(vals, R), atol=1e-12)
            np.testing.assert_allclose(L @ L.T, cov, atol=1e-12)
    # The bearings white-noise-acceleration Q = 0.1125 (u1 u1^T + u2 u2^T): its root is Q / sqrt(0.1125).
    Q = make_scenario("bearings").process_cov()
    lam = np.linalg.eigvalsh(Q).max()
    np.testing.assert_allclose(psd_sqrt(Q), Q / np.sqrt(lam), atol=1e-15)


def test_psd_sqrt_diagonal_cholesky_and_refusals():
    np.testing.assert_array_equal(psd_sqrt(np.diag([0.0, 4.0, 0.0, 9.0])), np.diag([0.0, 2.0, 0.0, 3.0]))
    A = np.array([[4.0, 2.0], [2.0, 5.0]])
    np.testing.assert_array_equal(psd_sqrt(A), np.linalg.cholesky(A))
    with pytest.raises(ScenarioError, match="not positive semi-definite"):
        psd_sqrt(np.diag([1.0, -1.0]))
    with pytest.raises(ScenarioError, match="not positive semi-definite"):
        psd_sqrt(np.array([[1.0, 2.0], [2.0, 1.0]]))
    with pytest.raises(ScenarioError, match="square matrix"):
        psd_sqrt(np.ones((2, 3)))


# ---- Lorenz 96 -----------------------------------------------------------------------------------
def test_lorenz96_known_answers():
    s = make_scenario("lorenz96")
    rest = np.full(40, 8.0)
    np.testing.assert_allclose(s.f(rest), rest)  # X = F is a fixed point
    # The advection term conserves energy: x . dx/dt = -|x|^2 + F sum(x) exactly.
    x = prior_states(s, np.random.default_rng(7), (10,))
    np.testing.assert_allclose((x * s._field(x)).sum(-1), -(x * x).sum(-1) + 8.0 * x.sum(-1), rtol=1e-12)


@pytest.mark.slow
@pytest.mark.parametrize("substeps", [1, 3])
@pytest.mark.parametrize("shape", [(40,), (3, 40), (2, 81, 40), (20001, 40)])
def test_lorenz96_f_is_bit_equal_to_rk4_of_the_field(shape, substeps, monkeypatch):
    """f integrates batches ring-major in chunks (the fast path); it must give rk4(_field)'s bits,
    so datasets do not change with the path or the batch. Small chunks force several, unequal ones."""
    import neural_estimator.scenarios.lorenz96 as l96

    monkeypatch.setattr(l96, "_RING_MAJOR_CHUNK", 7000)
    s = make_scenario("lorenz96", substeps=substeps)
    x = 4.0 * np.random.default_rng(3).standard_normal(shape)
    expected = rk4(s._field, x, s.config.dt / substeps, substeps)
    np.testing.assert_array_equal(s.f(x), expected)
    xc = x + 1e-20j * np.random.default_rng(4).standard_normal(shape)  # the complex step passes through
    np.testing.assert_array_equal(s.f(xc), rk4(s._field, xc, s.config.dt / substeps, substeps))


def test_lorenz96_spinup_lands_on_the_attractor():
    s = make_scenario("lorenz96")
    x = s.sample_initial(np.random.default_rng(8), 400)
    assert abs(x.mean() - s.config.prior_mean) < 0.15
    assert abs(x.std() - s.config.prior_std) < 0.15
    # Bounded: the attractor's energy 1/2 |x|^2 / J stays near (mean^2 + std^2) / 2 ~ 9.4.
    for _ in range(100):
        x = s.f(x)
    energy = 0.5 * (x * x).mean(-1)
    assert 5.0 < np.median(energy) < 14.0 and energy.max() < 30.0


def test_lorenz96_prior_is_the_measured_climatology():
    """The config's prior constants match a fresh (shorter) measurement within its error."""
    s = make_scenario("lorenz96")
    mean, std = measure_climatology(s, n_members=300, burn_in=100, n_steps=400, seed=11)
    assert abs(mean - s.config.prior_mean) < 0.05
    assert abs(std - s.config.prior_std) < 0.05


# ---- N-link pendulum -------------------------------------------------------------------------------
def test_nlink_conserves_energy_without_noise():
    s = make_scenario("nlink", dt=0.001, substeps=1)
    x = s.sample_initial(np.random.default_rng(9), 50)
    e0 = s.energy(x)
    for _ in range(500):  # 0.5 s; the RK4 error is then about 5e-9 of the well depth
        x = s.f(x)
    well_depth = s._constants()[2].sum()
    assert np.abs(s.energy(x) - e0).max() < 1e-7 * well_depth


def test_nlink_double_pendulum_matches_textbook_equations():
    """N = 2 against the closed-form double-pendulum accelerations (angles from the downward vertical)."""
    s = make_scenario("nlink", n_links=2, total_length=3.0, mass=2.0)
    g, l1, l2, m1, m2 = 9.81, 1.5, 1.5, 2.0, 2.0
    th1, th2, w1, w2 = np.random.default_rng(10).uniform(-3, 3, (4, 20))
    den = 2 * m1 + m2 - m2 * np.cos(2 * th1 - 2 * th2)
    a1 = (
        -g * (2 * m1 + m2) * np.sin(th1)
        - m2 * g * np.sin(th1 - 2 * th2)
        - 2 * np.sin(th1 - th2) * m2 * (w2**2 * l2 + w1**2 * l1 * np.cos(th1 - th2))
    ) / (l1 * den)
    a2 = (
        2
        * np.sin(th1 - th2)
        * (w1**2 * l1 * (m1 + m2) + g * (m1 + m2) * np.cos(th1) + w2**2 * l2 * m2 * np.cos(th1 - th2))
    ) / (l2 * den)
    field = s._field(np.stack([th1, th2, w1, w2], axis=-1))
    np.testing.assert_allclose(field[:, 2:], np.stack([a1, a2], axis=-1), rtol=1e-10, atol=1e-10)


def nlink_states(s, rng, shape):
    """Prior draws with some angular rates scaled up 10 and 40 times (up to ~100 rad/s)."""
    x = prior_states(s, rng, shape)
    x[..., s.n_links :] *= rng.choice([1.0, 10.0, 40.0], tuple(shape) + (s.n_links,))
    return x


@pytest.mark.parametrize("n_links", [1, 2, 3, 5])
@pytest.mark.parametrize("batch", [(), (7,), (3, 5)])
def test_nlink_component_step_equals_matrix_reference(n_links, batch, monkeypatch):
    """The component-form RK4 (unrolled L D L^T) against RK4 of the (..., N, N) field with a solve."""
    monkeypatch.setattr(nlink, "_BLOCK", 4)  # batches span several blocks and a partial last one
    s = make_scenario("nlink", n_links=n_links)
    x = nlink_states(s, np.random.default_rng(12), batch)
    ref = rk4(s._field, x, s.config.dt / s.config.substeps, s.config.substeps)
    err = np.abs(s._step_components(x) - ref) / np.abs(ref).max(axis=-1, keepdims=True)
    assert err.max() < 1e-12, err.max()


@pytest.mark.parametrize("n_links", [1, 3, 5])
def test_nlink_f_on_a_particle_batch_equals_matrix_reference(n_links):
    """f on a batch large enough for the component path, against the reference, wrapped."""
    s = make_scenario("nlink", n_links=n_links)
    x = nlink_states(s, np.random.default_rng(13), (16, 20))
    ref = s.normalize_state(rk4(s._field, x, s.config.dt / s.config.substeps, s.config.substeps))
    err = np.abs(s.state_residual(s.f(x), ref)) / np.abs(ref).max(axis=-1, keepdims=True)
    assert err.max() < 1e-12, err.max()


@pytest.mark.parametrize("n_links", [1, 3])
def test_nlink_component_step_is_complex_step_safe(n_links):
    s = make_scenario("nlink", n_links=n_links)
    x = prior_states(s, np.random.default_rng(14), (5,))
    ref = complex_step_jacobian(lambda z, _u: s._step_components(z), x, np.zeros((5, 0)))
    np.testing.assert_allclose(s.jac_f(x), ref, rtol=1e-12, atol=1e-12)


def test_nlink_dimensions_follow_n_links():
    s = make_scenario("nlink", n_links=5)
    assert s.dx == 10 and s.dy == 10 and s.angle_states == (0, 1, 2, 3, 4)
    assert s.state_names[:2] == ("theta1", "theta2") and s.obs_names[:2] == ("x1", "z1")
    # Hanging straight down: the last mass at depth total_length, at rest.
    down = np.zeros(10)
    np.testing.assert_allclose(s.h(down)[-2:], [0.0, -1.0], atol=1e-15)
    np.testing.assert_allclose(s.f(down), down, atol=1e-15)
    q = s.process_cov()
    np.testing.assert_allclose(q[np.ix_([0, 5], [0, 5])], 0.01 * np.array([[1e-6 / 3, 5e-5], [5e-5, 0.01]]))


# ---- planar quadrotor ------------------------------------------------------------------------------
def test_quadrotor_hover_thrust_balances_gravity():
    s = make_scenario("quadrotor", thrust_perturb_rel=0.0)
    u = s.sample_controls(np.random.default_rng(11), 3, s.horizon)
    np.testing.assert_allclose(u, s.hover_thrust)
    x = np.array([[0.0, 0.0, 0.0, 0.7, -0.4, 0.0]] * 3)
    x0 = x.copy()
    for k in range(s.horizon):
        x = s.f(x, u[:, k])
    np.testing.assert_allclose(x[:, 2:], x0[:, 2:], atol=1e-12)  # phi, body velocities unchanged
    np.testing.assert_allclose(x[:, :2], x0[:, :2] + s.horizon * s.dt * x0[:, 3:5], atol=1e-12)


def test_quadrotor_roll_rate_rows():
    x = np.array([0.0, 0.0, 0.2, 0.0, 0.0, 1.5])
    u = np.array([3.0, 2.0])
    kick = 1.0 * 0.25 * 0.01 / 0.00383
    assert make_scenario("quadrotor").f(x, u)[5] == pytest.approx(1.5 + kick)
    literal = make_scenario("quadrotor", integrate_phi_rate=False)  # the row as printed in the paper
    assert literal.f(x, u)[5] == pytest.approx(kick)
    xs = prior_states(literal, np.random.default_rng(12), (4,))
    us = controls(literal, np.random.default_rng(12), (4,))
    assert_jacobian_close(literal.jac_f(xs, us), fd_jacobian(lambda z: literal.f(z, us), xs, literal.state_residual))


def test_quadrotor_observation_matrix_is_stored_and_overridable():
    s = make_scenario("quadrotor")
    c = np.random.default_rng(0).standard_normal((3, 6))
    np.testing.assert_array_equal(np.asarray(s.config.c_matrix), c)
    assert s.describe()["config"]["c_matrix"] == c.tolist()
    assert s.angle_states == ()  # phi enters y = C x linearly: wrapping it would make y jump
    eye = np.eye(6)[:3]
    t = make_scenario("quadrotor", c_matrix=json.dumps(eye.tolist()))
    x = np.arange(6.0)
    np.testing.assert_array_equal(t.h(x), [0.0, 1.0, 2.0])
    with pytest.raises(ScenarioError):
        make_scenario("quadrotor", c_matrix=[[1.0, 2.0]])
