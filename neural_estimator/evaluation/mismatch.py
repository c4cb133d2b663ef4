"""How wrong may the model be before a network trained on the data wins? The mismatch crossover.

One constant ``NAME`` of the scenario (or ``Q`` / ``R``, the scales of the noise covariances the
model is told) is swept over multipliers v of its true value: at each v the model-based methods
(``table.has(m, needs_model=True)``: the filters, the hybrid) are built with ``NAME = v x true``
(:func:`~neural_estimator.scenarios.model.model_scenario`), on the same evaluation sets, which are
always simulated with the true constants. The data-trained networks do not see the model, so they
run once and their row is the same at every v. ``v = 1`` is the exact model; the *relative error*
of the model is e = v - 1 (signed: -0.2 is a constant 20 % too small).

At each v the reference is the *best filter* there (the classical filter of lowest median RMSE at
that v), and every method gets its paired RMSE ratio to it with the 95 % percentile-bootstrap
interval of :func:`~neural_estimator.metrics.paired.paired_ratio` (same trajectories, same draws).

**Crossover.** For a challenger c (the network; separately the hybrid) and one side of the grid
(e > 0, e < 0), walk outward from the exact model: with ratio rho(e) = RMSE_c / RMSE_best filter,
the crossover is the smallest |e| where rho(e) < 1, linearly interpolated between the last grid
point with rho >= 1 and the first with rho < 1:

    |e*| = |e_a| + (rho_a - 1) / (rho_a - rho_b) (|e_b| - |e_a|)

Its interval is the same construction on the interval's bounds: the upper bound of rho crossing 1
gives the far end (beyond it c is better with 95 % confidence), the lower bound the near end
(before it c is worse with 95 % confidence). ``0`` means c already beats the exact-model filters;
``None`` means it does not within the grid (the crossover is beyond the largest error tried).
Between grid points the interpolation assumes rho is monotone in |e|: the grid is the resolution.
"""

from __future__ import annotations

import json
import math
import numbers
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from neural_estimator import metrics as M
from neural_estimator.data.protocol import evaluation_sets
from neural_estimator.evaluation.protocol import MethodResult, evaluate
from neural_estimator.methods import table
from neural_estimator.metrics.paired import paired_ratio, run_rmse
from neural_estimator.scenarios import Scenario, ScenarioError
from neural_estimator.scenarios.model import NOISE_SCALES, model_scenario

MISMATCH_SCHEMA = "neural_estimator.mismatch/1"
DEFAULT_VALUES = (0.5, 0.8, 0.9, 1.0, 1.1, 1.25, 1.5, 2.0)
NOISE_VALUES = (0.1, 0.3, 1.0, 3.0, 10.0)  # Q and R: scales of a covariance, swept over decades

# One physically meaningful constant per scenario, plus the noise levels (the reproduce experiment):
# ballistic drag, bearings target process noise, Lorenz 96 forcing, N-link total length (its mass cancels from the
# equations of uniform links), quadrotor mass.
EXPERIMENT: dict[str, tuple[str, ...]] = {
    "ballistic": ("k", "Q", "R"),
    "bearings": ("accel_noise_std", "Q", "R"),
    "lorenz96": ("forcing", "Q", "R"),
    "nlink": ("total_length", "Q", "R"),
    "quadrotor": ("mass", "Q", "R"),
}


def true_value(scenario: Scenario, parameter: str) -> float:
    """The constant's true value (1.0 for the noise scales ``Q``/``R``); a ScenarioError for a name
    the scenario lacks or a constant that is not one real number (an integer count, a vector)."""
    if parameter in NOISE_SCALES:
        return 1.0
    if not hasattr(scenario.config, parameter):
        model_scenario(scenario, {parameter: "1"})  # the scenario's own message, with the valid names
    value = getattr(scenario.config, parameter)
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or isinstance(value, numbers.Integral):
        raise ScenarioError(
            f"scenario {scenario.name!r}: {parameter} = {value!r} is not a real-valued constant; "
            "mismatch scales one real constant (or Q, R)"
        )
    return float(value)


def default_values(parameter: str) -> tuple[float, ...]:
    """The grid of multipliers a sweep of ``parameter`` takes by default: decades for the noise scales."""
    return NOISE_VALUES if parameter in NOISE_SCALES else DEFAULT_VALUES


def check_values(values: Sequence[float]) -> list[float]:
    """The multipliers, sorted; each finite and > 0 (a ScenarioError otherwise)."""
    out = sorted({float(v) for v in values})
    if not out or any(not (math.isfinite(v) and v > 0) for v in out):
        raise ScenarioError(f"mismatch values are multipliers of the true constant, finite and > 0; got {list(values)}")
    return out


