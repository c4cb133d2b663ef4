"""The headline answer: per system, the best filter, the best network, their paired RMSE ratio with
its 95 % interval on the paper's aggregate and on each component a method estimates, and the
verdict; measured on one seed family (:mod:`~neural_estimator.evaluation.families`).

Per scenario (:func:`headline_row`):

- every method asked for and the ``openloop`` baseline run on the same evaluation sets;
- the figure ranked on is the RMSE (the paper's, after the outlier rule), or the Full RMSE (every
  trajectory) where the two give a different best filter or best network, or put the other one
  ahead;
- best filter: the classical filter with the smallest median of that figure; best network: the
  same among the neural methods (median over evaluation sets and trained instances);
- ratio: best network over best filter, paired over trajectories and instances
  (:func:`~neural_estimator.metrics.paired_ratio`), on the aggregate and on each component that
  some method estimates better than the open loop by 10 %;
- the estimated components together: the geometric mean of their ratios with its paired interval
  (:func:`~neural_estimator.metrics.paired_geometric_ratio`), each component weighed alike whatever
  its units (all components when every one is estimated);
- verdict: "network better" / "tied" / "filter better" by that interval: the decision rests on
  what the methods estimate, not on a component no method estimates (the ballistic drag carries over
  99 % of the aggregate's squared error) nor on the units that dominate a sum. The aggregate's own
  verdict is kept beside it (``verdict_aggregate``) and printed where the two differ; where no
  component is estimated the verdict is the aggregate's.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Callable

from neural_estimator import metrics as M
from neural_estimator.evaluation import comparison as C
from neural_estimator.evaluation.families import SEALED, family_seed
from neural_estimator.methods import table
from neural_estimator.paper import PAPER_SCENARIOS

# The question the headline answers: the best filter against the best network (a hybrid, which is
# neither, is evaluated only when named in ``methods`` and enters neither side)
HEADLINE_FAMILIES = ("classical", "neural")
_VERDICTS = {"better": "network better", "worse": "filter better", "tied": "tied", "unknown": "unknown"}


def measure_headline(
    family: str,
    scenarios=PAPER_SCENARIOS,
    methods=None,
    trajectories: int = 200,
    sets: int = 3,
    horizon: int | None = None,
    out: Path | None = None,
    progress: bool = True,
    cache_dir: Any = None,
    note: Callable[[str], None] | None = None,
    results_out: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Evaluate ``methods`` (and ``openloop``) on every scenario on ``family``'s seed and return the
    headline {family, seed, command sizes, rows: [per scenario]} (``methods``: default every filter
    and network of the table, :data:`HEADLINE_FAMILIES`); with ``out``, each scenario's
    results (``out/<scenario>/``), headline.json and headline.md are written there; with
    ``results_out``, each scenario's results are put there too (for other judgements of the same
    measurement, such as the paper's findings)."""
    from neural_estimator.evaluation.output import write_evaluation
    from neural_estimator.evaluation.protocol import evaluate
    from neural_estimator.scenarios import make_scenario

    seed = family_seed(family)
    methods = table.names(family=HEADLINE_FAMILIES) if methods is None else methods
    rows = []
    for name in scenarios:
        scenario = make_scenario(name)
        asked = [m for m in methods if m != "openloop"] + ["openloop"]
        results = evaluate(
            scenario,
            asked,
            trajectories=trajectories,
            sets=sets,
            horizon=horizon,
            seed=seed,
            sealed=family == SEALED,
            progress=progress,
            cache_dir=cache_dir,
        )
        info = dict(trajectories=trajectories, sets=sets, seed=seed, family=family, warmup=M.EVALUATION_WARMUP)
        info["horizon"] = horizon or scenario.horizon
        if out is not None:
            done = {m: len(r.reports) for m, r in results.items()}
            write_evaluation(Path(out) / name, scenario, results, info, done, plot=False)
        if results_out is not None:
            results_out[name] = results
        rows.append(headline_row(scenario, results))
        if note:
            note(f"{name}: {rows[-1]['verdict']}")
    headline = dict(family=family, seed=seed, trajectories=trajectories, sets=sets, horizon=horizon, rows=rows)
    if out is not None:
        Path(out).mkdir(parents=True, exist_ok=True)
        (Path(out) / "headline.json").write_text(json.dumps(M.to_json(headline), indent=1, allow_nan=False))
        (Path(out) / "headline.md").write_text(render_headline(headline))
    return headline


