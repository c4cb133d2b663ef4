"""Departures from the paper's protocol are marked where the number is printed, and only there.

Marks (neural_estimator/paper/departures.py): [c] bounded context, [o] the outlier rule decides the RMSE
(the Full RMSE beside it), [t] / [y] filters started from the truth / the first observation, (!) an
expected failure under that start; the scored steps are named as this project's choice, and the
every-step RMSE is in every report and in the reproduce report's main table.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from neural_estimator.paper import departures as D
from neural_estimator import metrics as M
from neural_estimator.evaluation import MethodResult, results_table
from neural_estimator.paper.expected_failures import MARK, expected_to_fail, mark_rows, notes


def _report(rng, scale, outliers=0, n=40, t=30, dx=2, warmup=10):
    x = rng.standard_normal((n, t, dx))
    xh = x + scale * rng.standard_normal(x.shape)
    xh[:outliers] += 50.0 * scale  # a few trajectories far off: flagged by the outlier rule
    return M.compute_metrics(x, xh, warmup=warmup)


# ---- the rules -----------------------------------------------------------------------------------


def test_outlier_mark_only_where_the_dropped_trajectories_change_the_rmse():
    assert D.rests_on_outliers(0.288, 0.43)
    assert D.rests_on_outliers(0.05, math.inf)
    assert not D.rests_on_outliers(0.049, 0.049)
    assert not D.rests_on_outliers(1.0, 1.0 + 0.5 * D.OUTLIER_TOLERANCE)  # within the tolerance
    assert not D.rests_on_outliers(math.nan, 1.0) and not D.rests_on_outliers(None, 1.0)


def test_row_marks_by_start_and_context():
    assert D.row_marks("pf", init="truth") == [D.FROM_TRUTH]
    assert D.row_marks("ekf", init="observation") == [D.FROM_OBSERVATION]
    assert D.row_marks("pf", init="prior") == []  # the paper's start: no mark
    assert D.row_marks("mamba", init="truth") == []  # a network has no start mode
    assert D.row_marks("gru", context=100) == [D.BOUNDED]
    assert D.row_marks("gru", context=0) == []


def test_legend_explains_each_used_mark_once_and_no_other():
    lines = D.legend([D.OUTLIERS, D.BOUNDED, D.OUTLIERS], contexts=[100, 0])
    assert [line.split(" ", 1)[0] for line in lines] == [D.BOUNDED, D.OUTLIERS]
    assert "at most 100 steps" in lines[0]
    assert D.legend([]) == [] and D.legend_text([]) == []
    assert all(not line.startswith("[") for line in D.legend_text([D.BOUNDED]))  # survives the launcher's filter


def test_scored_steps_are_named_as_this_projects_choice():
    text = D.scored_steps(10)
    assert "this project's choice" in text and "training loss only" in text and "--every-step" in text
    assert D.scored_steps(0) == "Every step scored."


def test_expected_failures_depend_on_the_start():
    assert expected_to_fail("lorenz96", "pf", "prior")
    assert not expected_to_fail("lorenz96", "pf", "observation")  # the start was the whole failure
    assert not expected_to_fail("lorenz96", "pf", "truth")
    assert expected_to_fail("quadrotor", "pf", "observation")  # degenerates from any start
    table = "Method RMSE\nekf 0.05\npf 0.06\n"
    assert MARK not in mark_rows(table, "lorenz96", {"pf": "observation"})
    assert mark_rows(table, "lorenz96").splitlines()[2].endswith(MARK)
    assert notes("lorenz96", ["pf"], "observation") == []


# ---- the every-step figure -----------------------------------------------------------------------


def test_every_step_rmse_is_in_every_report():
    rng = np.random.default_rng(0)
    x = rng.standard_normal((20, 30, 2))
    xh = x + 0.1 * rng.standard_normal(x.shape)
    xh[:, :5] += 3.0  # a bad start: the warm-up steps are far off
    scored = M.compute_metrics(x, xh, warmup=10)
    every = M.compute_metrics(x, xh, warmup=0)
    assert scored.rmse < 0.2 < 1.0 < scored.rmse_every_step
    assert scored.rmse_every_step == pytest.approx(every.rmse)
    assert every.rmse_every_step == every.rmse
    assert M.to_json(scored)["rmse_every_step"] == pytest.approx(every.rmse)


# ---- evaluate / metrics tables -------------------------------------------------------------------


def _results(rng):
    ekf = MethodResult("ekf", [_report(rng, 0.05)], init="observation")
    pf = MethodResult("pf", [_report(rng, 0.05, outliers=4)], init="observation")
    gru = MethodResult("gru", [_report(rng, 0.08)], context=100)
    mamba = MethodResult("mamba", [_report(rng, 0.06)])
    return {"ekf": ekf, "pf": pf, "gru": gru, "mamba": mamba}


def test_evaluate_table_marks_rows_and_cells_that_depart():
    from neural_estimator.evaluation import departure_legend

    results = _results(np.random.default_rng(1))
    rows = {line.split()[0]: line for line in results_table(results, fmt="text", marked=True).splitlines()[1:]}
    assert rows["ekf"].split()[1] == D.FROM_OBSERVATION and D.OUTLIERS not in rows["ekf"]
    assert D.FROM_OBSERVATION in rows["pf"] and D.OUTLIERS in rows["pf"]  # 4 of 40 dropped: RMSE << Full RMSE
    assert rows["gru"].split()[1] == D.BOUNDED
    assert not any(mk in rows["mamba"] for mk in (D.BOUNDED, D.OUTLIERS, D.FROM_TRUTH, D.FROM_OBSERVATION))
    legend = departure_legend(results)
    assert legend[0] == "Marks:" and [line.split()[0] for line in legend[1:]] == [
        D.BOUNDED,
        D.OUTLIERS,
        D.FROM_OBSERVATION,
    ]
    assert results_table(results, fmt="text") == M.format_table({m: r.summary for m, r in results.items()}, "text")


def test_a_table_without_departures_has_no_marks_and_no_legend():
    from neural_estimator.evaluation import departure_legend

    rng = np.random.default_rng(2)
    results = {"ekf": MethodResult("ekf", [_report(rng, 0.05)]), "mamba": MethodResult("mamba", [_report(rng, 0.06)])}
    text = results_table(results, fmt="text", marked=True)
    assert not any(mk in text for mk in (D.BOUNDED, D.OUTLIERS, D.FROM_TRUTH, D.FROM_OBSERVATION, MARK))
    assert departure_legend(results) == []


def test_bag_summary_marks_the_live_start_and_drops_the_start_only_failure(tmp_path):
    from neural_estimator.evaluation.bag_report import BagReport

    rng = np.random.default_rng(3)
    reports = {"ekf": _report(rng, 0.05, warmup=0), "pf": _report(rng, 0.05, warmup=0)}
    common = dict(path=tmp_path / "run.mcap", scenario="lorenz96", n_trajectories=40, horizon=30, dt=0.05)
    prior = BagReport(reports=reports, bag={}, **common).summary()
    live = BagReport(reports=reports, bag={}, starts={"ekf": "observation", "pf": "observation"}, **common).summary()
    pf_prior = next(line for line in prior.splitlines() if line.startswith("pf"))
    pf_live = next(line for line in live.splitlines() if line.startswith("pf"))
    assert pf_prior.endswith(MARK) and D.FROM_OBSERVATION not in pf_prior
    assert not pf_live.endswith(MARK) and pf_live.split()[1] == D.FROM_OBSERVATION
    assert sum(line.strip().startswith(D.FROM_OBSERVATION) for line in live.splitlines()) == 1  # the legend, once
    assert sum(D.FROM_OBSERVATION in line for line in live.splitlines()) == 3  # two rows and the legend
    assert "Every step scored." in live


def test_metrics_verb_names_the_scored_steps_and_marks_outliers_and_starts(tmp_path, capsys):
    from neural_estimator.cli import main
    from neural_estimator.data import load_trajectories
    from neural_estimator.data.io import save_npz

    data = tmp_path / "d.npz"
    args = ["simulate", "--scenario", "lorenz96", "--trajectories", "40", "--horizon", "30", "--out", str(data)]
    assert main(args) == 0
    truth, _ = load_trajectories(data)
    rng = np.random.default_rng(4)
    xh = truth.x + 0.05 * rng.standard_normal(truth.x.shape)
    xh[:4] += 5.0  # four trajectories far off: dropped by the outlier rule
    save_npz(tmp_path / "pf.npz", {"x_hat": xh}, {"method": "pf"})
    capsys.readouterr()
    assert main(["metrics", str(data), str(tmp_path / "pf.npz")]) == 0
    out = capsys.readouterr().out
    pf = next(line for line in out.splitlines() if line.startswith("pf"))
    assert D.OUTLIERS in pf and pf.endswith(MARK)  # recorded from the prior (default): the expected failure
    assert "this project's choice" in out and "Marks:" in out
    assert main(["metrics", str(data), str(tmp_path / "pf.npz"), "--every-step", "--start", "pf=observation"]) == 0
    out = capsys.readouterr().out
    pf = next(line for line in out.splitlines() if line.startswith("pf"))
    assert pf.split()[1] == D.FROM_OBSERVATION and not pf.endswith(MARK)
    assert "Every step scored." in out and "steps 10.. scored" not in out


# ---- the reproduce report ------------------------------------------------------------------------


def _fake_run(tmp_path, init="prior"):
    """write_report on fabricated results: accuracy on lorenz96 and quadrotor for a filter, the PF and
    two networks (GRU with a bounded context on lorenz96), runtime in both modes."""
    pytest.importorskip("ray")
    from neural_estimator.paper.reproduce.engine import Outcome
    from neural_estimator.paper.reproduce.jobs import Job
    from neural_estimator.paper.reproduce.report import write_report
    from neural_estimator.paper.reproduce.settings import Settings
    from neural_estimator.paper.reproduce.scales import get_scale

    rng = np.random.default_rng(5)
    scale = get_scale("smoke")
    scen, meth = ["quadrotor", "lorenz96"], ["ekf", "pf", "gru", "mamba2"]
    jobs, outcome = [], Outcome()
    for s in scen:
        for m in meth:
            res = M.to_json(_report(rng, 0.05 if m != "pf" else 0.5, outliers=6 if m == "pf" else 0))
            res["context"] = 100 if (s, m) == ("lorenz96", "gru") else 0
            # the start each filter got: --init observation is the prior where h determines nothing (quadrotor)
            res["start"] = init if m in ("ekf", "pf") and (init != "observation" or s == "lorenz96") else "prior"
            jobs.append(Job("evaluate", s, m, trajectories=40, init=init))
            outcome.results[len(jobs) - 1] = {"cached": False, "seconds": 0.1, "result": res}
            for mode, rate in (
                ("step", 1000.0 if m in ("ekf", "pf") else 300.0),
                ("sequence", 2000.0 * (m not in ("ekf", "pf")) + 900.0),
            ):
                jobs.append(Job("runtime", s, m, steps=10, warmup=2, experiment="runtime", mode=mode))
                outcome.results[len(jobs) - 1] = {"cached": False, "seconds": 0.1, "result": {"it_per_s": rate}}
    settings = Settings(
        scale, scen, meth, gpu=False, cache_dir=str(tmp_path / "cache"), address=None, num_cpus=1, init=init
    )
    path = write_report(tmp_path / "out", settings, jobs, outcome, 1.0)
    text = path.read_text()
    main_table = text.split("## Main accuracy")[1].split("## Relative score")[0]
    rows = {
        line.split("|")[1].strip(): line
        for line in main_table.splitlines()
        if line.startswith("| ") and "---" not in line
    }
    return text, main_table, rows


@pytest.mark.slow
def test_report_main_table_marks_departures_and_shows_the_every_step_rmse(tmp_path):
    text, main_table, rows = _fake_run(tmp_path)
    header = next(line for line in main_table.splitlines() if line.startswith("| Method"))
    assert header.count("RMSE all steps") == 2  # beside the scored RMSE of each scenario
    assert "this project's choice" in main_table and "training loss only" in main_table
    gru = rows["GRU"].split("|")
    assert D.BOUNDED not in gru[2] and D.BOUNDED in gru[5]  # quadrotor cell unmarked, lorenz96 cell marked
    assert D.OUTLIERS in rows["PF"] and "(full " in rows["PF"]
    assert all(D.OUTLIERS not in rows[m] for m in ("EKF", "GRU", "Mamba-2"))
    assert rows["PF"].count(f"{MARK} · ") == 2  # both PF rows are expected failures from the prior
    assert not any(mk in main_table for mk in (D.FROM_TRUTH, D.FROM_OBSERVATION))  # the paper's start: unmarked
    legend = [line for line in main_table.splitlines() if line.startswith("- [") or line.startswith(f"- {MARK}")]
    assert [line.split()[1] for line in legend] == [D.BOUNDED, D.OUTLIERS, MARK]  # each mark once
    every = rows["EKF"].split("|")[3]
    assert every.strip().endswith("· —") and float(every.split("·")[0]) > 0  # ours, and the paper has none


@pytest.mark.slow
def test_report_marks_the_start_where_it_applied_and_keeps_only_start_independent_failures(tmp_path):
    _, main_table, rows = _fake_run(tmp_path, init="observation")
    pf, ekf, gru = rows["PF"].split("|"), rows["EKF"].split("|"), rows["GRU"].split("|")
    # columns: 2-4 quadrotor (RMSE, all steps, NRMSE), 5-7 lorenz96; h inverts nothing on quadrotor
    assert D.FROM_OBSERVATION in pf[5] and D.FROM_OBSERVATION in ekf[5]
    assert D.FROM_OBSERVATION not in pf[2] and D.FROM_OBSERVATION not in ekf[2]  # started from the prior there
    assert D.FROM_OBSERVATION not in rows["GRU"]  # networks carry no start mark
    assert MARK in pf[2] and MARK not in pf[5]  # quadrotor PF fails from any start; Lorenz 96's only from the prior
    assert D.BOUNDED in gru[5]
    assert any(line.startswith(f"- {D.FROM_OBSERVATION}") for line in main_table.splitlines())
    assert "- lorenz96: (!) pf" not in main_table and "- quadrotor: (!) pf" in main_table


@pytest.mark.slow
def test_report_times_both_ways_and_says_which_ordering_each_supports(tmp_path):
    text, _, _ = _fake_run(tmp_path)
    runtime = text.split("## Runtime")[1].split("## Data efficiency")[0]
    step = runtime.split("### Step mode")[1].split("### Sequence mode")[0]
    sequence = runtime.split("### Sequence mode")[1]
    assert "live node's cost" in step and "| EKF | 1,000.0 · " in step
    assert "This mode supports the filters ahead of the networks" in step and "against the paper's ordering" in step
    assert "the paper's apparent method" in sequence and "| GRU | 2,900.0 · " in sequence
    assert "This mode supports the networks ahead of the filters" in sequence
    assert "; the paper's ordering" in sequence


def test_plan_and_jobs_time_both_modes(tmp_path, monkeypatch):
    from neural_estimator.paper.reproduce.jobs import Job, run_job
    from neural_estimator.paper.reproduce.plan import plan_jobs
    from neural_estimator.paper.reproduce.scales import get_scale

    jobs = [j for j in plan_jobs(get_scale("smoke"), ["ballistic"], ["ekf", "gru"]) if j.kind == "runtime"]
    assert sorted((j.method, j.mode) for j in jobs) == [
        ("ekf", "sequence"),
        ("ekf", "step"),
        ("gru", "sequence"),
        ("gru", "step"),
    ]
    assert "mode" not in Job("runtime", "ballistic", "ekf").to_json()  # step mode's keys are unchanged

    import neural_estimator.methods.registry as E

    real, calls = E.make_estimator, {"run": 0, "step": 0}

    def counting(*a, **k):
        est = real(*a, **k)
        run, step = est.run, est.step
        est.run = lambda *x, **y: (calls.__setitem__("run", calls["run"] + 1), run(*x, **y))[1]
        est.step = lambda *x, **y: (calls.__setitem__("step", calls["step"] + 1), step(*x, **y))[1]
        return est

    monkeypatch.setattr(E, "make_estimator", counting)
    seq = run_job(Job("runtime", "ballistic", "ekf", steps=10, warmup=2, mode="sequence"), tmp_path)
    assert seq["result"]["mode"] == "sequence" and seq["result"]["it_per_s"] > 0
    from neural_estimator.paper.reproduce.jobs import SEQUENCE_MAX_REPEATS, SEQUENCE_REPEATS

    # one untimed call on the warm-up steps, then timed calls until enough time is measured
    assert 1 + SEQUENCE_REPEATS <= calls["run"] <= 1 + SEQUENCE_MAX_REPEATS
    step = run_job(Job("runtime", "ballistic", "ekf", steps=10, warmup=2), tmp_path)
    assert not step["cached"] and step["result"]["mode"] == "step"  # its own cache entry