def default_methods(scenario: Scenario) -> list[str]:
    """EKF, UKF, every data-trained network (the best one is chosen on the sets, :func:`mismatch`)
    and the hybrid where the zoo ships one for this scenario."""
    from neural_estimator.serving.instances import zoo_instances

    # the deterministic filters (EKF, UKF): the EnKF's and PF's draws would add their own noise to the sweep
    methods = list(table.names(family="classical", seeded=False)) + list(table.names(family="neural"))
    methods += [m for m in table.names(family="hybrid") if zoo_instances(scenario.name, m)]
    return methods


def mismatch(
    scenario: Scenario,
    parameter: str,
    values: Sequence[float] = DEFAULT_VALUES,
    methods: Sequence[str] | None = None,
    *,
    trajectories: int = 100,
    sets: int = 2,
    horizon: int | None = None,
    seed: int = 0,
    cache_dir: Any = None,
    progress: bool = False,
    warmup: int = M.EVALUATION_WARMUP,
    options: Mapping[str, Mapping[str, Any]] | None = None,
) -> dict[str, Any]:
    """The mismatch sweep of ``parameter`` (see the module docstring), as a strict-JSON-ready dict.

    ``methods`` None: :func:`default_methods`, of which only the best network (lowest median RMSE on
    these sets; every network's is recorded under ``"networks"``) is kept as a row. Given methods
    are all kept. Each must be a filter, a network or the hybrid (no baselines). ``options``:
    {method: {option: value}} as :func:`~neural_estimator.evaluation.protocol.evaluate` takes them
    (``reproduce`` bounds the filters' threads with it, an option that changes no result).
    """
    base = true_value(scenario, parameter)
    values = check_values(values)
    chosen = list(methods) if methods else default_methods(scenario)
    model_based = [m for m in chosen if table.has(m, needs_model=True)]
    networks = [m for m in chosen if not table.has(m, needs_model=True)]
    filters = [m for m in model_based if table.has(m, family="classical")]
    if not filters or any(table.has(m, family="baseline") for m in chosen):
        raise ScenarioError("mismatch compares methods with the best filter: name at least one filter, no baselines")
    data = evaluation_sets(
        scenario, seed=seed, trajectories=trajectories, horizon=horizon, sets=sets, cache_dir=cache_dir
    )
    kw = dict(datasets=data, seed=seed, cache_dir=cache_dir, progress=progress, warmup=warmup, options=options)
    nets = evaluate(scenario, networks, **kw) if networks else {}
    net_rmse = {m: r.summary["rmse"].median for m, r in nets.items()}
    if not methods and nets:  # the default: the best network on these sets
        best = min(net_rmse, key=lambda m: net_rmse[m] if math.isfinite(net_rmse[m]) else math.inf)
        nets = {best: nets[best]}
    points = []
    for v in values:
        told = model_scenario(scenario, {parameter: repr(v * base)}) if v != 1.0 else scenario
        res = evaluate(scenario, model_based, model_scenario=told, **kw)
        points.append(_point(scenario, v, {**res, **nets}, filters))
    out = {
        "schema": MISMATCH_SCHEMA,
        "scenario": scenario.describe(),
        "parameter": parameter,
        "true_value": base,
        "values": values,
        "relative_errors": [v - 1.0 for v in values],
        "trajectories": trajectories,
        "sets": sets,
        "horizon": data[0].horizon,
        "seed": seed,
        "warmup": warmup,
        "components": list(scenario.state_names),
        "methods": list(model_based) + list(nets),
        "networks": net_rmse,
        "points": points,
    }
    out["crossover"] = {
        family: crossover(points, m)
        for family, pool in (("network", nets), ("hybrid", [m for m in model_based if table.has(m, family="hybrid")]))
        for m in list(pool)[:1]
    }
    return M.to_json(out)


def _point(scenario: Scenario, v: float, results: dict[str, MethodResult], filters: Sequence[str]) -> dict[str, Any]:
    """One grid point: each method's RMSE (median over runs, aggregate and per component) and its
    paired ratio to the best filter at this point, with the 95 % interval."""
    rmse = {m: r.summary["rmse"].median for m, r in results.items()}
    finite = [m for m in filters if math.isfinite(rmse[m])]
    best = min(finite, key=rmse.get) if finite else filters[0]
    rows = {}
    for m, r in results.items():
        ratio, (lo, hi) = paired_ratio(r.runs_by_set(), results[best].runs_by_set())
        comps = [float(np.median([run_rmse(e, [d]) for e in r.errors])) for d in range(scenario.dx)]
        rows[m] = {"rmse": rmse[m], "rmse_components": comps, "ratio": ratio, "ci95": [lo, hi]}
    return {"value": v, "relative_error": v - 1.0, "best_filter": best, "methods": rows}


