"""The differentiable form of the five systems (``scenario.torch_dynamics()``): the numpy form's f and
h to 1e-10 in float64 on random states of each prior and random controls, gradients that exist
(gradcheck), and autograd Jacobians equal to the analytic ones the EKF uses to 1e-8."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch

from neural_estimator.scenarios import BUILTIN_SCENARIOS, make_scenario, psd_sqrt

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def prior_states(scenario, rng, shape):
    """States drawn from the prior N(m0, P0) (not the scenarios' own samplers, which spin up or
    truncate), of leading ``shape``."""
    m0, p0 = scenario.prior()
    return m0 + rng.standard_normal(shape + (scenario.dx,)) @ psd_sqrt(p0).T


def controls(scenario, rng, shape):
    n = int(np.prod(shape))
    return scenario.sample_controls(rng, n, 1)[:, 0].reshape(shape + (scenario.du,))


def t(a, requires_grad=False):
    return torch.tensor(np.asarray(a, dtype=np.float64), requires_grad=requires_grad)


@pytest.mark.parametrize("shape", [(5,), (2, 40)], ids=["few", "batched"])  # 80 states: numpy's blocked paths
@pytest.mark.parametrize("name", BUILTIN_SCENARIOS)
def test_f_and_h_equal_the_numpy_form(name, shape):
    scenario = make_scenario(name)
    dyn = scenario.torch_dynamics()
    assert (dyn.dx, dyn.dy, dyn.du) == (scenario.dx, scenario.dy, scenario.du)
    rng = np.random.default_rng(7)
    x, u = prior_states(scenario, rng, shape), controls(scenario, rng, shape)
    with torch.no_grad():
        fx, hx = dyn.f(t(x), t(u)), dyn.h(t(x))
    assert fx.dtype == hx.dtype == torch.float64
    assert fx.shape == shape + (scenario.dx,) and hx.shape == shape + (scenario.dy,)
    np.testing.assert_allclose(fx.numpy(), scenario.f(x, u), rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(hx.numpy(), scenario.h(x), rtol=1e-10, atol=1e-10)
    # the states move: an f that returned x would not pass as the identity by accident
    assert not np.allclose(scenario.f(x, u), x, rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", ["nlink", "bearings"])
def test_angles_are_wrapped_as_the_numpy_form_wraps_them(name):
    """States far from (-pi, pi]: N-link's f and the bearing wrap exactly where numpy does."""
    scenario = make_scenario(name)
    dyn = scenario.torch_dynamics()
    rng = np.random.default_rng(3)
    x = prior_states(scenario, rng, (64,))
    if name == "nlink":
        x[:, : scenario.n_links] += rng.integers(-3, 4, size=(64, scenario.n_links)) * 2.0 * np.pi + 3.0
        got = dyn.f(t(x), None).detach().numpy()
        np.testing.assert_allclose(got, scenario.f(x, None), rtol=1e-10, atol=1e-10)
        assert np.abs(got[:, : scenario.n_links]).max() <= np.pi
    else:
        x[:, :2] = rng.standard_normal((64, 2))  # bearings all around the sensor
        x[0, :2] = (-1.0, -0.0)  # atan2 gives -pi: wrapped to pi, as numpy does
        got = dyn.h(t(x)).detach().numpy()
        np.testing.assert_allclose(got, scenario.h(x), rtol=1e-10, atol=1e-10)
        assert got[0, 0] == np.pi


@pytest.mark.parametrize("name", BUILTIN_SCENARIOS)
def test_gradients_exist(name):
    scenario = make_scenario(name)
    dyn = scenario.torch_dynamics()
    rng = np.random.default_rng(11)
    x, u = t(prior_states(scenario, rng, (3,)), True), t(controls(scenario, rng, (3,)), scenario.du > 0)
    if scenario.du:
        assert torch.autograd.gradcheck(lambda a, b: dyn.f(a, b), (x, u))
    else:
        assert torch.autograd.gradcheck(lambda a: dyn.f(a, u), (x,))
    assert torch.autograd.gradcheck(dyn.h, (x,))


@pytest.mark.parametrize("name", BUILTIN_SCENARIOS)
def test_autograd_jacobians_equal_the_analytic_ones(name):
    scenario = make_scenario(name)
    dyn = scenario.torch_dynamics()
    rng = np.random.default_rng(5)
    x, u = prior_states(scenario, rng, (4,)), controls(scenario, rng, (4,))
    for xi, ui in zip(x, u):
        jf = torch.autograd.functional.jacobian(lambda a: dyn.f(a, t(ui)), t(xi)).numpy()
        jh = torch.autograd.functional.jacobian(dyn.h, t(xi)).numpy()
        np.testing.assert_allclose(jf, scenario.jac_f(xi, ui), rtol=1e-8, atol=1e-8)
        np.testing.assert_allclose(jh, scenario.jac_h(xi), rtol=1e-8, atol=1e-8)


@pytest.mark.parametrize("name", ["lorenz96", "nlink"])
def test_the_constants_are_the_scenarios(name):
    """Another operating point (more variables, links, substeps) is followed, not the defaults."""
    scenario = make_scenario(name, substeps=3, **({"n_vars": 6} if name == "lorenz96" else {"n_links": 2}))
    dyn = scenario.torch_dynamics()
    x = prior_states(scenario, np.random.default_rng(2), (6,))
    np.testing.assert_allclose(dyn.f(t(x), None).detach().numpy(), scenario.f(x, None), rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(dyn.h(t(x)).detach().numpy(), scenario.h(x), rtol=1e-10, atol=1e-10)


def test_float32_in_float32_out():
    scenario = make_scenario("quadrotor")
    dyn = scenario.torch_dynamics()
    rng = np.random.default_rng(1)
    x, u = prior_states(scenario, rng, (4,)), controls(scenario, rng, (4,))
    fx = dyn.f(t(x).float(), t(u).float())
    assert fx.dtype == torch.float32
    np.testing.assert_allclose(fx.detach().numpy(), scenario.f(x, u), rtol=1e-4, atol=1e-4)


def test_a_scenario_without_a_differentiable_form_says_none():
    from neural_estimator.robot.data_scenario import DataScenario

    meta = {"dt": 0.1, "state_names": ["a"], "state_units": [""], "obs_names": ["b"], "obs_units": [""]}
    assert DataScenario(meta).torch_dynamics() is None


@pytest.mark.slow  # a subprocess (2 s)
def test_the_scenarios_import_without_torch():
    """torch is imported by torch_dynamics() only: building and running every scenario leaves it out."""
    code = (
        "import sys, numpy as np\n"
        "from neural_estimator.scenarios import BUILTIN_SCENARIOS, make_scenario\n"
        "for n in BUILTIN_SCENARIOS:\n"
        "    s = make_scenario(n); x = s.prior()[0]; s.h(s.f(x, np.zeros(s.du)))\n"
        "assert 'torch' not in sys.modules, 'torch imported'\n"
        "make_scenario('ballistic').torch_dynamics()\n"
        "assert 'torch' in sys.modules\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
