"""The practitioner's start: filters initialised from the first observation where h is invertible.

``init="observation"`` (a filter argument; ``evaluate --init observation``, ``replay --init``, the
estimator node's ``init`` parameter, ``neural-estimator live --init``) replaces the prior mean at
step 0 by the state y_0 determines (Lorenz 96, H = I: x = y_0; N-link: the angles from the mass
positions); the paper's start, the prior, stays the default.
"""

from __future__ import annotations

import numpy as np
import pytest

from neural_estimator.data import simulate
from neural_estimator.methods.registry import CLASSICAL_METHODS, EstimatorError, make_estimator
from neural_estimator.evaluation import evaluate
from neural_estimator.scenarios import make_scenario

SMALL = {"pf": {"n_particles": 256}, "enkf": {"n_members": 16}}


def _filter(method, scenario, **kw):
    return make_estimator(method, scenario, seed=0, threads=1, **SMALL.get(method, {}), **kw)


def test_h_is_inverted_where_it_can_be():
    rng = np.random.default_rng(0)
    for name in ("lorenz96", "nlink"):
        s = make_scenario(name)
        x = s.sample_initial(rng, 5)
        xo, observed = s.state_from_observation(s.h(x))
        np.testing.assert_allclose(xo[:, observed], x[:, observed], atol=1e-9)
        np.testing.assert_array_equal(
            xo[:, ~observed], np.broadcast_to(s.prior()[0][~observed], xo[:, ~observed].shape)
        )
    assert make_scenario("lorenz96").state_from_observation(np.zeros((1, make_scenario("lorenz96").dy)))[1].all()
    for name in ("bearings", "quadrotor", "ballistic"):  # a bearing, 3 mixtures of 6 states, a range: no inverse
        s = make_scenario(name)
        assert s.state_from_observation(np.zeros((1, s.dy))) is None


@pytest.mark.parametrize("name", ["bearings", "quadrotor"])
def test_observation_start_is_refused_where_h_determines_nothing(name):
    with pytest.raises(EstimatorError, match="init=observation needs an observation"):
        make_estimator("pf", make_scenario(name), init="observation")
    with pytest.raises(EstimatorError, match="init must be one of prior, observation"):
        make_estimator("ekf", make_scenario("lorenz96"), init="truth")


@pytest.mark.parametrize("method", CLASSICAL_METHODS)
def test_run_equals_a_loop_of_step_from_the_observation(method):
    s = make_scenario("lorenz96")
    d = simulate(s, 3, 12, seed=1)
    a = _filter(method, s, init="observation").run(d.y, d.u)
    f = _filter(method, s, init="observation")
    f.reset(3)
    from neural_estimator.methods.registry import previous_controls

    Up = previous_controls(d.u)
    xs = np.stack([f.step(d.y[:, k], Up[:, k]) for k in range(12)], axis=1)
    np.testing.assert_allclose(xs, a.x, rtol=0, atol=1e-10)
    prior = _filter(method, s).run(d.y, d.u)
    assert not np.allclose(prior.x[:, 0], a.x[:, 0])  # the start is not the prior's


def test_lorenz96_pf_tracks_from_the_first_observation_where_it_collapses_from_the_prior():
    """The expected failure the live pipeline had: the PF's unit cloud around the climatological mean."""
    s = make_scenario("lorenz96")
    d = simulate(s, 8, 120, seed=2)
    err = {}
    for init in ("prior", "observation"):
        est = make_estimator("pf", s, seed=0, threads=1, init=init).run(d.y, d.u)
        err[init] = float(np.sqrt(np.mean((est.x[:, 20:] - d.x[:, 20:]) ** 2, axis=(1, 2))).mean())
    assert err["observation"] < 0.25 * err["prior"]
    assert err["observation"] < 0.5  # the observation noise is 1.0: it tracks


