#!/usr/bin/env python3
"""Search the scenario constants that the paper leaves out, against its classical-filter rows and
the spread of its true states.

The paper (Table "accuracy_main" and the extended per-scenario tables) reports the RMSE of the
EKF, UKF, EnKF and PF in every scenario. Those rows do not depend on any training budget, so they
pin down the unstated constants (units and scale, noise levels, prior, sampling period). One
number per filter is not enough, though: the same RMSE is reached at operating points whose states
move ten times more or less. The paper's NRMSE column fixes that: NRMSE divides each component's
error by the spread of the true state (:func:`neural_estimator.metrics.state_spread`), so
RMSE / NRMSE is a weighted spread of the true states, a property of the scenario (nearly the same
for every method of a row in the paper). For each candidate set of constants this script
simulates a modest number of trajectories, runs the filters, and prints every method's RMSE beside
the paper's together with two distances,

    d_rmse  = max over EKF and UKF of |log(ours / paper)|                   (RMSE rows)
    d_ratio = |log(ratio_ours / ratio_paper)|, ratio = RMSE / NRMSE          (spread of the truth)

where ratio_paper is the ratio of the paper's most accurate method of the scenario (lowest NRMSE:
the row least driven by outliers; :data:`PAPER_RATIO`) and ratio_ours that of the most accurate of
the filters run. log 1.5 = 0.405 is the target for both. The first candidate of every scenario
after the presets is ``x0std1``: the paper's "x0 std = 1.0" read as the prior std of every
component.

Candidates come from the literature each system descends from (cited in each scenario module) and
from the paper's own hyperparameter table; the chosen one of each scenario is the default of its
``Config`` (the preset ``v4``; for N-link and bearings, whose ``v4`` fits the RMSE rows alone, the
joint fit ``v5``), documented in its docstring and in docs/scenarios.md. ``v3`` is the preset of
the constants before this calibration.

Usage (small default sizes, minutes on a loaded 2-core machine):

    .venv/bin/python experiments/calibrate_scenarios.py --scenario ballistic
    python experiments/calibrate_scenarios.py --scenario ballistic --trajectories 300 --methods ekf,ukf,enkf,pf
    .venv/bin/python experiments/calibrate_scenarios.py --scenario nlink --candidate v3 --candidate x0std1
    .venv/bin/python experiments/calibrate_scenarios.py --scenario quadrotor --set obs_noise_std=0.2

``--set name=value`` applies to every candidate of the run (after the candidate's own constants).
A candidate whose constants cannot be simulated (a prior with mass where the dynamics blow up)
prints its one-line error and the search goes on.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import json  # noqa: E402

from neural_estimator.data import DataError  # noqa: E402
from neural_estimator.methods.registry import EstimatorError  # noqa: E402
from neural_estimator.evaluation import INIT_MODES, evaluate  # noqa: E402
from neural_estimator.metrics import MetricsError  # noqa: E402
from neural_estimator.scenarios import ScenarioError, make_scenario, parse_assignments  # noqa: E402

# Paper, Table accuracy_main / extended tables: median RMSE (inf: "numerical divergence").
PAPER_RMSE = {
    "ballistic": {"ekf": 5.289, "ukf": 0.626, "enkf": 0.821, "pf": 0.657},
    "bearings": {"ekf": 308.624, "ukf": 180.946, "enkf": math.inf, "pf": 362.554},
    "lorenz96": {"ekf": 0.049, "ukf": 0.048, "enkf": 0.054, "pf": 0.065},
    "nlink": {"ekf": 0.080, "ukf": 0.081, "enkf": 0.092, "pf": 0.086},
    "quadrotor": {"ekf": 0.287, "ukf": 8.042, "enkf": 9.960, "pf": 128.009},
}


def paper_ratios(path: Path | None = None) -> dict[str, tuple[str, float]]:
    """scenario -> (method, RMSE / NRMSE) of the paper's most accurate method (lowest NRMSE)."""
    path = path or Path(__file__).resolve().parents[1] / "neural_estimator" / "paper" / "paper_results.json"
    rows = json.loads(path.read_text())["accuracy_main"]
    out = {}
    for scen, methods in rows.items():
        finite = {
            m: (float(c["rmse"]), float(c["nrmse"]))
            for m, c in methods.items()
            if math.isfinite(float(c["rmse"])) and math.isfinite(float(c["nrmse"])) and float(c["nrmse"]) > 0
        }
        best = min(finite, key=lambda m: finite[m][1])
        out[scen] = (best, finite[best][0] / finite[best][1])
    return out


