"""The reproduce report: our numbers beside the paper's (:mod:`neural_estimator.paper`), PNG figures.

Table cells read ``ours · paper`` (the paper's value after the dot; ``—`` where the paper has no
value, e.g. a scenario or method it lacks). Ours are medians (± IQR where the paper gives one)
over the evaluation sets, as in the paper's tables.
"""

from __future__ import annotations

import math
import platform
import subprocess
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from neural_estimator import departures as D
from neural_estimator import metrics as M
from neural_estimator.expected_failures import MARK, expected_to_fail, notes
from neural_estimator.paper import paper_value
from neural_estimator.reproduce.engine import Outcome
from neural_estimator.reproduce.jobs import Job
from neural_estimator.reproduce.plan import noise_reuses_accuracy
from neural_estimator.reproduce.settings import INIT_WORDS, Settings, describe_settings

PAPER_NAMES = {
    "ekf": "EKF",
    "ukf": "UKF",
    "enkf": "EnKF",
    "pf": "PF",
    "gru": "GRU",
    "lstm": "LSTM",
    "gpt2": "GPT-2",
    "filterformer": "Filterformer",
    "mamba": "Mamba",
    "mamba2": "Mamba-2",
}
EXTENDED = M.TABLE_COLUMNS[:8]  # the paper's eight extended-table columns (RMSE ... Drift)
SEP = " · "  # between ours and the paper's


def num(x: Any, decimals: int = 3) -> str:
    """A cell number: inf as ∞, missing as N/A, large values with one decimal."""
    if x is None:
        return "N/A"
    x = float(x)
    if math.isnan(x):
        return "N/A"
    if math.isinf(x):
        return "∞"
    if abs(x) >= 1000:
        return f"{x:,.1f}"
    return f"{x:.{decimals}f}"


def stat_cell(st: M.Stat | None, decimals: int, iqr: bool) -> str:
    if st is None or not st.applies:
        return "N/A"
    if iqr and math.isfinite(st.median) and math.isfinite(st.iqr):
        return f"{num(st.median, decimals)}±{num(st.iqr, decimals)}"
    return num(st.median, decimals)


def paper_cell(v: Any, decimals: int) -> str:
    if isinstance(v, dict):
        return f"{num(v['median'], decimals)}±{num(v['iqr'], decimals)}"
    return num(v, decimals)


def side(ours: str, paper: Any, decimals: int, in_paper: bool) -> str:
    return ours + SEP + (paper_cell(paper, decimals) if in_paper else "—")


def _row(cells: Sequence[str]) -> str:
    return "| " + " | ".join(cells) + " |"


def _header(cols: Sequence[str]) -> list[str]:
    return [_row(cols), _row(["---"] * len(cols))]


def summaries(runs: Mapping[str, Mapping[str, list[dict[str, Any]]]]) -> dict[str, dict[str, dict[str, M.Stat]]]:
    """{scenario: {method: {metric: Stat}}} over the runs (report dicts) of each pair."""
    return {s: {m: M.summarize(rs) for m, rs in by_m.items() if rs} for s, by_m in runs.items()}


def _in_paper(s: str, m: str) -> bool:
    return paper_value("accuracy_main", s, m) is not None


def cell_start(s: str, m: str, init: str = "prior", starts=None) -> str:
    """The start the filter ``m`` really got on ``s``: ``starts[s][m]`` when recorded (``--init observation``
    is the prior where h determines nothing), else the run's ``init``."""
    return (starts or {}).get(s, {}).get(m, init)


def rmse_marks(summ, s: str, m: str, contexts=None, init: str = "prior", starts=None) -> list[str]:
    """The marks of the RMSE cell of ``m`` on ``s``: [c] (bounded context, ``contexts[s][m]`` > 0), [t] / [y]
    (a filter started from the truth / the first observation) and [o] (the outlier rule decides it:
    :func:`neural_estimator.departures.rests_on_outliers`)."""
    st = summ.get(s, {}).get(m)
    marks = [D.BOUNDED] if (contexts or {}).get(s, {}).get(m) else []
    start = D.start_mark(m, cell_start(s, m, init, starts))
    if start:
        marks.append(start)
    if st is not None and D.rests_on_outliers(st["rmse"].median, st["full_rmse"].median):
        marks.append(D.OUTLIERS)
    return marks


