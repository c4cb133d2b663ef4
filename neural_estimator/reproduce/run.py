"""``reproduce``: plan the scale's jobs, run them on Ray, write the report (markdown + PNGs + JSON)."""

from __future__ import annotations

import json
import math
import platform
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from neural_estimator import consistency as CONSISTENCY
from neural_estimator import departures as D
from neural_estimator import metrics as M
from neural_estimator.reproduce import report as R
from neural_estimator.reproduce.engine import Outcome, run_jobs
from neural_estimator.reproduce.jobs import Job
from neural_estimator.reproduce.plan import noise_reuses_accuracy, plan_jobs
from neural_estimator.reproduce.scales import Scale

STATE_FILE = "reproduce.json"  # in --out: the run's settings and every job's status
INIT_WORDS = {
    "prior": "classical filters start from the scenario prior, the paper's start",
    "truth": "classical filters start at each trajectory's true x0 (mean only), the reading that makes the "
    "paper's PF rows possible",
    "observation": "classical filters start at the state the first observation determines where h is invertible "
    "(mean only; Lorenz 96: x0 = y0), a practitioner's start",
}
RUNTIME_WORDS = {
    "step": "Step by step, the live node's cost: each method's real per-step path (`reset(1)`, then one `step` per "
    "observation)",
    "sequence": "Sequence mode, the paper's apparent method: whole trajectories per call (`run` on one (1, T) "
    "sequence: the networks' parallel form, the filters' loop over time; the median of {repeats} calls)",
}


class ReproduceError(ValueError):
    """Bad arguments to reproduce (unknown scenario or method, an --out holding another run)."""


@dataclass
class Settings:
    scale: Scale
    scenarios: list[str]
    methods: list[str]
    gpu: bool
    cache_dir: str
    address: str | None
    num_cpus: int | None
    plugins: tuple[str, ...] = ()  # absolute paths of --plugin files: every Ray worker loads them before its job
    init: str = "prior"  # how the classical filters start in the accuracy and noise experiments (INIT_WORDS)

    def to_json(self) -> dict[str, Any]:
        out = {"scale": self.scale.settings(), "scenarios": self.scenarios, "methods": self.methods, "gpu": self.gpu}
        if self.init != "prior":  # the default is left out, so runs from before the option still resume
            out["init"] = self.init
        if self.plugins:  # a resumed run must use the same plugin code: its digest is part of the settings
            out["plugins"] = {p: _file_digest(p) for p in self.plugins}
        return out


def _file_digest(path: str) -> str:
    import hashlib

    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]
    except OSError:
        return "missing"


def describe_settings(settings: Settings, n_jobs: int) -> str:
    sc = settings.scale
    lines = [
        f"reproduce --scale {sc.name}: {n_jobs} jobs on Ray "
        f"({settings.address or 'local, ' + str(settings.num_cpus or 'default') + ' CPUs'})",
        f"  scenarios: {', '.join(settings.scenarios)}",
        f"  methods: {', '.join(settings.methods)}",
        f"  init: {settings.init} ({INIT_WORDS[settings.init]})",
    ]
    for k, v in sc.settings().items():
        if k not in ("name", "notes"):
            lines.append(f"  {k}: {'scenario default' if v is None else v}")
    lines += [f"  note: {n}" for n in sc.notes]
    lines.append(f"  runtime on GPU: {'yes' if settings.gpu else 'no (no CUDA device)'}")
    lines.append(f"  result cache: {settings.cache_dir}")
    lines += [f"  plugin: {p}" for p in settings.plugins]
    return "\n".join(lines)


def check_out_dir(out: Path, settings: Settings, resume: bool) -> None:
    state = out / STATE_FILE
    if not state.is_file():
        return
    if not resume:
        raise ReproduceError(
            f"{out} holds a previous reproduce run ({STATE_FILE}); pass --resume to continue it, "
            "or choose another --out"
        )
    try:
        before = json.loads(state.read_text()).get("settings")
    except ValueError:
        raise ReproduceError(f"{state} is damaged; remove it or choose another --out") from None
    if before != json.loads(json.dumps(settings.to_json())):  # compared as stored (tuples read back as lists)
        raise ReproduceError(
            f"--resume: {out} holds a run with other settings (scale, scenarios, methods or init); choose another --out"
        )


