"""A recorded run scored in memory that does not grow with the recording's length.

:func:`score_bag` gives what :func:`~neural_estimator.bags.dataset.load_bag_dataset` followed by
:func:`~neural_estimator.metrics.compute_metrics` per method gives (the same trajectories left out,
the same methods left out, the same stream counts, the same figures), without ever holding the run's
arrays:

1. one pass over the bag appends every stream message to that stream's file on disk
   (:class:`~neural_estimator.bags.spilled_cells.SpilledCells`);
2. each stream file is surveyed (messages outside the announced run, trajectories received, the
   largest step) and partitioned into files of ``block`` trajectories;
3. a first pass over the blocks finds which trajectories are complete in which stream (O(N) flags),
   from which the scored trajectories and methods are chosen exactly as load_bag_dataset chooses;
4. a second pass feeds each block's scored trajectories to one
   :class:`~neural_estimator.metrics.streaming.BlockScorer` per method.

Resident memory: one block of trajectories (about :data:`~neural_estimator.metrics.streaming.BLOCK_CELLS`
cells of every stream) plus O(trajectories + horizon). Disk: about the size of the recorded streams,
in a temporary directory removed at the end.
"""

from __future__ import annotations

import dataclasses
import tempfile
from collections.abc import Callable, Mapping
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from neural_estimator.bags import dataset as DS
from neural_estimator.stream import messages as MSG
from neural_estimator.bags.errors import BagError
from neural_estimator.bags.spilled_cells import SpilledCells
from neural_estimator.metrics.paired import TrajectoryErrors
from neural_estimator.metrics.streaming import BlockScorer, block_trajectories


@dataclasses.dataclass
class ScoredRun:
    """What a bag's scoring gives: ``meta`` as load_bag_dataset's ``truth.meta`` (its ``bag``
    entry included), the trajectories scored, their horizon, each kept method's report and
    per-trajectory errors (for the paired statistics)."""

    meta: dict[str, Any]
    n: int
    horizon: int
    dx: int
    warmup: int
    note: str
    reports: dict[str, Any]
    errors: dict[str, TrajectoryErrors]


def score_bag(
    path: str | Path,
    *,
    namespace: str = "/",
    description: Mapping[str, Any] | None = None,
    warmup: int = 10,
    short_runs: str = "error",
    spill_dir: str | None = None,
    check_horizon: Callable[[int], None] | None = None,
) -> ScoredRun:
    """Score every estimate stream of a bag in bounded memory (module docstring). ``warmup`` and
    ``short_runs`` as :func:`~neural_estimator.evaluation.bag_report.evaluate_bag`; ``check_horizon(T)``,
    called once the run's horizon is known and before anything is scored, may raise (the
    ``metrics`` verb's own message for a warm-up too long).

    Raises:
        BagError: as load_bag_dataset; a trajectory's steps too many for the array bound; no room
            for the temporary files.
        MetricsError: a warm-up that leaves no step ("error"), non-finite ground truth.
    """
    where = spill_dir or tempfile.gettempdir()
    try:
        with tempfile.TemporaryDirectory(prefix="neural-estimator-score-", dir=spill_dir) as tmp:
            store = partial(SpilledCells, directory=tmp)
            desc, status, cells, rejected = DS._read_streams(path, namespace, description, store)
            layout = _Layout(path, desc, cells)
            run = _Completeness(layout, cells, status, rejected)
            if check_horizon is not None:
                check_horizon(layout.horizon)
            return _score(path, namespace, layout, run, cells, warmup, short_runs, tmp)
    except OSError as exc:  # a full or read-only temporary directory: one line, the bag untouched
        raise BagError(
            f"{path}: scoring needs temporary files in {where} (about the size of the recording; "
            f"set TMPDIR to another directory): {exc.strerror or exc}"
        ) from None