def accuracy_table(
    summ,
    scenarios,
    methods,
    mark_expected: bool = False,
    *,
    init: str = "prior",
    contexts=None,
    every_step=None,
    starts=None,
) -> list[str]:
    """The main table, every departure from the paper's protocol marked where the number is printed.

    Columns per scenario: RMSE (the scored steps), RMSE over every step (``every_step[s][m]``: the
    median over runs; N/A where not measured), NRMSE. Marks (:mod:`neural_estimator.departures`):
    [c] on a bounded-context cell (``contexts[s][m]`` > 0), [o] with the Full RMSE beside an RMSE
    the outlier rule decides, [t] / [y] on a filter started from the truth / the first observation
    (``starts[s][m]``, else ``init``); with ``mark_expected`` the RMSE of an expected failure under that start
    (:mod:`neural_estimator.expected_failures`) ends with its mark, just before the paper's value.
    """
    cols = ["Method"] + [f"{s} {k}" for s in scenarios for k in ("RMSE", "RMSE all steps", "NRMSE")]
    lines = _header(cols)
    for m in methods:
        cells = [PAPER_NAMES.get(m, m)]
        for s in scenarios:
            st = summ.get(s, {}).get(m)
            ours = stat_cell(st and st["rmse"], 3, False)
            marks = rmse_marks(summ, s, m, contexts, init, starts)
            if marks:
                ours += " " + " ".join(marks)
            if D.OUTLIERS in marks:
                ours += f" (full {num(st['full_rmse'].median)})"
            if mark_expected and expected_to_fail(s, m, cell_start(s, m, init, starts)):
                ours += f" {MARK}"
            cells.append(side(ours, paper_value("accuracy_main", s, m, "rmse"), 3, _in_paper(s, m)))
            every = (every_step or {}).get(s, {}).get(m)
            cells.append(side(num(every), None, 3, False))
            cells.append(
                side(
                    stat_cell(st and st["nrmse"], 3, False),
                    paper_value("accuracy_main", s, m, "nrmse"),
                    3,
                    _in_paper(s, m),
                )
            )
        lines.append(_row(cells))
    return lines


def used_marks(
    summ, scenarios, methods, *, init: str = "prior", contexts=None, mark_expected: bool = False, starts=None
) -> set[str]:
    """Every mark :func:`accuracy_table` prints for these arguments (for the legend)."""
    used = {mk for s in scenarios for m in methods for mk in rmse_marks(summ, s, m, contexts, init, starts)}
    if mark_expected and any(
        expected_to_fail(s, m, cell_start(s, m, init, starts)) for s in scenarios for m in methods
    ):
        used.add(MARK)
    return used


def marks_legend(used: set[str], contexts=None) -> list[str]:
    """The legend of the marks in ``used``, one bullet each."""
    ctx = [c for by_m in (contexts or {}).values() for c in by_m.values()]
    return [f"- {line}" for line in D.legend(used, ctx)]


def expected_failure_notes(scenarios, methods, init: str = "prior", starts=None) -> list[str]:
    """One bullet per expected failure (under the start each cell got) or caveat in the table, with its reason."""
    lines = [
        f"- {s}: {note}"
        for s in scenarios
        for note in notes(s, methods, {m: cell_start(s, m, init, starts) for m in methods})
    ]
    return lines + [""] if lines else []


def relative_scores(summ, scenarios, methods) -> dict[str, dict[str, float]]:
    """score(m, s) = 100 RMSE(Mamba-2, s) / RMSE(m, s) (the paper's eq. relative_score); NaN without Mamba-2."""
    out: dict[str, dict[str, float]] = {}
    for s in scenarios:
        ref = summ.get(s, {}).get("mamba2")
        for m in methods:
            st = summ.get(s, {}).get(m)
            if ref is None or st is None:
                v = math.nan
            else:
                r, x = ref["rmse"].median, st["rmse"].median
                v = 0.0 if math.isinf(x) else (100 * r / x if x > 0 else math.nan)
            out.setdefault(s, {})[m] = v
    return out


def relative_table(summ, scenarios, methods) -> list[str]:
    scores = relative_scores(summ, scenarios, methods)
    lines = _header(["Method"] + list(scenarios))
    for m in methods:
        lines.append(
            _row(
                [PAPER_NAMES.get(m, m)]
                + [
                    side(num(scores[s][m], 1), paper_value("relative_score", s, m), 1, _in_paper(s, m))
                    for s in scenarios
                ]
            )
        )
    return lines


