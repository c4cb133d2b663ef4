"""The paper's seven findings judged on paired intervals, not on point figures.

:mod:`neural_estimator.paper.reproduce.fidelity` judges each finding on medians. A median ratio of 1.1
from 200 trajectories may be noise; here every comparison a finding makes is a paired ratio of two
methods on the same trajectories with its 95 % bootstrap interval
(:func:`neural_estimator.metrics.paired_ratio`), and a finding is judged on the interval:

- a *factor* finding (the paper's A is f_p times B: PF / EKF on the quadrotor, best network / EKF
  on the quadrotor, Filterformer / Mamba-2 on Lorenz 96 and N-link, EKF / UKF on ballistic):
  **reproduced** when the whole interval is at or above sqrt(f_p), **partly** when it lies above 1
  and below sqrt(f_p), **not** when it holds 1 or lies below, **undecided** when it straddles
  sqrt(f_p);
- *approach* (best SSM / best filter on Lorenz 96): **reproduced** when the interval lies at or
  below 1.2, **partly** when within (1.2, 2], **not** above 2, **undecided** across a boundary;
- *an SSM is the best network* (per scenario, the best SSM over the best other network run
  continuously): **SSM ahead** when the interval lies below 1, **tied** when it holds 1 (the tie
  is named), **behind** above 1; reproduced when an SSM is ahead in every scenario, partly when
  it is behind in none or ahead in three or more, not otherwise;
- *the EnKF diverges on bearings*: **reproduced** when it diverges or the EnKF / EKF interval lies
  at or above 10, **partly** when above 1.5, **not** otherwise.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from neural_estimator import metrics as M
from neural_estimator.methods import table

# the paper's filters, networks and selective state-space models, in its row order (the table of methods)
CLASSICAL_METHODS, NEURAL_METHODS = table.paper_methods(family="classical"), table.paper_methods(family="neural")
SSM = table.paper_methods(state_space=True)


def paper_factors() -> dict[str, float]:
    """The paper's factors, from its main table: PF / EKF and best network / EKF on the quadrotor,
    the smaller Filterformer / Mamba-2 of Lorenz 96 and N-link, EKF / UKF on ballistic."""
    from neural_estimator.paper.reproduce.fidelity import paper_table

    p = paper_table()
    q = p["quadrotor"]
    return {
        "pf_quadrotor": q["pf"] / q["ekf"],
        "network_quadrotor": min(q[m] for m in NEURAL_METHODS) / q["ekf"],
        "filterformer": min(p[s]["filterformer"] / p[s]["mamba2"] for s in ("lorenz96", "nlink")),
        "ekf_ukf": p["ballistic"]["ekf"] / p["ballistic"]["ukf"],
    }


# What each finding needs evaluated: {scenario: methods}.
NEEDED = {
    "lorenz96": ("ekf", "ukf", "enkf") + NEURAL_METHODS,
    "quadrotor": ("ekf", "pf") + NEURAL_METHODS,
    "nlink": ("filterformer", "mamba2") + tuple(m for m in NEURAL_METHODS if m not in ("filterformer", "mamba2")),
    "bearings": ("ekf", "enkf") + NEURAL_METHODS,
    "ballistic": ("ekf", "ukf") + NEURAL_METHODS,
}


def covers(by_scenario: Mapping[str, Mapping[str, Any]]) -> bool:
    """Whether ``by_scenario`` holds every method :func:`judge` compares (:data:`NEEDED`)."""
    return all(s in by_scenario and all(m in by_scenario[s] for m in ms) for s, ms in NEEDED.items())


def pair(results: Mapping[str, Any], a: str, b: str) -> tuple[float, tuple[float, float]]:
    """Paired ratio RMSE(a) / RMSE(b) and its interval, from two MethodResults of one evaluation."""
    return M.paired_ratio(results[a].runs_by_set(), results[b].runs_by_set())


def factor_status(ci: tuple[float, float], paper_factor: float) -> str:
    lo, hi = ci
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return "undecided"
    bar = math.sqrt(paper_factor)
    if lo >= bar:
        return "reproduced"
    if hi <= 1.0 or lo <= 1.0:
        return "not"
    return "partly" if hi < bar else "undecided"


def approach_status(ci: tuple[float, float]) -> str:
    lo, hi = ci
    if hi <= 1.2:
        return "reproduced"
    if lo > 2.0:
        return "not"
    if lo > 1.2 and hi <= 2.0:
        return "partly"
    return "undecided"


def _best(results, methods) -> str | None:
    scored = {m: results[m].summary["rmse"].median for m in methods if m in results and results[m].reports}
    scored = {m: v for m, v in scored.items() if math.isfinite(v)}
    return min(scored, key=scored.get) if scored else None


def judge(by_scenario: Mapping[str, Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Each finding: {finding, compared, ratio, ci95, status}; ``by_scenario`` {scenario: results of
    :func:`~neural_estimator.evaluation.evaluate`} holding :data:`NEEDED`."""
    out = []
    factors = paper_factors()

    def add(finding, compared, ratio, ci, status):
        out.append(dict(finding=finding, compared=compared, ratio=ratio, ci95=list(ci), status=status))

    l96 = by_scenario["lorenz96"]
    ssm, flt = _best(l96, SSM), _best(l96, CLASSICAL_METHODS)
    r, ci = pair(l96, ssm, flt)
    add(
        "Mamba and Mamba-2 approach the best classical filter on Lorenz 96",
        f"{ssm} / {flt}",
        r,
        ci,
        approach_status(ci),
    )
    quad = by_scenario["quadrotor"]
    r, ci = pair(quad, "pf", "ekf")
    add("the PF fails on the planar quadrotor", "pf / ekf", r, ci, factor_status(ci, factors["pf_quadrotor"]))
    verdicts = []
    for s, res in by_scenario.items():
        continuous = [m for m in NEURAL_METHODS if m in res and res[m].reports and not res[m].context]
        best_ssm, best_other = (
            _best(res, [m for m in continuous if m in SSM]),
            _best(res, [m for m in continuous if m not in SSM]),
        )
        if best_ssm is None or best_other is None:
            continue
        _, c = pair(res, best_ssm, best_other)
        word = {"better": "SSM ahead", "worse": "behind", "tied": "tied"}.get(M.verdict(c), "undecided")
        verdicts.append(f"{s}: {best_ssm} / {best_other} [{c[0]:.2f}, {c[1]:.2f}] {word}")
    behind = sum(v.endswith("behind") for v in verdicts)
    ahead = sum(v.endswith("SSM ahead") for v in verdicts)
    status = (
        "not measured"
        if not verdicts
        else "reproduced"
        if ahead == len(verdicts)
        else "partly"
        if not behind or ahead >= 3
        else "not"
    )
    add(
        "an SSM (Mamba or Mamba-2) is the best neural model in every scenario",
        "; ".join(verdicts),
        math.nan,
        (math.nan, math.nan),
        status,
    )
    net = _best(quad, NEURAL_METHODS)
    r, ci = pair(quad, net, "ekf")
    add(
        "the EKF dominates the planar quadrotor, far ahead of every neural model",
        f"{net} / ekf",
        r,
        ci,
        factor_status(ci, factors["network_quadrotor"]),
    )
    gaps = [(s, *pair(by_scenario[s], "filterformer", "mamba2")) for s in ("lorenz96", "nlink")]
    s, r, ci = min(gaps, key=lambda g: g[1])
    add(
        "the Filterformer is far behind Mamba-2 on Lorenz 96 and N-link",
        f"filterformer / mamba2 ({s}, the smaller)",
        r,
        ci,
        factor_status(ci, factors["filterformer"]),
    )
    brg = by_scenario["bearings"]
    r, ci = pair(brg, "enkf", "ekf")
    diverged = any(rep.n_diverged for rep in brg["enkf"].reports)
    status = "reproduced" if diverged or ci[0] >= 10 else "partly" if ci[0] > 1.5 else "not"
    add("the EnKF diverges on bearings-only tracking", "enkf / ekf", r, ci, status)
    r, ci = pair(by_scenario["ballistic"], "ekf", "ukf")
    add(
        "the UKF beats the EKF by a wide margin on ballistic re-entry",
        "ekf / ukf",
        r,
        ci,
        factor_status(ci, factors["ekf_ukf"]),
    )
    return out


def render(judged: list[dict[str, Any]]) -> str:
    """The findings' table, from :func:`judge` or its JSON (where NaN and inf were written as null)."""
    lines = ["| finding | compared | ratio [95% CI] | on the interval |", "|---|---|---|---|"]
    for j in judged:
        ratio = math.nan if j["ratio"] is None else j["ratio"]
        lo, hi = (math.nan if v is None else v for v in j["ci95"])
        cell = "—" if not math.isfinite(ratio) else f"{ratio:.2f} [{lo:.2f}, {hi:.2f}]"
        lines.append(f"| {j['finding']} | {j['compared']} | {cell} | {j['status']} |")
    return "\n".join(lines) + "\n"