def crossover(points: Sequence[dict[str, Any]], method: str) -> dict[str, Any]:
    """The crossover of ``method`` against the best filter on each side of the exact model
    (module docstring): {"above": {...}, "below": {...}}, each with ``at`` (|e*|), ``ci95`` and
    ``beyond_grid`` (the largest |e| tried, where it never crosses)."""
    out: dict[str, Any] = {"method": method}
    exact = [p for p in points if p["relative_error"] == 0.0]
    for side, sign in (("above", 1.0), ("below", -1.0)):
        side_points = sorted(
            (p for p in points if sign * p["relative_error"] > 0), key=lambda p: abs(p["relative_error"])
        )
        if not side_points:  # no grid point on this side: nothing measured
            out[side] = None
            continue
        walk = exact + side_points
        e = [abs(p["relative_error"]) for p in walk]
        rho = [p["methods"][method]["ratio"] for p in walk]
        lo = [p["methods"][method]["ci95"][0] for p in walk]
        hi = [p["methods"][method]["ci95"][1] for p in walk]
        out[side] = {
            "at": _first_below_one(e, rho),
            "ci95": [_first_below_one(e, lo), _first_below_one(e, hi)],
            "largest_error": e[-1],
        }
    return out


def _first_below_one(e: Sequence[float], rho: Sequence[float]) -> float | None:
    """The smallest e where rho crosses below 1 (linear between grid points), 0 if rho(e_0) < 1,
    None if it never does (or a ratio is not finite on the way)."""
    for i, r in enumerate(rho):
        if r is None or not math.isfinite(r):
            return None
        if r < 1.0:
            if i == 0:
                return 0.0 if e[0] == 0.0 else float(e[0])
            ra = rho[i - 1]
            return float(e[i - 1] + (ra - 1.0) / (ra - r) * (e[i] - e[i - 1]))
    return None


def rows_csv(result: dict[str, Any]) -> str:
    """One line per (value, method): RMSE, its ratio to the best filter with the interval, each
    component's RMSE (state order)."""
    comps = result["components"]
    lines = [
        ",".join(
            ["scenario", "parameter", "value", "relative_error", "method", "best_filter", "rmse", "ratio"]
            + ["ratio_lo", "ratio_hi"]
            + [f"rmse_{c}" for c in comps]
        )
    ]
    name = result["scenario"]["scenario"]
    for p in result["points"]:
        for m, row in p["methods"].items():
            cells = [name, result["parameter"], _g(p["value"]), _g(p["relative_error"]), m, p["best_filter"]]
            cells += [_g(row["rmse"]), _g(row["ratio"]), _g(row["ci95"][0]), _g(row["ci95"][1])]
            cells += [_g(x) for x in row["rmse_components"]]
            lines.append(",".join(cells))
    return "\n".join(lines) + "\n"


def _g(x: Any) -> str:
    return "" if x is None else f"{float(x):.6g}"


def crossover_text(c: dict[str, Any] | None) -> str:
    """'+0.23 [0.15, 0.41]' style text of one side's crossover; '> 1' beyond the grid, '—' none."""
    if c is None:
        return "—"
    if c["at"] is None:
        return f"> {c['largest_error']:.2g}"
    lo, hi = c["ci95"]
    hi_text = f"> {c['largest_error']:.2g}" if hi is None else f"{hi:.2g}"
    lo_text = "?" if lo is None else f"{lo:.2g}"
    return f"{c['at']:.2g} [{lo_text}, {hi_text}]"