def extended_table(summ, s, methods, *, init: str = "prior", contexts=None, starts=None) -> list[str]:
    """One scenario's extended table; the RMSE cell carries the main table's [c] / [t] / [y] / [o] marks
    (the Full RMSE is the next column)."""
    lines = _header(["Method"] + [h for _, h, _, _ in EXTENDED])
    for m in methods:
        st = summ.get(s, {}).get(m)
        marks = " ".join(rmse_marks(summ, s, m, contexts, init, starts))
        cells = []
        for k, _, d, iqr in EXTENDED:
            ours = stat_cell(st and st[k], d, iqr)
            if k == "rmse" and marks:
                ours += f" {marks}"
            cells.append(side(ours, paper_value("extended", s, m, k), d, _in_paper(s, m)))
        lines.append(_row([PAPER_NAMES.get(m, m)] + cells))
    return lines


def nrmse_avg_table(summ, scenarios, methods) -> list[str]:
    """Median and IQR over the scenario-level median NRMSEs (the paper's tab:nrmse_avg_all)."""
    lines = _header(["Method", "Median NRMSE", "(IQR)", "scenarios"])
    for m in methods:
        vals = [summ[s][m]["nrmse"].median for s in scenarios if m in summ.get(s, {})]
        med, iqr = M.median_iqr(vals) if vals else (math.nan, math.nan)
        paper = paper_value("nrmse_avg_all", m) or {}
        known = m in PAPER_NAMES
        lines.append(
            _row(
                [
                    PAPER_NAMES.get(m, m),
                    side(num(med), paper.get("median"), 3, known),
                    side(num(iqr), paper.get("iqr"), 3, known),
                    str(len(vals)),
                ]
            )
        )
    return lines


def stability_table(summ, scenarios, methods) -> list[str]:
    cols = ["Method"] + [f"Out. {s}" for s in scenarios] + [f"Drift {s}" for s in scenarios]
    lines = _header(cols)
    for m in methods:
        cells = [PAPER_NAMES.get(m, m)]
        for k in ("outlier_ratio", "drift_ratio"):
            for s in scenarios:
                st = summ.get(s, {}).get(m)
                cells.append(
                    side(stat_cell(st and st[k], 3, False), paper_value("stability", s, m, k), 3, _in_paper(s, m))
                )
        lines.append(_row(cells))
    return lines


def covariance_table(summ, scenarios, methods) -> list[str]:
    """Beyond the paper: NEES (median) and 95 % coverage where a method reports a covariance."""
    cols = ["Method"] + [f"{s} {k}" for s in scenarios for k in ("NEES med.", "95%")]
    lines = _header(cols)
    for m in methods:
        cells, any_applies = [PAPER_NAMES.get(m, m)], False
        for s in scenarios:
            st = summ.get(s, {}).get(m)
            for k, d in (("nees_median", 2), ("coverage95", 3)):
                applies = st is not None and st[k].applies
                any_applies |= applies
                cells.append(stat_cell(st[k], d, True) if applies else M.NOT_APPLICABLE)
        if any_applies:
            lines.append(_row(cells))
    return lines


def _family_averages(
    rt_device: Mapping[str, Mapping[str, float]], scenarios, methods
) -> tuple[list[float], list[float]]:
    """(filters, networks): each method's mean it/s over the scenarios it ran on."""
    from neural_estimator.estimator import CLASSICAL_METHODS

    avg: dict[str, float] = {}
    for m in methods:
        vals = [rt_device.get(s, {}).get(m) for s in scenarios]
        vals = [v for v in vals if v is not None and math.isfinite(v)]
        if vals:
            avg[m] = sum(vals) / len(vals)
    filters = [v for m, v in avg.items() if m in CLASSICAL_METHODS]
    networks = [v for m, v in avg.items() if m not in CLASSICAL_METHODS]
    return filters, networks


