"""The result cache of the evaluation protocol: every finished run is written at once, keyed by
everything that defines its result (:func:`run_key`), so an interrupted ``evaluate`` resumes from
the runs it finished and a second one with more methods only computes the new ones."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from neural_estimator import __version__
from neural_estimator import metrics as M
from neural_estimator.data import Trajectories
from neural_estimator.data.io import DataError, load_npz, save_npz
from neural_estimator.data.protocol import SIMULATION_REVISION, code_key
from neural_estimator.data.simulate import trajectories_digest as dataset_digest
from neural_estimator.evaluation.starts import check_init
from neural_estimator.methods import table
from neural_estimator.scenarios import Scenario

if TYPE_CHECKING:
    from neural_estimator.serving.card import Checkpoint

# Part of every cached result's key: bump it when a method's arithmetic or a metric's definition
# changes, so no result computed by older code is reused. 2: paper-matching NRMSE, NEES columns;
# 3: every report carries the every-step RMSE beside the scored one (rmse_every_step); 4: scenario
# presets and the recalibrated defaults (ballistic, quadrotor); 5: per-component RMSE and the
# per-trajectory errors of every run (rmse_components, the paired comparisons).
RESULTS_REVISION = 5
# Options that change how fast a method runs, not what it computes (tested bit-equal): not keyed.
_SPEED_ONLY_OPTIONS = frozenset({"threads"})


def checkpoint_digest(scenario: Scenario, method: str, checkpoint: str | Path | Checkpoint | None) -> str | None:
    """BLAKE2b of a neural method's card and weights (the shipped model's when ``checkpoint`` is
    None; a resolved :class:`~neural_estimator.serving.card.Checkpoint` carries its own); None for
    classical filters. A missing file hashes as "missing" (loading will fail)."""
    if not table.has(method, trainable=True):
        return None
    from neural_estimator.serving import card

    if isinstance(checkpoint, card.Checkpoint):
        return checkpoint.digest
    path = Path(checkpoint) if checkpoint is not None else card.default_checkpoint(scenario.name, method)
    return card.checkpoint_digest(path.parent if path.suffix == ".json" else path)


def run_key(
    scenario: Scenario,
    method: str,
    options: Mapping[str, Any] | None,
    checkpoint_hash: str | None,
    seed: int,
    device: str,
    data: Trajectories | str,
    init: str = "prior",
    warmup: int = 0,
) -> str:
    """Hex digest of everything that defines one run's result.

    Keyed: :data:`RESULTS_REVISION`, the simulation revision, the package version, the scenario
    with all its constants, the method, its options (those that only change the speed, like
    ``threads``, left out), the checkpoint's content hash, the filters' seed, the device, the
    evaluation set's content (:func:`dataset_digest`, or a digest given as a string) and, for
    classical filters, how they start (``init``; neural methods ignore it, so it is not keyed), and a
    plugin scenario's source file (:func:`~neural_estimator.scenarios.code_digest`), and the
    unscored leading steps (``warmup``; keyed only when nonzero, so results of every step made before
    it existed stay valid).
    """
    opts = {k: v for k, v in sorted((options or {}).items()) if k not in _SPEED_ONLY_OPTIONS}
    key = json.dumps(
        {
            "rev": RESULTS_REVISION,
            "sim": SIMULATION_REVISION,
            "version": __version__,
            "scenario": scenario.describe(),
            "method": method,
            "options": opts,
            "checkpoint": checkpoint_hash,
            "seed": int(seed),
            "device": str(device),
            "data": data if isinstance(data, str) else dataset_digest(data),
            **({"init": check_init(init)} if table.has(method, takes_init=True) else {}),
            **({"warmup": int(warmup)} if warmup else {}),
            **code_key(scenario),
        },
        sort_keys=True,
        default=str,
    )
    return hashlib.sha256(key.encode()).hexdigest()[:20]


def result_path(cache_root: Path, scenario: Scenario, method: str, key: str) -> Path:
    return Path(cache_root) / "results" / f"{scenario.name}-{method}-{key}.npz"


_REPORT_ARRAYS = ("rmse_t", "spread", "outlier_idx", "diverged_idx")


def save_run(
    path: Path, report: M.MetricReport, seconds: float, steps: int, errors: M.TrajectoryErrors | None = None
) -> Path:
    """Write one run (its metrics, per-trajectory errors, time and size) as .npz + JSON meta,
    atomically (no pickle)."""
    arrays = {k: np.asarray(getattr(report, k)) for k in _REPORT_ARRAYS}
    if errors is not None:
        arrays.update(trajectory_mse=np.asarray(errors.mse), kept=np.asarray(errors.kept))
    scalars = {
        f.name: getattr(report, f.name)
        for f in M.MetricReport.__dataclass_fields__.values()
        if f.name not in _REPORT_ARRAYS
    }
    meta = {
        "kind": "neural_estimator run result",
        "revision": RESULTS_REVISION,
        "report": scalars,
        "seconds": float(seconds),
        "steps": int(steps),
    }
    return save_npz(path, arrays, meta)  # JSON with allow_nan: inf and NaN survive


def load_run(path: Path) -> tuple[M.MetricReport, float, int, M.TrajectoryErrors] | None:
    """(report, seconds, steps, per-trajectory errors) of a cached run, or None if the file is absent,
    unreadable or lacks the per-trajectory errors (a damaged cache entry is recomputed, never trusted)."""
    if not Path(path).is_file():
        return None
    try:
        arrays, meta = load_npz(path)
        if meta.get("kind") != "neural_estimator run result" or meta.get("revision") != RESULTS_REVISION:
            return None
        fields = dict(meta["report"])
        for key in (
            "rmse_components",
            "coverage_curve",
            "coverage_curve_all",
        ):  # JSON lists back to the report's tuples
            if fields.get(key) is not None:
                fields[key] = tuple(float(v) for v in fields[key])
        report = M.MetricReport(**fields, **{k: arrays[k] for k in _REPORT_ARRAYS})
        errors = M.TrajectoryErrors(np.asarray(arrays["trajectory_mse"], dtype=np.float64), arrays["kept"].astype(bool))
        return report, float(meta["seconds"]), int(meta["steps"]), errors
    except (DataError, KeyError, TypeError, ValueError):
        return None
