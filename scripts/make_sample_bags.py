"""Write the sample bags in bags/: one per scenario, made by the project's own simulator.

Each holds the `scenario`, `observation` and `ground_truth` streams of 2 trajectories (seed 0,
200 steps; rosbag2-layout MCAP) and replays through every method:

    neural-estimator replay bags/lorenz96.mcap --methods ukf,mamba --out /tmp/l96.mcap --metrics

    python scripts/make_sample_bags.py [--scenarios lorenz96,...] [--preset v3] [--trajectories 2] [--horizon 200]

A bag records its scenario's constants, so a bag and the shipped models it replays through must be
made on the same constants. `bags/<scenario>.mcap` is made on the scenario's default constants;
`--preset P` (other than the default) writes `bags/<scenario>-P.mcap`, for the shipped models still
trained on that preset (the card names it; `python scripts/zoo_table.py` lists the shipped cards).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from neural_estimator.bags import arrays_to_bag
from neural_estimator.data import simulate
from neural_estimator.paper import PAPER_SCENARIOS
from neural_estimator.scenarios import default_preset, make_scenario

BAGS = Path(__file__).resolve().parents[1] / "bags"


def sample_bag_path(scenario: str, preset: str | None = None) -> Path:
    """bags/<scenario>.mcap on the default constants, bags/<scenario>-<preset>.mcap on another preset."""
    return BAGS / (
        f"{scenario}.mcap" if preset in (None, "", default_preset(scenario)) else f"{scenario}-{preset}.mcap"
    )


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--trajectories", type=int, default=2)
    p.add_argument("--horizon", type=int, default=200)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--scenarios", default=",".join(PAPER_SCENARIOS), help="comma-separated (default: the paper's five)")
    p.add_argument("--preset", default=None, help="constants preset (default: each scenario's defaults)")
    a = p.parse_args(argv)
    for name in a.scenarios.split(","):
        scenario = make_scenario(name, preset=a.preset)
        T = min(a.horizon, scenario.horizon)
        d = simulate(scenario, a.trajectories, T, a.seed)
        path = arrays_to_bag(
            sample_bag_path(name, a.preset),
            scenario,
            d.x,
            d.y,
            d.u,
            overwrite=True,
            run_info={"seed": a.seed, "trajectories": a.trajectories, "horizon": T},
        )
        print(f"{path}: {a.trajectories} x {T} steps, {path.stat().st_size / 1024:.0f} KiB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