PAPER_RATIO = paper_ratios()

# Candidate constants per scenario: label -> (preset, overrides, where they come from). The
# overrides apply on top of the preset; "v3", "v4" and "v5" are the presets themselves.
CANDIDATES: dict[str, dict[str, tuple[str, dict, str]]] = {
    "ballistic": {
        "v4": ("v4", {}, "the defaults (chosen below)"),
        "v3": ("v3", {}, "SSMToybox km scaling, drag spread 0.01 (calibrated to the RMSE rows only)"),
        "x0std1": ("v3", {"prior_std": (1.0, 1.0, 1.0)}, "the paper's x0 std = 1.0 for every component"),
        "x0std1-c4": (
            "v3",
            {"prior_std": (1.0, 1.0, 1.0), "prior_mean": (90.0, 6.0, 4.0)},
            "x0 std 1.0, drag mean 4 (positive drag without truncation)",
        ),
        "drag1-c4": (
            "v3",
            {"prior_std": (0.3048, 1.2192, 1.0), "prior_mean": (90.0, 6.0, 4.0)},
            "SSMToybox altitude/velocity spread, drag spread 1.0 around 4",
        ),
        "x0std1-dt0.02": ("v3", {"prior_std": (1.0, 1.0, 1.0), "dt": 0.02}, "x0 std 1.0, 10 s horizon"),
        "x0std1-dt0.01": ("v3", {"prior_std": (1.0, 1.0, 1.0), "dt": 0.01}, "x0 std 1.0, 5 s horizon"),
        "x0std1-dt0.05": ("v3", {"prior_std": (1.0, 1.0, 1.0), "dt": 0.05}, "x0 std 1.0, 25 s horizon"),
    },
    "bearings": {
        "v5": ("v5", {}, "the defaults: the far crossing, far4k-q0.12 (chosen below)"),
        "v4": ("v4", {}, "slow crossing target, narrow prior (calibrated to the RMSE rows only; = v3)"),
        "v3": ("v3", {}, "slow crossing target, narrow prior (calibrated to the RMSE rows only)"),
        "x0std1": ("v3", {"prior_std": (1.0, 1.0, 1.0, 1.0)}, "the paper's x0 std = 1.0 for every component"),
        "x0std1-q0.2": (
            "v3",
            {"prior_std": (1.0, 1.0, 1.0, 1.0), "accel_noise_std": 0.2},
            "x0 std 1.0, gentler manoeuvres",
        ),
        "x0std1-q0.15": (
            "v3",
            {"prior_std": (1.0, 1.0, 1.0, 1.0), "accel_noise_std": 0.15},
            "x0 std 1.0, gentler manoeuvres",
        ),
        "q0.2": ("v3", {"accel_noise_std": 0.2}, "gentler manoeuvres"),
        "x0std1-v1": (
            "v3",
            {"prior_std": (1.0, 1.0, 1.0, 1.0), "prior_mean": (-200.0, 400.0, 1.0, 0.0)},
            "x0 std 1.0, slower crossing",
        ),
        "far3k-q0.15": (
            "v3",
            {"prior_mean": (-200.0, 3000.0, 2.0, 0.0), "accel_noise_std": 0.15},
            "the same crossing 3 km from the sensor, gentler manoeuvres",
        ),
        "far4k-q0.12": (
            "v3",
            {"prior_mean": (-200.0, 4000.0, 2.0, 0.0), "accel_noise_std": 0.12},
            "the same crossing 4 km from the sensor, gentler manoeuvres",
        ),
    },
    "lorenz96": {
        "v4": ("v4", {}, "J = 10, obs std 0.07, process std 0.05 (matches both already)"),
        "x0std1": ("v4", {"prior_std": 1.0}, "the paper's x0 std = 1.0 as the filters' prior spread"),
    },
    "nlink": {
        "v5": ("v5", {}, "the defaults: x0std1-rate0.1-r0.01 (chosen below)"),
        "v4": ("v4", {}, "prior 0.1 rad, 0.1 rad/s, obs 0.02 m (calibrated to the RMSE rows only; = v3)"),
        "v3": ("v3", {}, "prior 0.1 rad, 0.1 rad/s, obs 0.02 m (calibrated to the RMSE rows only)"),
        "x0std1": ("v3", {"prior_angle_std": 1.0, "prior_rate_std": 1.0}, "the paper's x0 std = 1.0"),
        "x0std1-r0.01": (
            "v3",
            {"prior_angle_std": 1.0, "prior_rate_std": 1.0, "obs_noise_std": 0.01},
            "x0 std 1.0, better position sensor",
        ),
        "x0std1-r0.005": (
            "v3",
            {"prior_angle_std": 1.0, "prior_rate_std": 1.0, "obs_noise_std": 0.005},
            "x0 std 1.0, better position sensor",
        ),
        "x0std1-q0.001": (
            "v3",
            {"prior_angle_std": 1.0, "prior_rate_std": 1.0, "process_noise_q": 0.001},
            "x0 std 1.0, smaller process noise",
        ),
        "x0std1-r0.01-q0.001": (
            "v3",
            {"prior_angle_std": 1.0, "prior_rate_std": 1.0, "obs_noise_std": 0.01, "process_noise_q": 0.001},
            "x0 std 1.0, better sensor, smaller process noise",
        ),
        "x0std1-rate0.1": (
            "v3",
            {"prior_angle_std": 1.0, "prior_rate_std": 0.1},
            "x0 std 1.0 on the angles, the links released nearly at rest",
        ),
        "x0std1-rate0.1-r0.01": (
            "v3",
            {"prior_angle_std": 1.0, "prior_rate_std": 0.1, "obs_noise_std": 0.01},
            "x0 std 1.0 on the angles, released nearly at rest, 1 cm position sensor",
        ),
        "angle0.5-rate0.5": ("v3", {"prior_angle_std": 0.5, "prior_rate_std": 0.5}, "half the paper's x0 std"),
        "rate3-r0.01": (
            "v3",
            {"prior_angle_std": 1.0, "prior_rate_std": 3.0, "obs_noise_std": 0.01},
            "x0 std 1.0 on angles, faster initial rates",
        ),
    },
    "quadrotor": {
        "v4": ("v4", {}, "the defaults (chosen below)"),
        "v3": ("v3", {}, "velocity noise 0.1 per step (calibrated to the RMSE rows only)"),
        "x0std1": ("v3", {"prior_std": (1.0,) * 6}, "the paper's x0 std = 1.0 for every component"),
        "x0std1-dt0.05": ("v3", {"prior_std": (1.0,) * 6, "dt": 0.05}, "x0 std 1.0, tau 0.05 s (10 s)"),
        "x0std1-dt0.1": ("v3", {"prior_std": (1.0,) * 6, "dt": 0.1}, "x0 std 1.0, tau 0.1 s (20 s)"),
        "x0std1-h500": ("v3", {"prior_std": (1.0,) * 6, "horizon": 500}, "x0 std 1.0, 500 steps"),
        "x0std1-q0.15-t0.5": (
            "v3",
            {"prior_std": (1.0,) * 6, "process_noise_std": 0.15, "thrust_perturb_rel": 0.5},
            "x0 std 1.0, thrust perturbation 50 % (some flights grow without bound)",
        ),
        "x0std1-q0.15-t1": (
            "v3",
            {"prior_std": (1.0,) * 6, "process_noise_std": 0.15, "thrust_perturb_rel": 1.0},
            "x0 std 1.0, thrust perturbation 100 % (flights grow without bound)",
        ),
        "x0std1-dt0.05-q0.03": (
            "v3",
            {"prior_std": (1.0,) * 6, "dt": 0.05, "process_noise_std": 0.03},
            "x0 std 1.0, tau 0.05 s, smaller velocity noise",
        ),
    },
}


