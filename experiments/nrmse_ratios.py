"""RMSE / NRMSE of our filters on each scenario, beside the paper's ranges.

    .venv/bin/python experiments/nrmse_ratios.py                      # EKF, UKF; 30 trajectories, seed 7
    .venv/bin/python experiments/nrmse_ratios.py --trajectories 100 --methods ekf,ukf,enkf

The paper does not define NRMSE; docs/metrics.md explains the definition chosen from its tables.
This prints, per scenario and method, RMSE, Full RMSE, NRMSE (``nrmse``), ``nrmse_spread``, the ratio
RMSE / NRMSE and the per-component spreads s_d of the true state, so the ratios can be set beside
the paper's (RMSE / NRMSE within a scenario: ballistic 0.9-3.4, bearings 250-320, Lorenz 96 3.4-3.7,
N-link 5.5-8 except the PF, quadrotor 32-134). Seconds on 2 cores; no cache is written.
"""

from __future__ import annotations

import argparse

import numpy as np

from neural_estimator import metrics as M
from neural_estimator.data import simulate
from neural_estimator.methods.registry import make_estimator
from neural_estimator.scenarios import make_scenario

PAPER_RATIO_RANGE = {  # min and max RMSE / NRMSE over the ten methods of the paper's appendix tables
    "ballistic": (0.935, 3.37),
    "bearings": (254, 323),
    "lorenz96": (3.43, 3.69),
    "nlink": (5.5, 8.0),
    "quadrotor": (32, 134),
}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenarios", default=",".join(PAPER_RATIO_RANGE))
    p.add_argument("--methods", default="ekf,ukf")
    p.add_argument("--trajectories", type=int, default=30)
    p.add_argument("--seed", type=int, default=7)
    args = p.parse_args(argv)
    for name in args.scenarios.split(","):
        sc = make_scenario(name)
        data = simulate(sc, args.trajectories, None, seed=args.seed)
        for m in args.methods.split(","):
            est = make_estimator(m, sc, seed=0).run(data.y, data.u)
            r = M.compute_metrics(data.x, est.x, sc.angle_states, diverged=est.diverged)
            lo, hi = PAPER_RATIO_RANGE.get(name, (np.nan, np.nan))
            print(
                f"{name:9s} {m:4s} RMSE {r.rmse:.4g}  Full {r.full_rmse:.4g}  NRMSE {r.nrmse:.4g}  "
                f"nrmse_spread {r.nrmse_spread:.4g}  RMSE/NRMSE {r.rmse / r.nrmse:.3g} (paper {lo:g}-{hi:g})  "
                f"s_d {np.array2string(r.spread[:6], precision=4)}{' ...' if r.spread.size > 6 else ''}",
                flush=True,
            )


if __name__ == "__main__":
    main()