def previous_wall(out: Path) -> tuple[float, int]:
    """(seconds, invocations) that earlier invocations of the run in ``out`` spent, from its state file."""
    try:
        state = json.loads((out / STATE_FILE).read_text())
    except (OSError, ValueError):
        return 0.0, 0
    total = state.get("wall_total_s", state.get("wall_s"))
    if not isinstance(total, (int, float)) or not math.isfinite(total):
        return 0.0, 0  # an interrupted invocation records no time
    return float(total), int(state.get("invocations", 1))


def reproduce(settings: Settings, out: str | Path, *, resume: bool = False, progress: bool = True) -> dict[str, Any]:
    """Run every experiment of the scale and write ``out``/report.md, figures/*.png and reproduce.json."""
    out = Path(out)
    check_out_dir(out, settings, resume)
    jobs = plan_jobs(settings.scale, settings.scenarios, settings.methods, gpu=settings.gpu, init=settings.init)
    print(describe_settings(settings, len(jobs)), file=sys.stderr, flush=True)
    out.mkdir(parents=True, exist_ok=True)
    before_s, before_n = previous_wall(out) if resume else (0.0, 0)
    _write_state(out, settings, jobs, None, None, (before_s, before_n))
    t0 = time.time()
    outcome = run_jobs(
        jobs,
        settings.cache_dir,
        address=settings.address,
        num_cpus=settings.num_cpus,
        progress=progress,
        plugins=settings.plugins,
    )
    wall = time.time() - t0
    _write_state(out, settings, jobs, outcome, wall, (before_s, before_n))
    write_report(out, settings, jobs, outcome, wall, (before_s, before_n))
    return {
        "jobs": len(jobs),
        "computed": outcome.computed,
        "cached": outcome.cached,
        "failed": len(outcome.failed),
        "wall_s": wall,
        "report": str(out / "report.md"),
    }