def test_evaluate_keys_and_reports_the_start(tmp_path):
    s = make_scenario("lorenz96")
    kw = dict(trajectories=4, horizon=20, sets=1, cache_dir=tmp_path, progress=False, options={"pf": SMALL["pf"]})
    obs = evaluate(s, ["pf", "ekf"], init="observation", **kw)
    prior = evaluate(s, ["pf", "ekf"], **kw)
    assert obs["pf"].init == "observation" and prior["pf"].init == "prior"
    assert obs["pf"].cached == 0 and prior["pf"].cached == 0  # two cache entries, not one read as the other
    assert obs["ekf"].reports[0].rmse != prior["ekf"].reports[0].rmse


def test_live_launcher_passes_the_start_to_the_filters_and_the_evaluator(tmp_path, monkeypatch):
    from neural_estimator.nodes import launch

    started = {}

    class Done:
        returncode, pid = 0, 0

        def poll(self):
            return 0

    def fake_start(cmd, log, env):
        started[log.stem] = cmd
        return Done()

    monkeypatch.setattr(launch, "start_node", fake_start)
    launch.run_pipeline(
        launch.PipelineConfig("lorenz96", ("pf", "gru"), init="observation", output=str(tmp_path / "r.mcap"))
    )
    assert 'init:="observation"' in started["estimator_pf"]
    assert not any(a.startswith("init:=") for a in started["estimator_gru"])  # networks have no start
    assert 'starts:=["pf=observation"]' in started["evaluator"]
    assert launch.build_parser().parse_args(["--scenario", "x", "--methods", "pf"]).init == "prior"  # the paper's


@pytest.mark.slow
def test_replay_starts_the_filters_from_the_first_observation(tmp_path, capsys):
    from pathlib import Path

    from neural_estimator.cli import main

    bag = Path(__file__).resolve().parents[1] / "bags" / "lorenz96.mcap"
    args = ["replay", str(bag), "--methods", "pf,ekf", "--metrics"]  # the default 1,024 particles
    assert main([*args, "--out", str(tmp_path / "obs.mcap"), "--init", "observation"]) == 0
    obs = capsys.readouterr().out
    assert main([*args, "--out", str(tmp_path / "prior.mcap")]) == 0
    prior = capsys.readouterr().out

    def pf_row(text):
        return next(line for line in text.splitlines() if line.startswith("pf"))

    assert pf_row(obs).split()[1] == "[y]" and not pf_row(obs).endswith("(!)")
    assert pf_row(prior).endswith("(!)") and "[y]" not in prior
    assert float(pf_row(obs).split()[2]) < 0.25 * float(pf_row(prior).split()[1])  # RMSE: tracks vs collapsed


def test_the_main_job_runs_all_ten_methods_with_none_expected_to_fail():
    """scripts/run_demo.sh: Lorenz 96, the ten methods, filters started from the first observation, and
    the expected-failure machinery agrees that none of them fails there (no "(!)" row)."""
    import re
    from pathlib import Path

    from neural_estimator.methods.registry import METHODS
    from neural_estimator.paper.expected_failures import expected_to_fail

    demo = (Path(__file__).resolve().parents[1] / "scripts" / "run_demo.sh").read_text()
    assert "args+=(--init observation)" in demo and "args+=(--scenario lorenz96)" in demo
    assert re.search(r"args\+=\(--methods \"\$\(\"\$venv/bin/python\" -m neural_estimator\.methods\.table\)\"\)", demo)
    methods = list(METHODS)  # what `python -m neural_estimator.methods.table` prints: every method of the table
    assert [m for m in methods if expected_to_fail("lorenz96", m, "observation")] == []
    assert [m for m in methods if expected_to_fail("lorenz96", m, "prior")] == ["pf"]  # the paper's start


def test_the_protocol_starts_from_the_prior_where_the_observation_determines_nothing(tmp_path):
    """evaluate / reproduce --init observation on bearings: the prior (the same run, read from the cache)."""
    s = make_scenario("bearings")
    kw = dict(trajectories=3, horizon=15, sets=1, cache_dir=tmp_path, progress=False)
    prior = evaluate(s, ["ekf"], **kw)
    obs = evaluate(s, ["ekf"], init="observation", **kw)
    assert obs["ekf"].init == "prior" and obs["ekf"].cached == 1
    assert obs["ekf"].reports[0].rmse == prior["ekf"].reports[0].rmse