def headline_row(scenario, results) -> dict[str, Any]:
    """One scenario's line of the headline (see the module docstring)."""
    filters = {m: r for m, r in C.ranked(results).items() if table.has(m, family="classical")}
    networks = {m: r for m, r in C.ranked(results).items() if table.has(m, family="neural")}
    # the outlier rule decides the ranking when it changes the best filter, the best network, or
    # which of the two is ahead (a filter whose failures were dropped can look better than it is)
    ranking = {k: _ranking(filters, networks, k) for k in ("rmse", "full_rmse")}
    full = ranking["rmse"] != ranking["full_rmse"]
    key = "full_rmse" if full else "rmse"
    best_filter, best_network, _ = ranking[key]
    row: dict[str, Any] = dict(
        scenario=scenario.name, figure=key, best_filter=best_filter, best_network=best_network, components=[]
    )
    if best_filter is None or best_network is None:
        row.update(ratio=math.nan, ci95=[math.nan, math.nan], verdict="unknown", verdict_aggregate="unknown")
        return row
    net, ref = results[best_network].runs_by_set(), results[best_filter].runs_by_set()
    ratio, ci = M.paired_ratio(net, ref, full=full)
    row.update(
        filter_value=results[best_filter].summary[key].median,
        network_value=results[best_network].summary[key].median,
        network_instances=results[best_network].n_instances,
        ratio=ratio,
        ci95=list(ci),
        verdict_aggregate=_VERDICTS[M.verdict(ci)],
    )
    flags = C.not_estimated(results) or [False] * scenario.dx
    estimated = [d for d in range(scenario.dx) if not flags[d]]
    for d in estimated:
        r, c = M.paired_ratio(net, ref, components=[d], full=full)
        row["components"].append(
            dict(name=scenario.state_names[d], ratio=r, ci95=list(c), verdict=_VERDICTS[M.verdict(c)])
        )
    row["not_estimated"] = [n for n, f in zip(scenario.state_names, flags) if f]
    if estimated:
        g, c = M.paired_geometric_ratio(net, ref, estimated, full=full)
        row["estimated"] = dict(ratio=g, ci95=list(c), verdict=_VERDICTS[M.verdict(c)])
    row["verdict"] = row["estimated"]["verdict"] if estimated else row["verdict_aggregate"]
    return row


def render_headline(headline: dict[str, Any]) -> str:
    """The markdown table of :func:`measure_headline`'s result (also from its headline.json)."""
    lines = [
        "| system | best filter | best network | network / filter [95% CI] | on the estimated components | verdict |",
        "|---|---|---|---|---|---|",
    ]
    for row in headline["rows"]:
        fig = " (Full RMSE)" if row.get("figure") == "full_rmse" else ""
        comps = _components(row.get("components", []))
        if row.get("estimated") and len(row.get("components", [])) > 1:
            comps += f"; together {_ratio(row['estimated']['ratio'], row['estimated']['ci95'])}"
        if row.get("not_estimated"):
            comps += ("; " if comps else "") + "not estimated: " + ", ".join(row["not_estimated"])
        verdict = row["verdict"]
        if row.get("verdict_aggregate", verdict) != verdict:
            verdict += f" (aggregate: {row['verdict_aggregate']})"
        inst = row.get("network_instances", 1)
        best_filter = _named(row["best_filter"], row.get("filter_value"))
        network = _named(row["best_network"], row.get("network_value"))
        if row["best_network"]:
            network += f" ({inst} instance{'s' if inst != 1 else ''})"
        lines.append(
            f"| {row['scenario']} | {best_filter} | {network} | "
            f"{_ratio(row['ratio'], row['ci95'])}{fig} | {comps or '—'} | {verdict} |"
        )
    lines.append("")
    lines.append(
        f"Measured on the {headline['family']} evaluation family (seed {headline['seed']}): "
        f"{headline['sets']} sets x {headline['trajectories']} trajectories per system; ratio: median RMSE of the "
        "best network over that of the best filter, 95% paired bootstrap interval over trajectories and trained "
        "instances; beside each name its median RMSE (the Full RMSE where marked); together: the geometric mean "
        "of the estimated components' ratios, on which the verdict rests."
    )
    return "\n".join(lines) + "\n"


def _named(method: str | None, value: float | None) -> str:
    """A method's display name and its median figure ("UKF 0.52"), "—" where there is none."""
    if not method:
        return "—"
    shown = f" {value:.3g}" if value is not None and math.isfinite(value) else ""
    return table.label(method) + shown


def _components(items: list[dict[str, Any]], listed: int = 6) -> str:
    """Each estimated component's ratio; beyond ``listed`` of them (Lorenz 96 has 10), their range and
    the count of each verdict."""
    if len(items) <= listed:
        return "; ".join(f"{c['name']} {_ratio(c['ratio'], c['ci95'])}" for c in items)
    ratios = [c["ratio"] for c in items if c["ratio"] is not None and math.isfinite(c["ratio"])]
    counts = {v: sum(c["verdict"] == v for c in items) for v in _VERDICTS.values()}
    span = f"ratios {min(ratios):.2f}-{max(ratios):.2f}" if ratios else "no finite ratio"
    return f"{len(items)} components, {span} (" + ", ".join(f"{n} {v}" for v, n in counts.items() if n) + ")"


def _ranking(filters, networks, key: str) -> tuple[str | None, str | None, bool | None]:
    """(best filter, best network, whether the network's median ``key`` is below the filter's;
    None without both)."""
    f, n = _best(filters, key), _best(networks, key)
    ahead = None if f is None or n is None else networks[n].summary[key].median < filters[f].summary[key].median
    return f, n, ahead


def _best(results, key: str) -> str | None:
    scored = {m: r.summary[key].median for m, r in results.items()}
    scored = {m: v for m, v in scored.items() if v is not None and math.isfinite(v)}
    return min(scored, key=scored.get) if scored else None


def _ratio(ratio, ci) -> str:
    if ratio == math.inf:
        return "inf (diverged)"
    if ratio is None or not math.isfinite(ratio):
        return "N/A"
    lo, hi = (math.nan if v is None else v for v in ci)
    return f"{ratio:.2f} [{lo:.2f}, {hi:.2f}]"