class _Layout:
    """The run's extent (trajectory ids, horizon), as DS._rows finds it, and each stream's files
    partitioned into blocks of trajectories."""

    def __init__(self, path, desc: dict[str, Any], cells: dict[str, SpilledCells]) -> None:
        self.desc = desc
        self.dx = len(desc["state_names"])
        run = desc.get("run") if isinstance(desc.get("run"), Mapping) else {}
        n_ann, t_ann = DS._announced(run.get("trajectories")), DS._announced(run.get("horizon"))
        self.outside: dict[str, int] = {}
        limit = DS.max_array_bytes()
        # What scoring holds per trajectory, whatever the horizon: its id, a completeness flag per
        # stream, and per scored method its per-component MSE and a few sums and counts
        # (metrics/streaming.py: 18 values besides the dx MSEs).
        per_trajectory = 8 + len(cells) + 8 * (self.dx + 18) * len(cells)
        if n_ann * per_trajectory > limit:
            raise BagError(
                f"{path}: the run announces {n_ann} trajectories: {DS._gib(n_ann * per_trajectory)} to score them, "
                f"over the bound of {DS._gib(limit)} ({DS.MAX_ARRAY_ENV})"
            )
        ids, top = [np.arange(n_ann, dtype=np.int64)], -1
        for key, store in cells.items():
            out, received, last = store.survey(n_ann, t_ann)
            if out:
                self.outside[key] = out
            ids.append(received)
            top = max(top, last)
        self.ids = np.unique(np.concatenate(ids))
        self.horizon = max(top + 1, t_ann)
        width = sum(c.width for c in cells.values()) + self.dx + len(cells) + 2
        if len(self.ids) * per_trajectory > limit or self.horizon * 8 * width > limit:
            # a block of one trajectory must fit, and the per-trajectory figures of all of them
            raise BagError(
                f"{path}: the streams span {len(self.ids)} trajectories x {self.horizon} steps: "
                f"{DS._gib(len(self.ids) * per_trajectory)} to score them and {DS._gib(self.horizon * 8 * width)} "
                f"for one trajectory, over the bound of {DS._gib(limit)} ({DS.MAX_ARRAY_ENV}); a corrupt identity? "
                "A /scenario message announcing the run rejects identities outside it"
            )
        self.block = block_trajectories(self.horizon, self.dx)
        for store in cells.values():
            store.partition(self.block, n_ann, t_ann)
        self.blocks = np.unique(self.ids // self.block)

    def rows(self, b: int) -> np.ndarray:
        """The trajectory ids of block ``b``, sorted."""
        return self.ids[(self.ids // self.block) == b]


def _dense(cells, ids: np.ndarray, horizon: int, width: int) -> np.ndarray:
    """(len(ids), horizon, width) values of a block's resolved cells, NaN where no message came."""
    values = np.full((len(ids), horizon, width), np.nan)
    if len(cells.n):
        values[np.searchsorted(ids, cells.n), cells.k] = cells.values
    return values


class _Completeness:
    """First pass over the blocks: per trajectory, complete in which stream; the stream counts."""

    def __init__(self, layout: _Layout, cells: dict[str, SpilledCells], status, rejected) -> None:
        n, t = len(layout.ids), layout.horizon
        streams = sorted(set(cells) | {MSG.OBSERVATION, MSG.GROUND_TRUTH})
        self.complete = {k: np.zeros(n, dtype=bool) for k in streams}
        distinct = dict.fromkeys(streams, 0)
        duplicates = dict.fromkeys(cells, 0)
        start = 0
        for b in layout.blocks:
            ids = layout.rows(int(b))
            for key, store in cells.items():
                resolved = store.block(int(b))
                present = np.zeros((len(ids), t), dtype=bool)
                present[np.searchsorted(ids, resolved.n), resolved.k] = True
                self.complete[key][start : start + len(ids)] = present.all(axis=1)
                distinct[key] += len(resolved.n)
                duplicates[key] += resolved.duplicates
            start += len(ids)
        received = {k: c.messages - layout.outside.get(k, 0) for k, c in cells.items()}
        self.received = {k: received.get(k, 0) for k in streams}
        self.missing = {k: n * t - distinct[k] for k in streams}
        self.duplicates = {k: v for k, v in duplicates.items() if v}
        self.rejected = rejected
        self.run_complete = any(s.get("status") == MSG.STATUS_COMPLETE for s in status)
        self.methods = sorted(
            k.split("/")[1]
            for k in cells
            if k.startswith(MSG.ESTIMATES + "/") and not k.endswith("/" + MSG.COVARIANCE_SUFFIX)
        )


def _score(
    path, namespace: str, layout: _Layout, run: _Completeness, cells, warmup: int, short_runs: str, tmp: str
) -> ScoredRun:
    """Choose the scored trajectories and methods as load_bag_dataset does, then score them."""
    est_topic = MSG.resolve_topic(MSG.estimate_topic("<method>"), namespace)
    if not run.methods:
        raise BagError(
            f"{path}: no estimate stream ({est_topic}) to score; add one with "
            "`neural-estimator replay BAG --methods ... --out OUT.mcap`"
        )
    if not run.received.get(MSG.GROUND_TRUTH):
        raise BagError(
            f"{path}: no {MSG.resolve_topic(MSG.GROUND_TRUTH, namespace)} messages: "
            "nothing to score the estimates against"
        )
    base = run.complete[MSG.GROUND_TRUTH].copy()
    if run.received.get(MSG.OBSERVATION):
        base &= run.complete[MSG.OBSERVATION]
    coverage = {}
    for m in run.methods:
        ok = base & run.complete[MSG.estimate_topic(m)]
        if run.received.get(MSG.covariance_topic(m)):
            ok &= run.complete[MSG.covariance_topic(m)]
        coverage[m] = ok
    common, kept, methods_left_out = DS.scored_methods(path, base, coverage, run.missing)  # as load_bag_dataset
    note = ""
    if warmup >= layout.horizon and short_runs == "score_all":
        note = f"every step scored: the run has {layout.horizon} steps, not more than the {warmup}-step warm-up"
        warmup = 0
    angles = tuple(layout.desc.get("angle_states", ()))
    dx, t = layout.dx, layout.horizon
    with_cov = {m for m in kept if MSG.covariance_topic(m) in cells}
    scorers = {
        m: BlockScorer(t, dx, angles, warmup=warmup, covariance=m in with_cov, spill_dir=tmp) for m in sorted(kept)
    }
    try:
        start = 0
        for b in layout.blocks:
            ids = layout.rows(int(b))
            rows = common[start : start + len(ids)]
            start += len(ids)
            if not rows.any():
                continue
            x = _dense(cells[MSG.GROUND_TRUTH].block(int(b)), ids, t, dx)[rows]
            for m, scorer in scorers.items():
                xh = _dense(cells[MSG.estimate_topic(m)].block(int(b)), ids, t, dx)[rows]
                P = None
                if m in with_cov:
                    P = _dense(cells[MSG.covariance_topic(m)].block(int(b)), ids, t, dx * dx)[rows]
                    P = P.reshape(-1, t, dx, dx)
                scorer.add(x, xh, P)
        reports = {m: s.report() for m, s in scorers.items()}
        errors = {m: s.trajectory_errors() for m, s in scorers.items()}
    finally:
        for s in scorers.values():
            s.close()
    meta = dict(layout.desc)
    meta.update(
        trajectories=int(common.sum()),
        horizon=t,
        bag={
            "path": str(path),
            "trajectory_ids": layout.ids[common].tolist(),
            "left_out": layout.ids[~common].tolist(),
            "methods_left_out": methods_left_out,
            "received": run.received,
            "missing": run.missing,
            "duplicates": run.duplicates,
            "rejected": run.rejected,
            "outside": layout.outside,
            "complete": run.run_complete,
        },
    )
    return ScoredRun(meta, int(common.sum()), t, dx, warmup, note, reports, errors)
