"""The decision table printed beside the paper's: per method, the RMSE of every state component in
its own units, the paired ratio to the best filter with its 95 % interval, the verdict and the
number of trained instances; baselines as reference rows. The figures are those of
:mod:`neural_estimator.evaluation.comparison`, also written to results.json."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING

from neural_estimator.evaluation import comparison as C
from neural_estimator.methods import table
from neural_estimator.scenarios import Scenario  # or any object with state_names, state_units and dx

if TYPE_CHECKING:
    from neural_estimator.evaluation.protocol import MethodResult

NOT_ESTIMATED = "not estimated"


def component_headers(scenario: Scenario, flags: list[bool] | None) -> list[str]:
    """'name [unit]' per state component, '(not estimated)' added where no method beats open loop."""
    units = list(getattr(scenario, "state_units", ()) or [""] * scenario.dx)
    out = []
    for d, name in enumerate(scenario.state_names):
        head = f"{name} [{units[d]}]" if d < len(units) and units[d] else str(name)
        if flags is not None and flags[d]:
            head += f" ({NOT_ESTIMATED})"
        out.append(head)
    return out


def decision_table(scenario: Scenario, results: Mapping[str, MethodResult], fmt: str = "text") -> str | None:
    """The table (``fmt`` "text" or "markdown"); None when no run carries component errors. At most
    the first 8 components are columns (Lorenz 96 has 40: the rest are in results.json)."""
    stats = {m: C.component_stats(r) for m, r in results.items() if r.reports}
    stats = {m: s for m, s in stats.items() if s is not None}
    if not stats:
        return None
    flags = C.not_estimated(results)
    shown = min(scenario.dx, 8)
    pairs = C.paired(results)
    ref = next((p["reference"] for p in pairs.values() if p), None)
    header = ["Method"] + component_headers(scenario, flags)[:shown]
    header += [f"RMSE / {ref} [95% CI]" if ref else "RMSE ratio", "verdict", "instances"]
    body = []
    for m, s in stats.items():
        r = results[m]
        name = f"{m} (reference row)" if r.baseline else m
        row = [name] + [_number(st.median) for st in s[:shown]]
        p = pairs.get(m)
        if p is None:
            row += ["—", "—"]
        else:
            lo, hi = p["ci95"]
            ratio = f"{p['ratio']:.3f}" if math.isfinite(p["ratio"]) else _number(p["ratio"])
            row += [f"{ratio} [{_number(lo, 3)}, {_number(hi, 3)}]", p["verdict"]]
        row.append(_instances(r))
        body.append(row)
    if fmt == "markdown":
        lines = ["| " + " | ".join(header) + " |", "|" + "|".join(["---"] + ["---:"] * (len(header) - 1)) + "|"]
        return "\n".join(lines + ["| " + " | ".join(r) + " |" for r in body]) + "\n"
    widths = [max(len(r[i]) for r in [header] + body) for i in range(len(header))]
    return (
        "\n".join(
            "  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths))).rstrip()
            for r in [header] + body
        )
        + "\n"
    )


def decision_notes(scenario: Scenario, results: Mapping[str, MethodResult]) -> list[str]:
    """The lines under the table: what the ratio is, which components are not estimated, where the
    outlier rule changes the ranking."""
    notes = [
        "ratio: the method's RMSE over the reference's (median over runs), 95% paired bootstrap interval over "
        "trajectories and trained instances; better / worse when the interval excludes 1, else tied"
    ]
    flags = C.not_estimated(results)
    if flags is None:
        notes.append("components not judged: add openloop to --methods to flag those no method estimates")
    elif any(flags):
        names = [n for n, f in zip(scenario.state_names, flags) if f]
        notes.append(
            f"{NOT_ESTIMATED}: {', '.join(names)} (no method beats the open-loop baseline on it by 10%; the "
            "aggregate RMSE there says nothing about filtering)"
        )
    if len(C.ranked(results)) > 1 and C.outlier_rule_flips(results):
        notes.append(
            "the outlier rule changes the ranking: the Full RMSE (every trajectory) ranks "
            f"{C.reference_method(results, full=True)} best among the filters; judge on the Full RMSE"
        )
    return notes


def estimates_decision(truth, estimates, angles, reports, warmup: int, fmt: str = "text", errors=None) -> str:
    """The decision table and its notes for estimates given as arrays (the ``metrics`` verb, a bag's
    report): ``truth`` a Trajectories (with ``errors``: anything with a ``meta``) whose meta may
    name the state components, ``estimates``
    {method: (x_hat, P or None)}, ``reports`` their :class:`~neural_estimator.metrics.MetricReport`;
    "" when there is nothing to show. ``errors``: {method: TrajectoryErrors} already computed (a
    block scorer's, :mod:`neural_estimator.metrics.streaming`), instead of recomputing them from the
    arrays."""
    from types import SimpleNamespace

    from neural_estimator import metrics as M
    from neural_estimator.evaluation.protocol import MethodResult

    results = {}
    for m, rep in reports.items():
        results[m] = MethodResult(m)
        per_trajectory = (errors or {}).get(m)
        if per_trajectory is None:
            labelled = getattr(truth, "labelled", None)
            per_trajectory = M.trajectory_errors(truth.x, estimates[m][0], angles, rep.outlier_idx, warmup, labelled)
        results[m].add(rep, per_trajectory)
    dx = next(iter(errors.values())).mse.shape[1] if errors else truth.x.shape[2]
    names = truth.meta.get("state_names") or [f"x{d}" for d in range(dx)]
    units = truth.meta.get("state_units") or [""] * dx
    states = SimpleNamespace(state_names=list(names), state_units=list(units), dx=dx)
    table = decision_table(states, results, fmt=fmt)
    if not table:
        return ""
    bullet = "- " if fmt == "markdown" else ""
    return table + "".join(f"{bullet}{line}\n" for line in decision_notes(states, results))


def _instances(result: MethodResult) -> str:
    """Trained instances of a network ('1 instance', or K with the spread of their RMSE); '—' else."""
    if not table.has(result.method, trainable=True):
        return "—"
    k = result.n_instances
    if k == 1:
        return "1 instance"
    spread = C.instance_spread(result)
    return f"{k} (RMSE {min(spread):.3g}-{max(spread):.3g})"


def _number(x: float, digits: int = 4) -> str:
    if not math.isfinite(x):
        return "inf" if x == math.inf else "N/A"
    return f"{x:.{digits}g}"