def runtime_ordering(
    rt_device: Mapping[str, Mapping[str, float]], scenarios, methods, paper_device: str = "cpu"
) -> str:
    """One sentence: which family is faster in these timings (median over methods of each method's mean
    it/s over the scenarios), and whether that is the paper's ordering on ``paper_device``."""
    filters, networks = _family_averages(rt_device, scenarios, methods)
    if not filters or not networks:
        return "Only one family was timed: no ordering between filters and networks."
    f, n = float(np.median(filters)), float(np.median(networks))
    paper = paper_value("runtime_full", paper_device) or {}
    pf, pn = _family_averages(paper, list(paper), list(PAPER_NAMES))
    ours = "the networks ahead of the filters" if n > f else "the filters ahead of the networks"
    verdict = ""
    if pf and pn:
        paper_f, paper_n = float(np.median(pf)), float(np.median(pn))
        same = (paper_n > paper_f) == (n > f)
        verdict = (
            f"; {'the' if same else 'against the'} paper's ordering "
            f"(paper {paper_device.upper()}: filters {paper_f:,.0f}, networks {paper_n:,.0f})"
        )
    return (
        f"This mode supports {ours}: filters {f:,.0f} it/s, networks {n:,.0f} it/s "
        f"(median over methods of each one's mean over scenarios){verdict}."
    )


def runtime_table(rt: Mapping[str, Mapping[str, Mapping[str, float]]], scenarios, methods, device: str) -> list[str]:
    """Iterations per second at batch 1: {device: {scenario: {method: it/s}}}, beside tab:runtime_full_app."""
    lines = _header(["Method"] + list(scenarios) + ["Avg."])
    paper_device = "gpu" if device != "cpu" else "cpu"
    for m in methods:
        vals = [rt.get(device, {}).get(s, {}).get(m) for s in scenarios]
        if all(v is None for v in vals):
            continue
        known = [v for v in vals if v is not None]
        avg = sum(known) / len(known) if len(known) == len(vals) else None
        cells = [
            side(num(v, 1), paper_value("runtime_full", paper_device, s, m), 1, m in PAPER_NAMES)
            for v, s in zip(vals, scenarios)
        ]
        # the paper's average is over its five scenarios: shown only when we ran those five
        all_five = sorted(scenarios) == sorted(paper_value("runtime_full", "cpu") or {})
        cells.append(
            side(num(avg, 1), paper_value("runtime_summary", m, paper_device), 1, m in PAPER_NAMES and all_five)
        )
        lines.append(_row([PAPER_NAMES.get(m, m)] + cells))
    return lines


def data_ratio_table(
    nrmse: Mapping[str, Mapping[str, Mapping[float, list[float]]]], scenarios, methods, ratios: Sequence[float]
) -> list[str]:
    """Median across scenarios of each scenario's median NRMSE (over sets x instances), per ratio,
    beside tab:data_ratio_main: ``nrmse[scenario][method][ratio] = [NRMSE of each run]``."""
    lines = _header(["Method"] + [f"{r:g}:1" for r in ratios])
    for m in methods:
        cells = [PAPER_NAMES.get(m, m)]
        for r in ratios:
            per_s = [M.median_iqr(nrmse[s][m][r])[0] for s in scenarios if nrmse.get(s, {}).get(m, {}).get(r)]
            ours = M.median_iqr(per_s)[0] if per_s else math.nan
            paper = paper_value("data_ratio_main", f"{r:g}", m)
            cells.append(side(num(ours), paper, 3, paper is not None))
        lines.append(_row(cells))
    return lines


def plot_data_ratio(by_method: Mapping[str, Mapping[float, list[float]]], path: Path, title: str) -> Path:
    """Grouped bars: median NRMSE per architecture at each data-to-parameter ratio (IQR as error bars)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods = [m for m, v in by_method.items() if v]
    ratios = sorted({r for m in methods for r in by_method[m]}, reverse=True)
    fig, ax = plt.subplots(figsize=(8, 4.5), dpi=120)
    width = 0.8 / max(1, len(ratios))
    for k, r in enumerate(ratios):
        med, lo, hi = [], [], []
        for m in methods:
            v = np.asarray(by_method[m].get(r, []), float)
            v = v[np.isfinite(v)]
            q = np.percentile(v, [25, 50, 75]) if v.size else [np.nan] * 3
            med.append(q[1]), lo.append(q[1] - q[0]), hi.append(q[2] - q[1])
        x = np.arange(len(methods)) + (k - (len(ratios) - 1) / 2) * width
        ax.bar(x, med, width, yerr=[lo, hi], capsize=2, label=f"{r:g}:1")
    ax.set_xticks(np.arange(len(methods)), [PAPER_NAMES.get(m, m) for m in methods])
    ax.set_ylabel("NRMSE (median over sets x instances)")
    ax.set_title(title)
    ax.grid(True, axis="y", alpha=0.3)
    ax.legend(title="data : parameters", fontsize=8)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


def data_ratio_paper_table() -> list[str]:
    lines = _header(["Method", "20:1", "10:1", "5:1", "1:1"])
    for m in ("gru", "lstm", "gpt2", "filterformer", "mamba", "mamba2"):
        lines.append(
            _row([PAPER_NAMES[m]] + [num(paper_value("data_ratio_main", r, m)) for r in ("20", "10", "5", "1")])
        )
    return lines


def plot_noise(curves: Mapping[str, Mapping[float, list[float]]], path: Path, title: str) -> Path:
    """RMSE against the observation-noise scale, median over sets with the IQR shaded, per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4.5), dpi=120)
    for m, by_scale in curves.items():
        xs = sorted(by_scale)
        stats = [M.median_iqr(by_scale[x]) for x in xs]
        q = [
            (np.nanpercentile(np.asarray(by_scale[x], float), 25), np.nanpercentile(np.asarray(by_scale[x], float), 75))
            if np.isfinite(by_scale[x]).any()
            else (np.nan, np.nan)
            for x in xs
        ]
        (line,) = ax.plot(xs, [st[0] for st in stats], marker="o", label=PAPER_NAMES.get(m, m))
        ax.fill_between(xs, [a for a, _ in q], [b for _, b in q], color=line.get_color(), alpha=0.2)
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    ax.set_xlabel("observation-noise scale (x nominal; models trained at 1)")
    ax.set_ylabel("RMSE")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, ncol=2)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