def distance(ours: dict[str, float], paper: dict[str, float], methods=("ekf", "ukf")) -> float:
    """max over ``methods`` of |log(ours / paper)|; inf where either is not finite or positive."""
    out = 0.0
    for m in methods:
        a, b = ours.get(m, math.nan), paper[m]
        if not (math.isfinite(a) and math.isfinite(b) and a > 0 and b > 0):
            return math.inf
        out = max(out, abs(math.log(a / b)))
    return out


def ratio_distance(res: dict[str, dict[str, float]], paper_ratio: float) -> tuple[float, float]:
    """(our RMSE / NRMSE, |log(ours / paper)|): ours is the ratio of the method with the lowest
    NRMSE among those run (inf where none is finite)."""
    finite = {m: r for m, r in res.items() if math.isfinite(r["nrmse"]) and r["nrmse"] > 0 and math.isfinite(r["rmse"])}
    if not finite:
        return math.inf, math.inf
    best = min(finite.values(), key=lambda r: r["nrmse"])
    ratio = best["rmse"] / best["nrmse"]
    return ratio, abs(math.log(ratio / paper_ratio))


def run_candidate(
    scenario_name: str,
    preset: str,
    overrides: dict,
    methods: list[str],
    trajectories: int,
    horizon: int | None,
    seed: int,
    init: str,
    pf_trajectories: int | None,
) -> dict[str, dict[str, float]]:
    """RMSE, full RMSE and outlier ratio of each method on one evaluation set of the candidate."""
    scenario = make_scenario(scenario_name, preset=preset, **overrides)
    out: dict[str, dict[str, float]] = {}
    for m in methods:
        n = pf_trajectories if (m == "pf" and pf_trajectories) else trajectories
        res = evaluate(
            scenario,
            [m],
            trajectories=n,
            horizon=horizon,
            seed=seed,
            sets=1,
            cache_dir=False,
            progress=False,
            init=init,
        )[m]
        rep = res.reports[0]
        out[m] = {
            "rmse": float(rep.rmse),
            "nrmse": float(rep.nrmse),
            "full": float(rep.full_rmse),
            "out": float(rep.outlier_ratio),
            "medae": float(rep.medae),
            "drift": float(rep.drift_ratio),
        }
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenario", required=True, choices=sorted(PAPER_RMSE))
    p.add_argument("--candidate", action="append", help="label(s) to run (default: all of the scenario)")
    p.add_argument("--methods", default="ekf,ukf", help="comma-separated classical methods (default ekf,ukf)")
    p.add_argument("--trajectories", type=int, default=100, help="trajectories per candidate (default 100)")
    p.add_argument("--pf-trajectories", type=int, help="fewer trajectories for the PF (default: --trajectories)")
    p.add_argument("--horizon", type=int, help="steps (default: the scenario's)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--init", choices=INIT_MODES, default="prior", help="how the filters start (see evaluate --init)")
    p.add_argument("--set", action="append", metavar="NAME=VALUE", help="constant applied to every candidate")
    args = p.parse_args(argv)

    extra = parse_assignments(args.set)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    table = CANDIDATES[args.scenario]
    labels = args.candidate or list(table)
    unknown = [c for c in labels if c not in table]
    if unknown:
        p.error(f"unknown candidate(s) {', '.join(unknown)} for {args.scenario}; choose from {', '.join(table)}")
    paper = PAPER_RMSE[args.scenario]
    ratio_method, paper_ratio = PAPER_RATIO[args.scenario]
    print(
        f"{args.scenario}: {args.trajectories} trajectories, init={args.init}, seed {args.seed}; "
        f"paper RMSE "
        + ", ".join(f"{m} {paper[m]:g}" for m in methods)
        + f"; paper RMSE/NRMSE {paper_ratio:.3g} ({ratio_method})"
    )
    for label in labels:
        preset, overrides, source = table[label]
        t0 = time.perf_counter()
        constants = {**overrides, **extra}
        try:
            scenario = make_scenario(args.scenario, preset=preset, **constants)
            res = run_candidate(
                args.scenario,
                preset,
                constants,
                methods,
                args.trajectories,
                args.horizon,
                args.seed,
                args.init,
                args.pf_trajectories,
            )
        except (ScenarioError, DataError, EstimatorError, MetricsError) as exc:
            print(f"- {label:<14} not run: {exc}", flush=True)
            continue
        ours = {m: r["rmse"] for m, r in res.items()}
        ratio, d_ratio = ratio_distance(res, paper_ratio)
        cells = "  ".join(
            f"{m} {r['rmse']:.4g} (x{r['rmse'] / paper[m]:.2f}; nrmse {r['nrmse']:.3g}, medae {r['medae']:.3g}, "
            f"out {r['out']:.3f})"
            for m, r in res.items()
        )
        rejected = getattr(scenario, "rejected_fraction", None)
        note = f" rejected prior mass {rejected():.3f};" if rejected and rejected() > 0 else ""
        print(
            f"- {label:<14} d_rmse={distance(ours, paper):.3f} d_ratio={d_ratio:.3f} (ratio {ratio:.3g})"
            f"{note}  {cells}  [{time.perf_counter() - t0:.0f} s] {source}",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
