"""The reproduce report: report.md with every table beside the paper's
(:mod:`~neural_estimator.paper.reproduce.tables`), the model-mismatch section
(:mod:`~neural_estimator.paper.reproduce.mismatch`) and the figures, written from a run's jobs and
their outcome; a section for each experiment the run did."""

from __future__ import annotations

import math
import platform
import subprocess
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from neural_estimator.metrics import consistency as CONSISTENCY
from neural_estimator.paper import departures as D
from neural_estimator import metrics as M
from neural_estimator.methods import table
from neural_estimator.paper.reproduce import tables as T
from neural_estimator.paper.reproduce.engine import Outcome
from neural_estimator.paper.reproduce.jobs import Job
from neural_estimator.paper.reproduce.plan import noise_reuses_accuracy
from neural_estimator.paper.reproduce.settings import INIT_WORDS, Settings, describe_settings

RUNTIME_WORDS = {
    "step": "Step by step, the live node's cost: each method's real per-step path (`reset(1)`, then one `step` per "
    "observation)",
    "sequence": "Sequence mode, the paper's apparent method: whole trajectories per call (`run` on one (1, T) "
    "sequence: the networks' parallel form, the filters' loop over time; the median of at least {repeats} calls, "
    "more until they took {seconds:g} s)",
}


def versions() -> dict[str, str]:
    import numpy
    import ray
    import torch

    from neural_estimator import __version__

    return {
        "neural_estimator": __version__,
        "python": platform.python_version(),
        "numpy": numpy.__version__,
        "torch": torch.__version__,
        "ray": ray.__version__,
        "platform": platform.platform(),
    }