def exact_table(results: Sequence[dict[str, Any]], scenario_column: bool = True) -> list[str]:
    """Markdown lines, one row per scenario: at the exact model (v = 1, the same runs in every
    sweep of a scenario, so read from its first sweep that has it) the best filter's RMSE, the
    network's and the hybrid's, each challenger with its paired RMSE ratio to the filter [95 %]."""
    head = ["scenario"] * scenario_column + ["best filter", "network", "network / filter [95 %]"]
    head += ["hybrid", "hybrid / filter [95 %]"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    seen = set()
    for r in results:
        exact = next((p for p in r["points"] if p["value"] == 1.0), None)
        name = r["scenario"]["scenario"]
        if exact is None or name in seen:
            continue
        seen.add(name)
        best = exact["best_filter"]
        cells = [name] * scenario_column + [f"{best} {_rmse(exact['methods'][best]['rmse'])}"]
        for family in ("network", "hybrid"):
            c = r["crossover"].get(family)
            row = exact["methods"][c["method"]] if c else None
            cells += [f"{c['method']} {_rmse(row['rmse'])}", _ratio(row)] if row else ["—", "—"]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def crossover_table(results: Sequence[dict[str, Any]], scenario_column: bool = True) -> list[str]:
    """Markdown lines of the crossovers, two rows per sweep (the model's value too large, e > 0;
    too small, e < 0): where the network, and the hybrid, overtake the best filter, as the relative
    error |e*| of the model with its 95 % interval (:func:`crossover_text`). The results page
    (``docs/hooks/generate.py``) and the reproduce report print this table and :func:`exact_table`."""
    head = ["scenario"] * scenario_column + ["parameter", "model's value"]
    head += ["network crossover [95 %]", "hybrid crossover [95 %]"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in results:
        true = "noise scale" if r["parameter"] in NOISE_SCALES else f"true {r['true_value']:.4g}"
        cells = [r["scenario"]["scenario"]] * scenario_column + [f"`{r['parameter']}` ({true})"]
        for side, words in (("above", "too large"), ("below", "too small")):
            crossings = []
            for family in ("network", "hybrid"):
                c = r["crossover"].get(family)
                crossings.append(f"{c['method']} {crossover_text(c[side])}" if c else "—")
            lines.append("| " + " | ".join(cells + [words] + crossings) + " |")
    return lines


def _ratio(row: dict[str, Any]) -> str:
    return "—" if row["ratio"] is None else f"{row['ratio']:.3f} {_interval(row['ci95'])}".rstrip()


def _rmse(x: float | None) -> str:
    return "—" if x is None else f"{x:.4g}"


def _interval(ci: Sequence[float | None]) -> str:
    return "" if None in ci else f"[{ci[0]:.3f}, {ci[1]:.3f}]"


def write_result(result: dict[str, Any], out: str | Path) -> Path:
    """``out``/SCENARIO-PARAMETER.json (the sweep), .csv (:func:`rows_csv`) and .png
    (:func:`plot_mismatch`), each written whole; returns the common stem."""
    from neural_estimator.core.atomic import write_text_atomically

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    stem = out / f"{result['scenario']['scenario']}-{result['parameter']}"
    write_text_atomically(stem.with_suffix(".json"), json.dumps(result, indent=1, allow_nan=False) + "\n")
    write_text_atomically(stem.with_suffix(".csv"), rows_csv(result))
    plot_mismatch(result, stem.with_suffix(".png"))
    return stem


def plot_mismatch(result: dict[str, Any], path: Any) -> Any:
    """RMSE against the model's relative error, one line per method (the networks flat: they do not
    see the model), the crossovers marked; the style of :mod:`neural_estimator.metrics.plots`."""
    from neural_estimator.metrics.plots import new_figure, save_figure

    fig, ax = new_figure((6, 4))
    e = [p["relative_error"] for p in result["points"]]
    for m in result["methods"]:
        y = [p["methods"][m]["rmse"] for p in result["points"]]
        style = "--" if not table.has(m, needs_model=True) else "-"
        ax.plot(e, [np.nan if v is None else v for v in y], style, marker="o", ms=3, lw=1.4, label=m)
    for family, c in (result.get("crossover") or {}).items():
        for side, sign in (("above", 1.0), ("below", -1.0)):
            at = (c.get(side) or {}).get("at")
            if at is not None:
                ax.axvline(sign * at, color="k", lw=0.8, ls=":")
                ax.annotate(
                    f"{family} crossover",
                    (sign * at, 0.98),
                    xycoords=("data", "axes fraction"),
                    rotation=90,
                    va="top",
                    ha="right",
                    fontsize=7,
                )
    ax.set_yscale("log")
    ax.set_xlabel(f"relative error of the model's {result['parameter']} (0 = exact)")
    ax.set_ylabel("RMSE")
    ax.set_title(f"{result['scenario']['scenario']}: {result['parameter']} mismatch")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    return save_figure(fig, path)


def result_text(result: dict[str, Any]) -> str:
    """The sweep as text: per value the best filter and each method's RMSE and ratio [95 %], then
    the crossovers."""
    head = (
        f"{result['scenario']['scenario']}: model {result['parameter']} = v x {result['true_value']:.6g}, "
        f"{result['sets']} sets x {result['trajectories']} trajectories x {result['horizon']} steps"
    )
    lines = [head, f"{'v':>6} {'best filter':>11}  " + "  ".join(f"{m:>26}" for m in result["methods"])]
    for p in result["points"]:
        cells = []
        for m in result["methods"]:
            row = p["methods"][m]
            ci = row["ci95"]
            ratio = "—" if row["ratio"] is None else f"{row['ratio']:.3f}"
            bounds = "" if None in ci else f" [{ci[0]:.2f},{ci[1]:.2f}]"
            cells.append(f"{row['rmse']:>9.4g} x{ratio}{bounds}".rjust(26))
        lines.append(f"{p['value']:>6g} {p['best_filter']:>11}  " + "  ".join(cells))
    for family, c in result["crossover"].items():
        lines.append(
            f"crossover of the {family} ({c['method']}) over the best filter, relative error |e| [95 %]: "
            f"model too large {crossover_text(c['above'])}, too small {crossover_text(c['below'])}"
        )
    return "\n".join(lines) + "\n"
