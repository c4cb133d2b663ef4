"""The sizes of each scale of ``neural-estimator reproduce``.

``paper`` is the paper's protocol ("Evaluation Protocol": three independent evaluation sets of
8,000 trajectories at the scenario's horizon; batch-1 throughput). ``small`` fits one 2-core
machine with the shipped models (one instance each) and reduced sets. ``smoke`` runs every
experiment on tiny sizes, for the test suite: its numbers say the pipeline works, nothing about
the methods.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any


class ScaleError(ValueError):
    """An unknown scale name."""


@dataclass(frozen=True)
class Scale:
    name: str
    trajectories: int  # per evaluation set
    sets: int  # independent evaluation sets (paper: 3)
    horizon: int | None  # steps per trajectory; None: the scenario's (paper: 500, quadrotor 200)
    noise_scales: tuple[float, ...]  # observation-noise multipliers of the robustness sweep (1.0 = nominal)
    noise_trajectories: int  # per set in the noise sweep
    noise_sets: int
    runtime_steps: int  # timed batch-1 steps per method and scenario
    runtime_warmup: int  # untimed steps first (allocations, lazy initialisation)
    seed: int = 0  # of the evaluation sets' streams and the filters' draws
    notes: tuple[str, ...] = field(default_factory=tuple)

    def settings(self) -> dict[str, Any]:
        return asdict(self)


SCALES: dict[str, Scale] = {
    "smoke": Scale("smoke", trajectories=4, sets=2, horizon=20, noise_scales=(0.5, 1.0, 2.0), noise_trajectories=4,
                   noise_sets=2, runtime_steps=20, runtime_warmup=3,
                   notes=("tiny sizes: checks that every experiment runs, not what the methods achieve",)),
    "small": Scale("small", trajectories=200, sets=3, horizon=None, noise_scales=(0.5, 1.0, 2.0, 4.0),
                   noise_trajectories=100, noise_sets=3, runtime_steps=500, runtime_warmup=20,
                   notes=("shipped models, one instance per architecture", "reduced evaluation sets")),
    "paper": Scale("paper", trajectories=8000, sets=3, horizon=None, noise_scales=(0.5, 1.0, 2.0, 4.0, 8.0),
                   noise_trajectories=8000, noise_sets=3, runtime_steps=2000, runtime_warmup=50,
                   notes=("the paper's evaluation sizes; its noise levels are not published: ours are 0.5x to 8x",
                          "training the 15 instances per pair is not yet part of reproduce: shipped models are used")),
}


def get_scale(name: str) -> Scale:
    if name not in SCALES:
        raise ScaleError(f"unknown scale {name!r}; choose one of: {', '.join(SCALES)}")
    return SCALES[name]
