"""The model-mismatch experiment of ``reproduce``: planned for all five scenarios at every scale, one
job per sweep running the ``mismatch`` verb's code, cached by what defines it, and its report section
(the crossover tables and each sweep's figure) written from the jobs' results. No Ray: jobs run
in this process (:func:`~neural_estimator.paper.reproduce.jobs.run_job` is Ray-free)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest

from neural_estimator.cli import main
from neural_estimator.evaluation import mismatch as MM
from neural_estimator.paper.reproduce.jobs import EXPERIMENTS, Job, run_job
from neural_estimator.paper.reproduce.mismatch import mismatch_key, mismatch_path
from neural_estimator.paper.reproduce.plan import plan_jobs
from neural_estimator.paper.reproduce.scales import SCALES, get_scale
from neural_estimator.paper.results import PAPER_SCENARIOS

ROOT = Path(__file__).resolve().parents[1]
# a tiny sweep: 2 sets of 3 trajectories, 20 steps, three values of the Lorenz 96 forcing
TINY = Job(
    "mismatch",
    "lorenz96",
    "",
    trajectories=3,
    horizon=20,
    experiment="mismatch",
    parameter="forcing",
    values=(0.9, 1.0, 1.1),
    sets=2,
)


def _sweeps(jobs) -> list[tuple[str, str]]:
    return [(j.scenario, j.parameter) for j in jobs if j.kind == "mismatch"]


@pytest.mark.parametrize("name", list(SCALES))
def test_every_scale_plans_each_declared_sweep_of_the_five_scenarios_once(name):
    scale = get_scale(name)
    jobs = plan_jobs(scale, list(PAPER_SCENARIOS), ["ekf", "gru"])
    declared = {(s, p) for s in PAPER_SCENARIOS for p in MM.EXPERIMENT[s]}
    assert len(PAPER_SCENARIOS) == 5 and len(declared) == 15
    assert sorted(_sweeps(jobs)) == sorted(declared)  # each once
    mm = [j for j in jobs if j.kind == "mismatch"]
    assert {(j.trajectories, j.sets, j.horizon) for j in mm} == {
        (scale.mismatch_trajectories, scale.mismatch_sets, scale.horizon)
    }
    for j in mm:
        grid = scale.mismatch_noise_values if j.parameter in ("Q", "R") else scale.mismatch_values
        assert j.values == tuple(sorted(grid)) and 1.0 in j.values and j.experiment == "mismatch"
    # parameter-major: every scenario's first sweep before any second one; its others wait for it (they
    # read its exact-model and network runs from the cache)
    assert {j.scenario for j in mm[:5]} == set(PAPER_SCENARIOS) and {j.parameter for j in mm[5:]} == {"Q", "R"}
    assert all(j.after is None for j in mm[:5])
    assert all(j.after == mm[PAPER_SCENARIOS.index(j.scenario)] for j in mm[5:])


def test_the_small_scale_is_the_size_of_the_committed_sweeps():
    """``reproduce --scale small`` regenerates docs/results/mismatch: the same sets, sizes and grids."""
    jobs = [j for j in plan_jobs(get_scale("small"), list(PAPER_SCENARIOS), ["ekf"]) if j.kind == "mismatch"]
    for j in jobs:
        committed = json.loads((ROOT / "docs/results/mismatch" / f"{j.scenario}-{j.parameter}.json").read_text())
        assert (j.trajectories, j.sets, j.seed) == (committed["trajectories"], committed["sets"], committed["seed"])
        assert list(j.values) == committed["values"], j.label


def test_experiments_select_the_jobs():
    sc = get_scale("smoke")
    only = plan_jobs(sc, ["lorenz96", "nlink"], ["ekf"], experiments=["mismatch"])
    assert only and {j.kind for j in only} == {"mismatch"} and len(only) == 6
    without = plan_jobs(sc, ["lorenz96"], ["ekf"], experiments=[e for e in EXPERIMENTS if e != "mismatch"])
    assert without and not _sweeps(without)
    # the noise sweep alone measures its nominal point itself (no accuracy run to reuse)
    noise = plan_jobs(sc, ["lorenz96"], ["ekf"], experiments=["noise"])
    assert {j.noise_scale for j in noise} == set(sc.noise_scales) and {j.experiment for j in noise} == {"noise"}
    assert 1.0 not in {j.noise_scale for j in plan_jobs(sc, ["lorenz96"], ["ekf"]) if j.experiment == "noise"}
    # a scenario that declares no sweep (a plugin's) has no mismatch job
    assert not _sweeps(plan_jobs(sc, ["oscillator"], ["ekf"], experiments=["mismatch"]))


def test_the_cache_key_follows_the_sweep_definition(monkeypatch):
    import neural_estimator.evaluation as E

    key = mismatch_key(TINY)
    assert mismatch_key(Job(**{**TINY.__dict__})) == key  # nothing changed: the same key
    for change in (
        {"values": (0.8, 1.0, 1.1)},
        {"trajectories": 4},
        {"sets": 3},
        {"horizon": 30},
        {"seed": 1},
        {"parameter": "Q"},
    ):
        assert mismatch_key(Job(**{**TINY.__dict__, **change})) != key, change
    # a network's weights changed: another key (the checkpoints' content digests are part of it)
    real = E.checkpoint_digest
    monkeypatch.setattr(E, "checkpoint_digest", lambda s, m, c: "retrained" if m == "gru" else real(s, m, c))
    assert mismatch_key(TINY) != key
    monkeypatch.undo()
    assert mismatch_key(TINY) == key
    assert mismatch_path("/c", TINY).parent == Path("/c/mismatch")
    assert mismatch_key(replace(TINY, after=replace(TINY, parameter="Q"))) == key  # whom it waits for: no result
    # the fields of the mismatch kind leave the other kinds' JSON, hence their keys, unchanged
    assert not {"parameter", "values", "sets"} & set(Job("runtime", "ballistic", "ekf").to_json())


def test_a_mismatch_job_is_the_verbs_sweep_and_feeds_the_report_section(tmp_path):
    pytest.importorskip("ray")  # the report records Ray's version
    from neural_estimator.paper.reproduce.engine import Outcome
    from neural_estimator.paper.reproduce.report import write_report
    from neural_estimator.paper.reproduce.settings import Settings
    from neural_estimator.scenarios import make_scenario

    first = run_job(TINY, tmp_path / "cache")
    assert first["job"]["kind"] == "mismatch" and not first["cached"]
    direct = MM.mismatch(
        make_scenario("lorenz96"), "forcing", [0.9, 1.0, 1.1], trajectories=3, sets=2, horizon=20, cache_dir=False
    )
    assert first["result"] == json.loads(json.dumps(direct))  # the verb's code, not a copy of it
    again = run_job(TINY, tmp_path / "cache")
    assert again["cached"] and again["result"] == first["result"]
    res = first["result"]
    assert set(res["crossover"]) == {"network", "hybrid"}  # the best network and the shipped hybrid

    settings = Settings(
        get_scale("smoke"),
        ["lorenz96", "nlink"],
        ["ekf"],
        gpu=False,
        cache_dir=str(tmp_path / "cache"),
        address=None,
        num_cpus=1,
        experiments=("mismatch",),
    )
    outcome = Outcome(results={0: first})
    text = write_report(tmp_path / "out", settings, [TINY], outcome, 1.0).read_text()
    assert "## Main accuracy" not in text and "## Runtime" not in text  # only the experiment run
    section = text.split("## Model mismatch")[1]
    lorenz = section.split("### lorenz96")[1].split("### nlink")[0]
    net, hyb = res["crossover"]["network"], res["crossover"]["hybrid"]
    for side, words in (("above", "too large"), ("below", "too small")):
        row = f"| `forcing` (true 8) | {words} | {net['method']} {MM.crossover_text(net[side])} | "
        assert row + f"{hyb['method']} {MM.crossover_text(hyb[side])} |" in lorenz
    exact = next(p for p in res["points"] if p["value"] == 1.0)
    assert f"| {exact['best_filter']} {exact['methods'][exact['best_filter']]['rmse']:.4g} | " in lorenz
    assert "![lorenz96: forcing mismatch](mismatch/lorenz96-forcing.png)" in lorenz
    png = (tmp_path / "out" / "mismatch" / "lorenz96-forcing.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 5000
    assert json.loads((tmp_path / "out" / "mismatch" / "lorenz96-forcing.json").read_text()) == res
    assert "No sweep of this scenario finished" in section.split("### nlink")[1]


def test_unknown_experiment_is_a_one_line_error(tmp_path, capsys):
    pytest.importorskip("ray")
    rc = main(["reproduce", "--scale", "smoke", "--experiments", "mismatch,crossover", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "unknown experiment 'crossover'" in err and "\n" not in err
    assert not (tmp_path / "o").exists()