def git_commit() -> str:
    root = Path(__file__).resolve().parents[3]
    try:
        head = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10)
        dirty = subprocess.run(
            ["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            timeout=10,
        )
    except (OSError, subprocess.SubprocessError):
        return "unknown (no git)"
    if head.returncode != 0:
        return "unknown (not a git checkout)"
    return head.stdout.strip() + (" (with uncommitted changes)" if dirty.stdout.strip() else "")


def write_report(
    out: Path,
    settings: Settings,
    jobs: Sequence[Job],
    outcome: Outcome,
    wall: float,
    before: tuple[float, int] = (0.0, 0),
) -> Path:
    """report.md with every table beside the paper's and the figures (figures/*.png), then the
    model-mismatch section (its sweeps' files in mismatch/), each for the experiments the run did;
    ``before``: (seconds, invocations) of the earlier invocations of a resumed run, added to the wall time."""
    from neural_estimator.paper.reproduce.mismatch import mismatch_section

    r = _gather(settings, jobs, outcome)
    figs = out / "figures"
    ran = set(settings.experiments)
    L = _heading(settings, jobs, outcome, wall, before)
    L += _accuracy(settings, r) + _rmse_over_time(settings, r, figs) if "accuracy" in ran else []
    L += _noise_figures(settings, r, figs) if "noise" in ran else []
    L += _runtime(settings, r) if "runtime" in ran else []
    L += _data_efficiency(settings, jobs, r, figs) if "data_ratio" in ran else []
    if "mismatch" in ran:
        L += mismatch_section(settings.scale, settings.scenarios, jobs, outcome, out)
    path = out / "report.md"
    path.write_text("\n".join(L))
    return path


@dataclass
class _Results:
    """A run's results by experiment, the shapes the tables take."""

    acc: dict[str, dict[str, list]]  # {scenario: {method: [accuracy result]}}
    noise: dict[str, dict[str, dict[float, list]]]  # {scenario: {method: {noise scale: [rmse]}}}
    rt: dict[str, dict[str, dict[str, dict[str, float]]]]  # {mode: {device: {scenario: {method: it/s}}}}
    every: dict[str, dict[str, list[float]]]  # every-step RMSE per run
    contexts: dict[str, dict[str, int]]  # bounded context of each neural cell
    starts: dict[str, dict[str, str]]  # the start each classical cell really got
    ratio: dict[str, dict[str, dict[float, list[float]]]]  # {scenario: {method: {data ratio: [nrmse]}}}
    summ: dict = field(default_factory=dict)  # accuracy summaries (tables.summaries)
    rt_share: dict[str, dict[tuple[str, str], float]] = field(default_factory=dict)  # {mode: {(s, m): CPU share}}
    instances: dict[str, dict[str, int]] = field(default_factory=dict)  # {scenario: {network: instances evaluated}}
    instance_ids: dict[tuple[str, str], set] = field(default_factory=dict)  # {(scenario, network): {instance}}


def _gather(settings: Settings, jobs: Sequence[Job], outcome: Outcome) -> _Results:
    scen, meth, sc = settings.scenarios, settings.methods, settings.scale
    r = _Results(
        acc={s: {m: [] for m in meth} for s in scen},
        noise={s: {m: {} for m in meth} for s in scen},
        rt={},
        every={s: {m: [] for m in meth} for s in scen},
        contexts={s: {} for s in scen},
        starts={s: {} for s in scen},
        ratio={s: {m: {} for m in meth} for s in scen},
    )
    for i, o in outcome.results.items():
        job, res = jobs[i], o["result"]
        if job.experiment == "accuracy":
            r.acc[job.scenario][job.method].append(res)
            if job.kind == "evaluate" and table.has(job.method, family="neural"):
                seen = r.instance_ids.setdefault((job.scenario, job.method), set())
                seen.add(job.instance)
                r.instances.setdefault(job.scenario, {})[job.method] = len(seen)
            r.every[job.scenario][job.method] += _floats([res.get("rmse_every_step")])
            r.starts[job.scenario][job.method] = res.get("start", job.init)
            if res.get("context"):
                r.contexts[job.scenario][job.method] = max(
                    r.contexts[job.scenario].get(job.method, 0), int(res["context"])
                )
            if noise_reuses_accuracy(sc) and 1.0 in sc.noise_scales:
                r.noise[job.scenario][job.method].setdefault(1.0, []).append(_floats([res["rmse"]])[0])
        elif job.experiment == "noise":
            r.noise[job.scenario][job.method].setdefault(job.noise_scale, []).append(_floats([res["rmse"]])[0])
        elif job.experiment == "data_ratio" and job.kind == "evaluate":
            r.ratio[job.scenario][job.method].setdefault(job.data_ratio, []).append(_floats([res["nrmse"]])[0])
        elif job.experiment == "runtime":
            by_device = r.rt.setdefault(job.mode, {}).setdefault(job.device, {})
            by_device.setdefault(job.scenario, {})[job.method] = res["it_per_s"]
            if job.device == "cpu" and res.get("cpu_share") is not None:
                r.rt_share.setdefault(job.mode, {})[(job.scenario, job.method)] = float(res["cpu_share"])
    r.summ = T.summaries(r.acc)
    return r


def _heading(settings: Settings, jobs: Sequence[Job], outcome: Outcome, wall: float, before) -> list[str]:
    """Title, how to read a cell, the settings and the run's facts, the failed jobs."""
    sc = settings.scale
    L: list[str] = [f"# Reproduction report: scale `{sc.name}`", ""]
    L += [
        "Every table cell reads **ours · paper** (the paper's published value after the dot, `—` where the paper has "
        "none). Ours are medians over the evaluation sets (± IQR where the paper gives one).",
        "",
    ]
    if sc.name == "smoke":
        L += [
            "> **Smoke scale**: tiny sizes that check that every experiment runs; "
            "its numbers say nothing about the methods.",
            "",
        ]
    L += ["## Settings", "", "```", describe_settings(settings, len(jobs)), "```", ""]
    L += [
        "| | |",
        "|---|---|",
        f"| git commit | {git_commit()} |",
        f"| wall time | {_wall_words(wall, before)} |",
        f"| jobs | {len(jobs)}: {outcome.computed} computed, {outcome.cached} read from the cache, "
        f"{len(outcome.failed)} failed |",
        f"| seeds | evaluation sets and filters: {sc.seed}; neural models: {_neural_models(sc)} |",
    ]
    L += [f"| {k} | {v} |" for k, v in versions().items()] + [""]
    if outcome.failed:
        L += ["## Failed jobs", ""] + [f"- {jobs[i].label}: `{e}`" for i, e in sorted(outcome.failed.items())] + [""]
    return L


def _accuracy(settings: Settings, r: _Results) -> list[str]:
    """The main accuracy table and the tables made from the same runs."""
    from neural_estimator.metrics import EVALUATION_WARMUP
    from neural_estimator.scenarios import make_scenario

    scen, meth, summ = settings.scenarios, settings.methods, r.summ
    every_med = {s: {m: M.median_iqr(v)[0] for m, v in by_m.items() if v} for s, by_m in r.every.items()}
    marking = dict(init=settings.init, contexts=r.contexts, starts=r.starts)
    L = ["## Main accuracy (paper: Table accuracy_main)", ""]
    L += [
        f"Filters start: {settings.init} ({INIT_WORDS[settings.init]}). "
        + D.scored_steps(EVALUATION_WARMUP, "`--every-step`")
        + " The column *RMSE all steps* scores every step (the paper gives no such figure).",
        "",
    ]
    L += T.accuracy_table(summ, scen, meth, mark_expected=True, every_step=every_med, **marking) + [""]
    used = T.used_marks(summ, scen, meth, mark_expected=True, **marking)
    if used:
        L += ["Marks, each a departure from the paper's protocol:", ""] + T.marks_legend(used, r.contexts) + [""]
    L += T.expected_failure_notes(scen, meth, settings.init, r.starts)
    L += ["## Relative score, 100 RMSE(Mamba-2) / RMSE (paper: Table relative_score)", ""]
    if "mamba2" not in meth:
        L += ["Mamba-2 was not run: no relative score (N/A).", ""]
    L += T.relative_table(summ, scen, meth) + [""]
    L += ["## Extended metrics per scenario (paper: Appendix tables *_extended)", ""]
    for s in scen:
        L += [f"### {s}", ""] + T.extended_table(summ, s, meth, **marking) + [""]
    L += [
        "## Beyond the paper: RMSE per state component",
        "",
        "Each component in its own units, median over sets x instances (the aggregate RMSE adds components of "
        "different units; docs/decisions.md).",
        "",
    ]
    for s in scen:
        sc = make_scenario(s)
        names = [f"{n} [{u}]" if u else n for n, u in zip(sc.state_names, sc.state_units)][:8]
        L += [f"### {s}", ""] + T.components_table(r.acc, s, meth, names, r.instances.get(s)) + [""]
    L += [
        "## Cross-scenario NRMSE (paper: Table nrmse_avg_all)",
        "",
        "Median and IQR over the scenario-level median NRMSEs"
        + ("" if len(scen) == 5 else f" (only {len(scen)} of the paper's 5 scenarios run)")
        + ".",
        "",
    ]
    L += T.nrmse_avg_table(summ, scen, meth) + [""]
    L += (
        ["## Stability: outlier and drift ratios (paper: Table stability_summary_app)", ""]
        + T.stability_table(summ, scen, meth)
        + [""]
    )
    L += [
        "## Beyond the paper: covariance consistency (NEES median, 95 % coverage)",
        "",
        "Methods that report a covariance; a consistent estimator has NEES ≈ dx and 95 % coverage ≈ 0.95.",
        "",
    ]
    L += T.covariance_table(summ, scen, meth) + [""]
    L += [
        "Mean NEES per state dimension and the verdict (consistent: 95 % coverage in "
        f"{list(CONSISTENCY.COVERAGE_BAND)} and mean NEES/dx in {list(CONSISTENCY.NEES_BAND)}; docs/uncertainty.md):",
        "",
    ]
    return L + T.consistency_table(summ, scen, meth, {s: make_scenario(s).dx for s in scen}) + [""]


def _rmse_over_time(settings: Settings, r: _Results, figs: Path) -> list[str]:
    """The RMSE-over-time figures (of the accuracy runs)."""
    from neural_estimator.metrics.plots import plot_rmse_over_time
    from neural_estimator.scenarios import make_scenario

    scen, meth = settings.scenarios, settings.methods
    L = ["## RMSE over time (paper: Appendix figures rmse_time_*)", ""]
    for s in scen:
        curves = {m: [_floats(x["rmse_t"]) for x in r.acc[s][m] if x.get("rmse_t")] for m in meth}
        curves = {m: c for m, c in curves.items() if c}
        first = max((int(x.get("warmup", 0)) for m in meth for x in r.acc[s][m]), default=0)
        if curves:
            p = plot_rmse_over_time(
                curves, figs / f"rmse_over_time_{s}.png", title=s, dt=make_scenario(s).dt, first_step=first
            )
            L += [f"![RMSE over time, {s}](figures/{p.name})", ""]
    return L


def _noise_figures(settings: Settings, r: _Results, figs: Path) -> list[str]:
    """The observation-noise figures."""
    scen, sc = settings.scenarios, settings.scale
    L = [
        "## Robustness to observation noise (paper: Appendix figures noise_*)",
        "",
        f"RMSE against the observation-noise scale {list(sc.noise_scales)} (median over sets, IQR shaded); neural "
        "models are the ones trained at the nominal noise. The paper does not publish its noise levels.",
        "",
    ]
    for s in scen:
        curves = {m: v for m, v in r.noise[s].items() if v}
        if curves:
            p = T.plot_noise(curves, figs / f"noise_{s}.png", title=s)
            L += [f"![noise robustness, {s}](figures/{p.name})", ""]
    return L


def _runtime(settings: Settings, r: _Results) -> list[str]:
    """Iterations per second at batch 1, each mode and device, with the orderings."""
    from neural_estimator.paper.reproduce.jobs import RUNTIME_MODES, SEQUENCE_MIN_SECONDS, SEQUENCE_REPEATS

    scen, meth, sc = settings.scenarios, settings.methods, settings.scale
    L = [
        "## Runtime: iterations per second at batch 1 (paper: Table runtime_full_app)",
        "",
        f"Two ways, {sc.runtime_steps} timed steps after {sc.runtime_warmup} untimed, one thread, the job alone on the "
        "Ray node; the paper's figures (after the dot) are beside both, since the paper does not say how it timed. "
        "Our hardware is not the paper's: compare orderings, not values.",
        "",
    ]
    for mode in RUNTIME_MODES:
        if mode not in r.rt:
            continue
        L += [
            f"### {mode.capitalize()} mode",
            "",
            RUNTIME_WORDS[mode].format(repeats=SEQUENCE_REPEATS, seconds=SEQUENCE_MIN_SECONDS) + ".",
            "",
        ]
        for device in r.rt[mode]:
            L += [f"#### {device.upper()}", ""] + T.runtime_table(r.rt[mode], scen, meth, device) + [""]
            L += [T.runtime_ordering(r.rt[mode][device], scen, meth, "gpu" if device != "cpu" else "cpu"), ""]
            if device == "cpu" and r.rt_share.get(mode):
                L += [cpu_share_words(r.rt_share[mode]), ""]
        if all(device == "cpu" for device in r.rt[mode]):  # the paper's GPU column stays, ours says why not
            why = "no CUDA" if not settings.gpu else "no GPU runtime job"
            L += ["#### GPU", ""] + T.runtime_table_not_measured(scen, meth, "gpu", why) + [""]
    return L


CPU_SHARE_FLOOR = 0.9  # below it a CPU figure was measured while other work took the job's core


def cpu_share_words(shares: dict[tuple[str, str], float]) -> str:
    """One sentence on whether the CPU figures above were measured with the CPU to themselves."""
    (s_low, m_low), low = min(shares.items(), key=lambda kv: kv[1])
    shared = sorted(f"{s} {m} ({v:.2f})" for (s, m), v in shares.items() if v < CPU_SHARE_FLOOR)
    head = (
        f"CPU share of the timed part (the job's CPU time over its wall time; about 1 with the core to itself): "
        f"lowest {low:.2f} ({s_low} {m_low}) of {len(shares)} jobs"
    )
    if not shared:
        return head + "; none measured on a shared CPU."
    return (
        head + f". **{len(shared)} figures were measured while other work took the CPU** (share below "
        f"{CPU_SHARE_FLOOR}): {', '.join(shared)}; they understate the speed. Measure them again on an otherwise "
        "idle machine (remove the result cache's runtime/ folder and run the same command)."
    )


def _data_efficiency(settings: Settings, jobs: Sequence[Job], r: _Results, figs: Path) -> list[str]:
    """The data-ratio table and figures (the paper's values alone when no neural method ran)."""
    scen, meth, sc = settings.scenarios, settings.methods, settings.scale
    neural = [m for m in meth if table.has(m, trainable=True)]
    L = ["## Data efficiency (paper: Table data_ratio_main, figures data_ratio_*)", ""]
    if not neural:
        return (
            L
            + ["No neural method was run: no data-efficiency experiment. The paper's values:", ""]
            + T.data_ratio_paper_table()
            + [""]
        )
    n_train = sum(1 for j in jobs if j.kind == "train")
    L += [
        f"Median NRMSE across scenarios of each scenario's median over sets × instances; {n_train} models trained "
        f"({sc.train_instances} instance(s) per scenario, architecture and ratio; recipe: the paper's"
        + (f" with {dict(sc.train_overrides)}" if sc.train_overrides else "")
        + (
            f", {sc.train_trajectories_at_20} training trajectories at 20:1 scaled by the ratio"
            if sc.train_trajectories_at_20
            else ""
        )
        + ")"
        + ("" if len(scen) == 5 else f"; only {len(scen)} of the paper's 5 scenarios run")
        + ".",
        "",
    ]
    L += T.data_ratio_table(r.ratio, scen, neural, sc.data_ratios) + [""]
    for s in scen:
        by_m = {m: r.ratio[s][m] for m in neural if r.ratio[s][m]}
        if by_m:
            p = T.plot_data_ratio(by_m, figs / f"data_ratio_{s}.png", title=s)
            L += [f"![data efficiency, {s}](figures/{p.name})", ""]
    return L


def _wall_words(wall: float, before: tuple[float, int]) -> str:
    if not before[1]:
        return f"{wall:.1f} s"
    n = before[1] + 1
    return f"{before[0] + wall:.1f} s over {n} invocations (this one {wall:.1f} s; the run was resumed)"


def _neural_models(sc) -> str:
    if sc.main_from_training:
        return (
            f"{sc.train_instances} instances per architecture trained at 20:1 (init seeds 0-{sc.train_instances - 1}, "
            f"data seed {sc.seed}) for the accuracy and noise tables; the shipped checkpoints for runtime"
        )
    return (
        "every instance the zoo ships for the accuracy and noise tables (median over instances x sets; each "
        "network's count in the components table), the shipped model (instance 0) for runtime"
    )


def _floats(values) -> list[float]:
    """JSON numbers back to floats: null (a value that was not finite) becomes NaN (left out of plots)."""
    return [math.nan if v is None else float(v) for v in values]