# ---- the report of a reproduce run -------------------------------------------------------------------
RUNTIME_WORDS = {
    "step": "Step by step, the live node's cost: each method's real per-step path (`reset(1)`, then one `step` per "
    "observation)",
    "sequence": "Sequence mode, the paper's apparent method: whole trajectories per call (`run` on one (1, T) "
    "sequence: the networks' parallel form, the filters' loop over time; the median of {repeats} calls)",
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
    summ = summaries(acc)
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
    L += accuracy_table(summ, scen, meth, mark_expected=True, every_step=every_med, **marking) + [""]
    used = used_marks(summ, scen, meth, mark_expected=True, **marking)
    if used:
        L += ["Marks, each a departure from the paper's protocol:", ""] + marks_legend(used, contexts) + [""]
    L += expected_failure_notes(scen, meth, settings.init, starts)
    L += ["## Relative score, 100 RMSE(Mamba-2) / RMSE (paper: Table relative_score)", ""]
    if "mamba2" not in meth:
        L += ["Mamba-2 was not run: no relative score (N/A).", ""]
    L += relative_table(summ, scen, meth) + [""]
    L += ["## Extended metrics per scenario (paper: Appendix tables *_extended)", ""]
    for s in scen:
        L += [f"### {s}", ""] + extended_table(summ, s, meth, **marking) + [""]
    L += [
        "## Cross-scenario NRMSE (paper: Table nrmse_avg_all)",
        "",
        "Median and IQR over the scenario-level median NRMSEs"
        + ("" if len(scen) == 5 else f" (only {len(scen)} of the paper's 5 scenarios run)")
        + ".",
        "",
    ]
    L += nrmse_avg_table(summ, scen, meth) + [""]
    L += (
        ["## Stability: outlier and drift ratios (paper: Table stability_summary_app)", ""]
        + stability_table(summ, scen, meth)
        + [""]
    )
    L += [
        "## Beyond the paper: covariance consistency (NEES median, 95 % coverage)",
        "",
        "Methods that report a covariance; a consistent estimator has NEES ≈ dx and 95 % coverage ≈ 0.95.",
        "",
    ]
    L += covariance_table(summ, scen, meth) + [""]
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
            p = plot_noise(curves, figs / f"noise_{s}.png", title=s)
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
            L += [f"#### {device.upper()}", ""] + runtime_table(rt[mode], scen, meth, device) + [""]
            L += [runtime_ordering(rt[mode][device], scen, meth, "gpu" if device != "cpu" else "cpu"), ""]
    from neural_estimator.registry import NEURAL_METHODS

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
        L += data_ratio_table(ratio, scen, neural, sc.data_ratios) + [""]
        for s in scen:
            by_m = {m: ratio[s][m] for m in neural if ratio[s][m]}
            if by_m:
                p = plot_data_ratio(by_m, figs / f"data_ratio_{s}.png", title=s)
                L += [f"![data efficiency, {s}](figures/{p.name})", ""]
    else:
        L += (
            ["No neural method was run: no data-efficiency experiment. The paper's values:", ""]
            + data_ratio_paper_table()
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
