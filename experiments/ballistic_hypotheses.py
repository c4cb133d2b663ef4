"""Ballistic hypotheses for the paper's EKF/UKF split: the classic Athans / Julier set-up,
where the filters' prior on the drag coefficient is far from and much wider than the truth's; and
bodies that cross the ground, where the paper's E(a) = min(exp(-k a), 1) has its kink.

    .venv/bin/python experiments/ballistic_hypotheses.py                    # EKF, UKF, EnKF, PF; 100 trajectories

The paper's ballistic EKF (5.29) is 8x its UKF (0.63). Our scenario (the classic problem in km) has
EKF = UKF. In the classic falling-body problem (Athans, Wishner & Bertolini 1968; Julier & Uhlmann
2004) the truth has c = 1e-3 1/ft while the filters start from c = 3e-5 with a standard deviation
of 1e-2: in km (c / 3.048e-4) truth 3.28 1/km, prior 0.098 +- 32.8. The truth here is drawn around
x0 = (91.44 km, 6.096 km/s, c) with a tiny spread; the filters get the separate prior below. Prints
RMSE over the non-diverged trajectories, the median absolute error and the diverged count.

The last two cases keep our constants but sample every 0.5 s or 1 s, so that every body reaches
a = 0 within the 500 steps (median step 153 and 77) and falls on below it at sea-level density:
the EKF's Jacobian of E jumps there (from -k to 0) while the UKF's sigma points straddle the kink.
The two after them put the radar under the flight path (r0 = 0: the range |a - a_ref| has a kink
where every body passes a_ref = 30 km), the second with a 3 km range noise so that the filters are
still uncertain when they reach it.
Output of the default run: experiments/results/ballistic_hypotheses.txt.
"""

from __future__ import annotations

import argparse

import numpy as np

from neural_estimator.data.simulate import simulate
from neural_estimator.methods.registry import make_estimator
from neural_estimator.scenarios import make_scenario

C_TRUE = 3.28  # 1e-3 1/ft in 1/km
TRUTH_CLASSIC = dict(prior_mean=(91.44, 6.096, C_TRUE), prior_std=(0.01, 0.01, 0.001))
CASES = {  # name: (the truth's initial distribution, the filters' prior)
    "classic: filters' c prior 0.098 +- 32.8": (
        TRUTH_CLASSIC,
        dict(prior_mean=(91.44, 6.096, 0.098), prior_std=(0.3048, 0.6096, 32.8)),
    ),
    "classic, c prior 0.098 +- 3.28": (
        TRUTH_CLASSIC,
        dict(prior_mean=(91.44, 6.096, 0.098), prior_std=(0.3048, 0.6096, 3.28)),
    ),
    "our truth, filters' c prior 0.098 +- 1": (
        {},
        dict(prior_mean=(90.0, 6.0, 0.098), prior_std=(0.3048, 1.2192, 1.0)),
    ),
    "our truth, filters' P0 = I (x0 std 1.0)": ({}, dict(prior_std=(1.0, 1.0, 1.0))),
    "every body crosses a = 0 (dt 0.5 s)": (dict(dt=0.5), dict(dt=0.5)),
    "every body crosses a = 0 (dt 1 s)": (dict(dt=1.0), dict(dt=1.0)),
    "range |a - a_ref| (r0 = 0)": (dict(r0=0.0), dict(r0=0.0)),
    "r0 = 0.1 km, range noise 3 km": (dict(r0=0.1, obs_noise_std=3.0), dict(r0=0.1, obs_noise_std=3.0)),
}


def summary(x: np.ndarray, xhat: np.ndarray) -> str:
    err = xhat - x
    ok = np.isfinite(err).all(axis=(1, 2))
    rmse = float(np.sqrt(np.mean(err[ok] ** 2))) if ok.any() else float("nan")
    medae = float(np.median(np.abs(err[ok]))) if ok.any() else float("nan")
    return f"{rmse:.3f} (MedAE {medae:.3f}, diverged {int((~ok).sum())})"


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--methods", default="ekf,ukf,enkf,pf")
    p.add_argument("--trajectories", type=int, default=100)
    p.add_argument("--seed", type=int, default=3)
    args = p.parse_args(argv)
    for name, (truth, prior) in CASES.items():
        # the cases override the constants these hypotheses were written against (preset v3)
        data = simulate(make_scenario("ballistic", preset="v3", **truth), args.trajectories, seed=args.seed)
        filters = make_scenario("ballistic", preset="v3", **prior)
        crossed = float((data.x[:, :, 0].min(axis=1) < 0).mean())
        name += f" [{crossed:.0%} reach a < 0]"
        cells = [
            f"{m.upper()} {summary(data.x, make_estimator(m, filters, seed=0).run(data.y, data.u).x)}"
            for m in args.methods.split(",")
        ]
        print(f"{name}: " + "; ".join(cells), flush=True)


if __name__ == "__main__":
    main()