def _write_state(
    out: Path,
    settings: Settings,
    jobs: Sequence[Job],
    outcome: Outcome | None,
    wall: float | None,
    before: tuple[float, int] = (0.0, 0),
) -> None:
    """The state file; ``before``: (seconds, invocations) of the earlier invocations a resumed run continues."""
    from neural_estimator.metrics import to_json

    rows = []
    for i, job in enumerate(jobs):
        row: dict[str, Any] = {"job": job.to_json(), "status": "pending"}
        if outcome is not None and i in outcome.results:
            r = outcome.results[i]
            row.update(status="cached" if r["cached"] else "computed", seconds=r["seconds"], result=r["result"])
        elif outcome is not None and i in outcome.failed:
            row.update(status="failed", error=outcome.failed[i])
        rows.append(row)
    payload = to_json(
        {
            "settings": settings.to_json(),
            "complete": outcome is not None and not outcome.failed,
            "wall_s": wall,
            # an unfinished invocation keeps the earlier total, so a second interruption loses nothing
            "wall_total_s": before[0] + wall if wall is not None else (before[0] if before[1] else None),
            "invocations": before[1] + (wall is not None),
            "jobs": rows,
        }
    )
    tmp = out / (STATE_FILE + ".tmp")
    tmp.write_text(json.dumps(payload, indent=1, allow_nan=False))
    tmp.replace(out / STATE_FILE)


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
    root = Path(__file__).resolve().parents[2]
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
    """report.md with every table beside the paper's and the figures (figures/*.png); ``before``:
    (seconds, invocations) of the earlier invocations of a resumed run, added to the wall time."""
    from neural_estimator.metrics import EVALUATION_WARMUP
    from neural_estimator.plots import plot_rmse_over_time
    from neural_estimator.scenarios import make_scenario

    scen, meth, sc = settings.scenarios, settings.methods, settings.scale
    acc: dict[str, dict[str, list]] = {s: {m: [] for m in meth} for s in scen}
    noise: dict[str, dict[str, dict[float, list]]] = {s: {m: {} for m in meth} for s in scen}
    rt: dict[str, dict[str, dict[str, dict[str, float]]]] = {}  # {mode: {device: {scenario: {method: it/s}}}}
    every: dict[str, dict[str, list[float]]] = {s: {m: [] for m in meth} for s in scen}  # every-step RMSE per run
    contexts: dict[str, dict[str, int]] = {s: {} for s in scen}  # bounded context of each neural cell
    starts: dict[str, dict[str, str]] = {s: {} for s in scen}  # the start each classical cell really got
    ratio: dict[str, dict[str, dict[float, list[float]]]] = {s: {m: {} for m in meth} for s in scen}
    for i, r in outcome.results.items():
        job, res = jobs[i], r["result"]
        if job.experiment == "accuracy":
            acc[job.scenario][job.method].append(res)
            every[job.scenario][job.method] += _floats([res.get("rmse_every_step")])
            starts[job.scenario][job.method] = res.get("start", job.init)
            if res.get("context"):
                contexts[job.scenario][job.method] = max(contexts[job.scenario].get(job.method, 0), int(res["context"]))
            if noise_reuses_accuracy(sc) and 1.0 in sc.noise_scales:
                noise[job.scenario][job.method].setdefault(1.0, []).append(_floats([res["rmse"]])[0])
        elif job.experiment == "noise":
            noise[job.scenario][job.method].setdefault(job.noise_scale, []).append(_floats([res["rmse"]])[0])
        elif job.experiment == "data_ratio" and job.kind == "evaluate":
            ratio[job.scenario][job.method].setdefault(job.data_ratio, []).append(_floats([res["nrmse"]])[0])
        elif job.experiment == "runtime":
            by_device = rt.setdefault(job.mode, {}).setdefault(job.device, {})
            by_device.setdefault(job.scenario, {})[job.method] = res["it_per_s"]
    summ = R.summaries(acc)
    figs = out / "figures"
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
    every_med = {s: {m: M.median_iqr(v)[0] for m, v in by_m.items() if v} for s, by_m in every.items()}
    marking = dict(init=settings.init, contexts=contexts, starts=starts)
    L += ["## Main accuracy (paper: Table accuracy_main)", ""]
    L += [
        f"Filters start: {settings.init} ({INIT_WORDS[settings.init]}). "
        + D.scored_steps(EVALUATION_WARMUP, "`--every-step`")
        + " The column *RMSE all steps* scores every step (the paper gives no such figure).",
        "",
    ]
    L += R.accuracy_table(summ, scen, meth, mark_expected=True, every_step=every_med, **marking) + [""]
    used = R.used_marks(summ, scen, meth, mark_expected=True, **marking)
    if used:
        L += ["Marks, each a departure from the paper's protocol:", ""] + R.marks_legend(used, contexts) + [""]
    L += R.expected_failure_notes(scen, meth, settings.init, starts)
    L += ["## Relative score, 100 RMSE(Mamba-2) / RMSE (paper: Table relative_score)", ""]
    if "mamba2" not in meth:
        L += ["Mamba-2 was not run: no relative score (N/A).", ""]
    L += R.relative_table(summ, scen, meth) + [""]
    L += ["## Extended metrics per scenario (paper: Appendix tables *_extended)", ""]
    for s in scen:
        L += [f"### {s}", ""] + R.extended_table(summ, s, meth, **marking) + [""]
    L += [
        "## Cross-scenario NRMSE (paper: Table nrmse_avg_all)",
        "",
        "Median and IQR over the scenario-level median NRMSEs"
        + ("" if len(scen) == 5 else f" (only {len(scen)} of the paper's 5 scenarios run)")
        + ".",
        "",
    ]
    L += R.nrmse_avg_table(summ, scen, meth) + [""]
    L += (
        ["## Stability: outlier and drift ratios (paper: Table stability_summary_app)", ""]
        + R.stability_table(summ, scen, meth)
        + [""]
    )
    L += [
        "## Beyond the paper: covariance consistency (NEES median, 95 % coverage)",
        "",
        "Methods that report a covariance; a consistent estimator has NEES ≈ dx and 95 % coverage ≈ 0.95.",
        "",
    ]
    L += R.covariance_table(summ, scen, meth) + [""]
    L += [
        "Mean NEES per state dimension and the verdict (consistent: 95 % coverage in "
        f"{list(CONSISTENCY.COVERAGE_BAND)} and mean NEES/dx in {list(CONSISTENCY.NEES_BAND)}; docs/uncertainty.md):",
        "",
    ]
    L += R.consistency_table(summ, scen, meth, {s: make_scenario(s).dx for s in scen}) + [""]
    L += ["## RMSE over time (paper: Appendix figures rmse_time_*)", ""]
    for s in scen:
        curves = {m: [_floats(r["rmse_t"]) for r in acc[s][m] if r.get("rmse_t")] for m in meth}
        curves = {m: c for m, c in curves.items() if c}
        first = max((int(r.get("warmup", 0)) for m in meth for r in acc[s][m]), default=0)
        if curves:
            p = plot_rmse_over_time(
                curves, figs / f"rmse_over_time_{s}.png", title=s, dt=make_scenario(s).dt, first_step=first
            )
            L += [f"![RMSE over time, {s}](figures/{p.name})", ""]
    L += [
        "## Robustness to observation noise (paper: Appendix figures noise_*)",
        "",
        f"RMSE against the observation-noise scale {list(sc.noise_scales)} (median over sets, IQR shaded); neural "
        "models are the ones trained at the nominal noise. The paper does not publish its noise levels.",
        "",
    ]
    for s in scen:
        curves = {m: v for m, v in noise[s].items() if v}
        if curves:
            p = R.plot_noise(curves, figs / f"noise_{s}.png", title=s)
            L += [f"![noise robustness, {s}](figures/{p.name})", ""]
    L += [
        "## Runtime: iterations per second at batch 1 (paper: Table runtime_full_app)",
        "",
        f"Two ways, {sc.runtime_steps} timed steps after {sc.runtime_warmup} untimed, one thread, the job alone on the "
        "Ray node; the paper's figures (after the dot) are beside both, since the paper does not say how it timed. "
        "Our hardware is not the paper's: compare orderings, not values.",
        "",
    ]
    from neural_estimator.reproduce.jobs import RUNTIME_MODES, SEQUENCE_REPEATS

    for mode in RUNTIME_MODES:
        if mode not in rt:
            continue
        L += [f"### {mode.capitalize()} mode", "", RUNTIME_WORDS[mode].format(repeats=SEQUENCE_REPEATS) + ".", ""]
        for device in rt[mode]:
            L += [f"#### {device.upper()}", ""] + R.runtime_table(rt[mode], scen, meth, device) + [""]
            L += [R.runtime_ordering(rt[mode][device], scen, meth, "gpu" if device != "cpu" else "cpu"), ""]
    from neural_estimator.estimators import NEURAL_METHODS

    neural = [m for m in meth if m in NEURAL_METHODS]
    L += ["## Data efficiency (paper: Table data_ratio_main, figures data_ratio_*)", ""]
    if neural:
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
        L += R.data_ratio_table(ratio, scen, neural, sc.data_ratios) + [""]
        for s in scen:
            by_m = {m: ratio[s][m] for m in neural if ratio[s][m]}
            if by_m:
                p = R.plot_data_ratio(by_m, figs / f"data_ratio_{s}.png", title=s)
                L += [f"![data efficiency, {s}](figures/{p.name})", ""]
    else:
        L += (
            ["No neural method was run: no data-efficiency experiment. The paper's values:", ""]
            + R.data_ratio_paper_table()
            + [""]
        )
    path = out / "report.md"
    path.write_text("\n".join(L))
    return path


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
    return "the shipped checkpoints (one instance each) for accuracy, noise and runtime"


def _floats(values) -> list[float]:
    """JSON numbers back to floats: null (a value that was not finite) becomes NaN (left out of plots)."""
    return [math.nan if v is None else float(v) for v in values]
