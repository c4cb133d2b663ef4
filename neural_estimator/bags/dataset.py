"""A run as arrays <-> a bag: the dataset view of the streams of :mod:`~neural_estimator.stream.messages`.

:func:`bag_to_arrays` gathers every vector message of a bag by its in-band identity (trajectory,
step), whatever order the messages were recorded in, into (N, T, .) arrays; cells without a message
are NaN and counted. :func:`arrays_to_bag` writes simulated data (and optionally estimates) as the
simulator and estimator nodes would publish them: the sample bags in ``bags/`` are made this way.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from neural_estimator.stream import messages as MSG
from neural_estimator.bags.cells import StreamCells
from neural_estimator.bags.errors import BagError, MessageError
from neural_estimator.bags.directory import open_bag
from neural_estimator.bags.writer import DEFAULT_CHUNK_SIZE, LATCHED_QOS, STREAM_QOS, BagWriter


@dataclasses.dataclass
class RunArrays:
    """The streams of one recorded run, keyed by (trajectory, step).

    Rows are the trajectory indices in ``trajectories`` (sorted); column k is step k. Cells that no
    message filled are NaN (stamps: -1).
    """

    description: dict[str, Any]  # scenario.describe() plus "run" (seed, trajectories, horizon, ...)
    trajectories: np.ndarray  # (N,) trajectory indices
    x: np.ndarray  # (N, T, dx) ground truth x_k
    y: np.ndarray  # (N, T, dy) observations y_k
    u_prev: np.ndarray  # (N, T, du) u_{k-1} as the observations carry it (0 at k = 0)
    stamps: np.ndarray  # (N, T) int64 observation stamps (ns)
    x_hat: dict[str, np.ndarray]  # {method: (N, T, dx)}
    P_hat: dict[str, np.ndarray]  # {method: (N, T, dx, dx)} where published
    received: dict[str, int]  # valid messages per stream ("observation", "estimates/ukf", ...)
    missing: dict[str, int]  # (trajectory, step) cells without a message, per stream
    duplicates: dict[str, int]  # messages repeating a cell already filled (the last one is kept)
    rejected: dict[str, int]  # messages that did not fit the layout (wrong names, malformed)
    status: list[dict[str, Any]]  # run_status messages in order
    present: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)  # {stream: (N, T) bool}
    outside: dict[str, int] = dataclasses.field(default_factory=dict)  # identities outside the announced run

    @property
    def scenario(self):
        """The scenario, rebuilt from the recorded description."""
        from neural_estimator.scenarios import scenario_from_description

        return scenario_from_description(self.description)

    @property
    def methods(self) -> list[str]:
        return sorted(self.x_hat)

    @property
    def u(self) -> np.ndarray:
        """(N, T, du) controls u_k in dataset convention: u[:, k] = u_prev[:, k + 1].

        The last control of a trajectory is never sent (no estimator uses it) and is 0 here.
        """
        u = np.zeros_like(self.u_prev)
        u[:, :-1] = self.u_prev[:, 1:]
        return u

    @property
    def complete(self) -> bool:
        """True when the run announced its end (run_status "complete")."""
        return any(s.get("status") == MSG.STATUS_COMPLETE for s in self.status)


def _stream_key(role: MSG.TopicRole) -> str:
    if role.kind == "estimate":
        return MSG.estimate_topic(role.method)
    if role.kind == "covariance":
        return MSG.covariance_topic(role.method)
    return role.kind


def bag_to_arrays(path: str | Path, *, namespace: str = "/", description: Mapping[str, Any] | None = None) -> RunArrays:
    """Read a recorded run into arrays.

    Args:
        path: the ``.mcap`` bag or rosbag2 directory (a damaged one is recovered as far as possible, see
            :class:`~neural_estimator.bags.reader.BagReader`).
        namespace: the namespace the streams were published in.
        description: the scenario description to use when the bag has no ``scenario`` message.

    Raises:
        BagError: no scenario description, or a stream topic holding a different message type.
    """
    desc, status, cells, rejected = _read_streams(path, namespace, description)
    traj_ids, N, T, outside = _rows(path, desc, cells)
    dx, dy = len(desc["state_names"]), len(desc["obs_names"])
    du = len(desc.get("control_names", ()))
    ids = np.asarray(traj_ids, dtype=np.int64)

    def fill(key: str, width: int) -> np.ndarray:
        out = np.full((N, T, width), np.nan)
        store = cells.get(key)
        if store is not None and len(store.n):
            out[np.searchsorted(ids, store.n), store.k] = store.values
        return out

    obs = fill(MSG.OBSERVATION, dy + du)
    stamps = np.full((N, T), -1, dtype=np.int64)
    if MSG.OBSERVATION in cells:
        store = cells[MSG.OBSERVATION]
        stamps[np.searchsorted(ids, store.n), store.k] = store.stamps
    x_hat, P_hat = {}, {}
    for key in cells:
        if not key.startswith(MSG.ESTIMATES + "/"):
            continue
        method = key.split("/")[1]
        if key.endswith("/" + MSG.COVARIANCE_SUFFIX):
            P_hat[method] = fill(key, dx * dx).reshape(N, T, dx, dx)
        else:
            x_hat[method] = fill(key, dx)
    total = N * T
    streams = set(cells) | {MSG.OBSERVATION, MSG.GROUND_TRUTH}
    present = {}
    for key in sorted(streams):
        mask = np.zeros((N, T), dtype=bool)
        if key in cells:
            mask[np.searchsorted(ids, cells[key].n), cells[key].k] = True
        present[key] = mask
    received = {k: c.messages - outside.get(k, 0) for k, c in cells.items()}
    return RunArrays(
        description=desc,
        trajectories=np.asarray(traj_ids, dtype=np.int64),
        x=fill(MSG.GROUND_TRUTH, dx),
        y=obs[..., :dy],
        u_prev=obs[..., dy:],
        stamps=stamps,
        x_hat=x_hat,
        P_hat=P_hat,
        received={k: received.get(k, 0) for k in sorted(streams)},
        missing={k: total - (len(cells[k].n) if k in cells else 0) for k in sorted(streams)},
        duplicates={k: c.duplicates for k, c in cells.items() if c.duplicates},
        rejected=rejected,
        status=status,
        present=present,
        outside=outside,
    )


def _read_streams(
    path: str | Path, namespace: str, description: Mapping[str, Any] | None, store=StreamCells
) -> tuple[dict[str, Any], list[dict[str, Any]], dict[str, StreamCells], dict[str, int]]:
    """(scenario description, run statuses, the cells of each vector stream, rejected messages per
    stream) of a bag: every topic of the run checked for its message type. Stream messages are
    decoded as they are read (held raw only until the bag's first /scenario message, when that
    comes after them), into compact :class:`~neural_estimator.bags.cells.StreamCells`, or what
    ``store(width)`` makes (:class:`~neural_estimator.bags.spilled_cells.SpilledCells`: on disk)."""
    with open_bag(path) as bag:
        roles = {}
        for topic, conn in bag.topics.items():
            role = MSG.topic_role(topic, namespace)
            if role is None:
                continue
            want = MSG.STRING if role.kind in (MSG.SCENARIO, MSG.RUN_STATUS) else MSG.JOINT_STATE
            if conn.msgtype != want:
                raise BagError(f"{path}: topic {topic!r} holds {conn.msgtype}, expected {want}")
            roles[topic] = role
        if not any(r.kind == MSG.OBSERVATION for r in roles.values()) and not any(
            r.kind == MSG.GROUND_TRUTH for r in roles.values()
        ):
            raise BagError(
                f"{path}: no {MSG.resolve_topic(MSG.OBSERVATION, namespace)} or "
                f"{MSG.resolve_topic(MSG.GROUND_TRUTH, namespace)} topic "
                f"(topics: {', '.join(sorted(bag.topics)) or 'none'})"
            )

        desc: dict[str, Any] | None = dict(description) if description is not None else None
        status: list[dict[str, Any]] = []
        rejected: dict[str, int] = {}
        pending: list[tuple[str, bytes]] = []  # stream messages before the description is known
        decoder: _CellDecoder | None = None if desc is None else _CellDecoder(desc, rejected, store)
        for conn, _, raw in bag.messages(list(roles)):
            role = roles[conn.topic]
            key = _stream_key(role)
            try:
                if role.kind == MSG.SCENARIO:
                    if desc is None:  # the first announcement defines the run: a later one cannot resize it
                        desc = MSG.decode_scenario(raw)
                        decoder = _CellDecoder(desc, rejected, store)
                        for item in pending:
                            decoder.add(*item)
                        pending = []
                    continue
                if role.kind == MSG.RUN_STATUS:
                    status.append(MSG.decode_run_status(raw))
                    continue
                if decoder is None:
                    pending.append((key, bytes(raw)))
                else:
                    decoder.add(key, raw)
            except MessageError:
                rejected[key] = rejected.get(key, 0) + 1
    if desc is None or decoder is None:
        raise BagError(
            f"{path}: no {MSG.resolve_topic(MSG.SCENARIO, namespace)} message: name the scenario "
            "(--scenario NAME [--set ...] on the command line, -p scenario:=NAME on a node)"
        )
    return desc, status, {k: c.finish() for k, c in decoder.cells.items()}, rejected


class _CellDecoder:
    """Decodes stream messages into each stream's :class:`StreamCells`; a message that does not
    decode, or names other components than its stream's, counts as rejected."""

    def __init__(self, desc: dict[str, Any], rejected: dict[str, int], store=StreamCells) -> None:
        dx = len(desc["state_names"])
        self.store = store
        self.expected = {MSG.OBSERVATION: MSG.observation_labels(desc), MSG.GROUND_TRUTH: MSG.state_labels(desc)}
        self.state_names, self.cov_names = MSG.state_labels(desc), MSG.covariance_labels(dx)
        self.rejected = rejected
        self.codecs: dict[str, MSG.VectorCodec] = {}
        self.cells: dict[str, StreamCells] = {}

    def add(self, key: str, raw: bytes | memoryview) -> None:
        codec = self.codecs.get(key)
        if codec is None:
            if key.startswith(MSG.ESTIMATES + "/"):
                names = self.cov_names if key.endswith("/" + MSG.COVARIANCE_SUFFIX) else self.state_names
            else:
                names = self.expected[key]
            codec = self.codecs[key] = MSG.VectorCodec("", names)
        try:
            vec = codec.decode(raw)
        except MessageError:
            self.rejected[key] = self.rejected.get(key, 0) + 1
            return
        if vec.names != codec.names:
            self.rejected[key] = self.rejected.get(key, 0) + 1
            return
        store = self.cells.get(key)
        if store is None:
            store = self.cells[key] = self.store(len(codec.names))
        store.add(vec.trajectory, vec.step, vec.stamp_ns, vec.values)


def _rows(path: str | Path, desc: dict[str, Any], cells: dict[str, StreamCells]) -> tuple[list[int], int, int, dict]:
    """(trajectory ids, N, T, cells outside the announced run per stream): the arrays' extent,
    bounded (:func:`max_array_bytes`); cells outside an announced run are dropped."""
    dx, dy = len(desc["state_names"]), len(desc["obs_names"])
    du = len(desc.get("control_names", ()))
    run = desc.get("run") if isinstance(desc.get("run"), Mapping) else {}
    widths = {MSG.OBSERVATION: dy + du, MSG.GROUND_TRUTH: dx}
    for key in cells:
        if key.startswith(MSG.ESTIMATES + "/"):
            widths[key] = dx * dx if key.endswith("/" + MSG.COVARIANCE_SUFFIX) else dx
    cell_bytes = 8 * sum(widths.values()) + 8 + len(widths)  # values, the stamp, a presence flag per stream
    limit = max_array_bytes()
    n_ann, t_ann = _announced(run.get("trajectories")), _announced(run.get("horizon"))
    if n_ann and t_ann and n_ann * t_ann * cell_bytes > limit:
        raise BagError(
            f"{path}: the run announces {n_ann} trajectories x {t_ann} steps: {_gib(n_ann * t_ann * cell_bytes)} "
            f"as arrays, over the bound of {_gib(limit)} ({MAX_ARRAY_ENV})"
        )
    outside: dict[str, int] = {}
    if n_ann and t_ann:  # a cell outside the announced run is a corrupt or forged identity: rejected
        for key, store in cells.items():
            bad = store.drop((store.n >= 0) & (store.n < n_ann) & (store.k >= 0) & (store.k < t_ann))
            if bad:
                outside[key] = bad
    # Rows: every trajectory announced by the run (so that a wholly lost one counts as missing)
    # and every one that was received.
    traj_ids = np.union1d(np.concatenate([np.zeros(0, np.int64), *(c.n for c in cells.values())]), np.arange(n_ann))
    horizon = max([int(c.k.max()) + 1 for c in cells.values() if len(c.k)] + [t_ann])
    N, T = len(traj_ids), horizon
    if N * T * cell_bytes > limit:
        last = _first_at_largest_step(cells)
        raise BagError(
            f"{path}: the streams span {N} trajectories x {T} steps (largest step index {last[1]}, in trajectory "
            f"{last[0]}): {_gib(N * T * cell_bytes)} as arrays, over the bound of {_gib(limit)} ({MAX_ARRAY_ENV}); "
            "a corrupt identity? A /scenario message announcing the run rejects identities outside it"
        )
    return [int(n) for n in traj_ids], N, T, outside


def _first_at_largest_step(cells: dict[str, StreamCells]) -> tuple[int, int]:
    """(trajectory, step) of the first cell to arrive at the largest step, streams in arrival order."""
    top = max([int(c.k.max()) for c in cells.values() if len(c.k)], default=None)
    if top is None:
        return (0, 0)
    for store in cells.values():
        at = np.flatnonzero(store.k == top)
        if len(at):
            i = at[np.argmin(store.first[at])]
            return int(store.n[i]), top
    return (0, top)


def arrays_to_bag(
    path: str | Path,
    scenario: Any,
    x: np.ndarray,
    y: np.ndarray,
    u: np.ndarray | None = None,
    *,
    estimates: Mapping[str, np.ndarray] | None = None,
    covariances: Mapping[str, np.ndarray] | None = None,
    start_ns: int = 0,
    namespace: str = "/",
    run_info: Mapping[str, Any] | None = None,
    overwrite: bool = False,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
) -> Path:
    """Write simulated arrays as a bag of this package's streams.

    Messages are written in the order the simulator publishes them (per step: observation, ground
    truth, then estimates), log time = header stamp = ``start_ns + (n T + k) dt``.

    Args:
        path: output ``.mcap``.
        scenario: the :class:`~neural_estimator.scenarios.Scenario` the data come from.
        x, y, u: (N, T, dx), (N, T, dy), (N, T, du) in dataset convention (u[:, k] = u_k).
        estimates: {method: (N, T, dx)} estimates to add as ``estimates/<method>``.
        covariances: {method: (N, T, dx, dx)} to add as ``estimates/<method>/covariance``.
        start_ns: stamp of step 0 of trajectory 0.
        namespace: namespace of the topics.
        run_info: extra entries of the scenario message's ``"run"`` (e.g. ``seed``).
        overwrite: replace an existing file.
        chunk_size: uncompressed bytes per chunk of the file.
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    N, T = x.shape[:2]
    if x.shape != (N, T, scenario.dx) or y.shape != (N, T, scenario.dy):
        raise BagError(
            f"x and y must be (N, T, {scenario.dx}) and (N, T, {scenario.dy}) for {scenario.name}, "
            f"got {x.shape} and {y.shape}"
        )
    u = np.zeros((N, T, scenario.du)) if u is None else np.asarray(u, dtype=np.float64)
    if u.shape != (N, T, scenario.du):
        raise BagError(f"u must be {(N, T, scenario.du)}, got {u.shape}")
    estimates = dict(estimates or {})
    covariances = dict(covariances or {})
    for m, a in estimates.items():
        if np.shape(a) != x.shape:
            raise BagError(f"estimates[{m!r}] must be {x.shape}, got {np.shape(a)}")
    for m, a in covariances.items():
        if np.shape(a) != (N, T, scenario.dx, scenario.dx):
            raise BagError(f"covariances[{m!r}] must be {(N, T, scenario.dx, scenario.dx)}, got {np.shape(a)}")
    period = MSG.dt_ns(scenario.dt)
    topic = lambda rel: MSG.resolve_topic(rel, namespace)  # noqa: E731
    obs_codec = MSG.VectorCodec(scenario.name, MSG.observation_labels(scenario))
    truth_codec = MSG.VectorCodec(scenario.name, MSG.state_labels(scenario))
    est_codecs = {m: MSG.VectorCodec(m, MSG.state_labels(scenario)) for m in estimates}
    cov_codecs = {m: MSG.VectorCodec(m, MSG.covariance_labels(scenario.dx)) for m in covariances}
    info = {"trajectories": N, "horizon": T, "messages": N * T}
    with BagWriter(path, overwrite=overwrite, chunk_size=chunk_size) as bag:
        bag.add_topic(topic(MSG.SCENARIO), MSG.STRING, qos=[LATCHED_QOS])
        bag.add_topic(topic(MSG.RUN_STATUS), MSG.STRING, qos=[LATCHED_QOS])
        bag.add_topic(topic(MSG.OBSERVATION), MSG.JOINT_STATE, qos=[STREAM_QOS])
        bag.add_topic(topic(MSG.GROUND_TRUTH), MSG.JOINT_STATE, qos=[STREAM_QOS])
        for m in estimates:
            bag.add_topic(topic(MSG.estimate_topic(m)), MSG.JOINT_STATE, qos=[STREAM_QOS])
        for m in covariances:
            bag.add_topic(topic(MSG.covariance_topic(m)), MSG.JOINT_STATE, qos=[STREAM_QOS])
        run = {"start_ns": int(start_ns), "dt_ns": period, "rate_hz": None, **info, **dict(run_info or {})}
        bag.write(topic(MSG.SCENARIO), start_ns, MSG.encode_scenario(scenario.describe(), **run))
        bag.write(topic(MSG.RUN_STATUS), start_ns, MSG.encode_run_status(MSG.STATUS_STARTED, **info))
        stamp = start_ns
        for n in range(N):
            for k in range(T):
                stamp = MSG.step_stamp_ns(start_ns, n * T + k, period)
                u_prev = u[n, k - 1] if k else np.zeros(scenario.du)
                bag.write(
                    topic(MSG.OBSERVATION), stamp, obs_codec.encode(stamp, n, k, np.concatenate([y[n, k], u_prev]))
                )
                bag.write(topic(MSG.GROUND_TRUTH), stamp, truth_codec.encode(stamp, n, k, x[n, k]))
                for m, a in estimates.items():
                    bag.write(topic(MSG.estimate_topic(m)), stamp, est_codecs[m].encode(stamp, n, k, a[n, k]))
                for m, a in covariances.items():
                    bag.write(topic(MSG.covariance_topic(m)), stamp, cov_codecs[m].encode(stamp, n, k, a[n, k]))
        bag.write(topic(MSG.RUN_STATUS), stamp, MSG.encode_run_status(MSG.STATUS_COMPLETE, **info))
    return Path(path)


MAX_ARRAY_ENV = "NEURAL_ESTIMATOR_MAX_ARRAY_GB"
DEFAULT_MAX_ARRAY_GB = 4.0


def max_array_bytes() -> int:
    """The bound on the dense arrays a bag is read into (bytes): ``$NEURAL_ESTIMATOR_MAX_ARRAY_GB``
    GiB (default 4), checked before anything is allocated."""
    import os

    try:
        gb = float(os.environ.get(MAX_ARRAY_ENV, DEFAULT_MAX_ARRAY_GB))
    except ValueError:
        raise BagError(f"{MAX_ARRAY_ENV} must be a number of GiB, got {os.environ[MAX_ARRAY_ENV]!r}") from None
    return int(gb * 2**30)


def _announced(value: Any) -> int:
    """A count of the run announcement (trajectories, horizon): a positive integer, else 0 (unknown)."""
    try:
        v = int(value or 0)
    except (TypeError, ValueError, OverflowError):
        return 0
    return v if v > 0 else 0


def _gib(n: float) -> str:
    return f"{n / 2**30:.1f} GiB"


def scored_methods(
    path, base: np.ndarray, coverage: dict[str, np.ndarray], missing: dict[str, int]
) -> tuple[np.ndarray, list[str], dict[str, str]]:
    """(trajectories scored, methods kept, {method left out: why}): the methods are taken greedily,
    most complete stream first, while each keeps at least half of the trajectories kept so far;
    ``base`` marks the trajectories with complete ground truth (and observations), ``coverage`` each
    method's complete ones among them. BagError when no trajectory is left."""
    common = base.copy()
    kept: list[str] = []
    left_out: dict[str, str] = {}
    for m in sorted(coverage, key=lambda m: (-int(coverage[m].sum()), m)):
        cand = common & coverage[m]
        if cand.any() and 2 * int(cand.sum()) >= int(common.sum()):
            common, kept = cand, kept + [m]
        else:
            left_out[m] = (
                f"its stream is complete on {int(coverage[m].sum())} of {int(base.sum())} "
                "trajectories with complete ground truth"
            )
    if not kept or not common.any():
        raise BagError(
            f"{path}: no trajectory is complete in the ground truth, observations and an estimate stream "
            "(missing cells: " + ", ".join(f"{k} {v}" for k, v in missing.items() if v) + ")"
        )
    return common, kept, left_out


def load_bag_dataset(
    path: str | Path,
    *,
    namespace: str = "/",
    description: Mapping[str, Any] | None = None,
) -> tuple[Any, dict[str, tuple[np.ndarray, np.ndarray | None]], tuple[int, ...]]:
    """A recorded run as the evaluation inputs: ``(truth, {method: (x_hat, P_hat or None)}, angle_states)``.

    ``truth`` is a :class:`~neural_estimator.data.Trajectories` of the trajectories that are
    complete in the ground truth, the observations (when recorded) and every scored estimate
    stream, so that every method is scored on the same trajectories. A method whose stream is
    complete on fewer than half of the trajectories the methods before it (by coverage) share is
    left out rather than shrinking everyone's set; ``truth.meta["bag"]`` records what was
    received, missing, and which trajectories (``left_out``) and methods (``methods_left_out``,
    with the reason) were not scored.

    Args:
        path: a ``.mcap`` bag or a rosbag2 directory.
        namespace: the namespace the streams were published in.
        description: the scenario description for a bag without a ``scenario`` message.

    Raises:
        BagError: as :func:`bag_to_arrays`; when the bag has no estimate stream or no ground truth
            (nothing to score), or when no trajectory is complete in the streams.
    """
    from neural_estimator.data import Trajectories

    run = bag_to_arrays(path, namespace=namespace, description=description)
    est_topic = MSG.resolve_topic(MSG.estimate_topic("<method>"), namespace)
    if not run.x_hat:
        raise BagError(
            f"{path}: no estimate stream ({est_topic}) to score; add one with "
            "`neural-estimator replay BAG --methods ... --out OUT.mcap`"
        )
    if not run.received.get(MSG.GROUND_TRUTH):
        raise BagError(
            f"{path}: no {MSG.resolve_topic(MSG.GROUND_TRUTH, namespace)} messages: "
            "nothing to score the estimates against"
        )
    base = run.present[MSG.GROUND_TRUTH].all(axis=1)
    if run.received.get(MSG.OBSERVATION):
        base &= run.present[MSG.OBSERVATION].all(axis=1)
    coverage = {}
    for m in run.x_hat:  # a diverged estimate (NaN values) is present, not missing
        ok = base & run.present[MSG.estimate_topic(m)].all(axis=1)
        cov_key = MSG.covariance_topic(m)
        if run.received.get(cov_key):
            ok &= run.present[cov_key].all(axis=1)
        coverage[m] = ok
    common, kept, methods_left_out = scored_methods(path, base, coverage, run.missing)
    keep = np.flatnonzero(common)
    meta = dict(run.description)
    meta.update(
        trajectories=int(keep.size),
        horizon=int(run.x.shape[1]),
        bag={
            "path": str(path),
            "trajectory_ids": run.trajectories[keep].tolist(),
            "left_out": run.trajectories[~common].tolist(),
            "methods_left_out": methods_left_out,
            "received": run.received,
            "missing": run.missing,
            "duplicates": run.duplicates,
            "rejected": run.rejected,
            "outside": run.outside,
            "complete": run.complete,
        },
    )
    truth = Trajectories(run.x[keep], run.y[keep], run.u[keep], meta)
    estimates = {m: (run.x_hat[m][keep], run.P_hat[m][keep] if m in run.P_hat else None) for m in sorted(kept)}
    return truth, estimates, tuple(run.description.get("angle_states", ()))


def outside_note(bag_info: Mapping[str, Any]) -> str:
    """One line counting the messages set aside because their (trajectory, step) lies outside the
    run the bag's /scenario announced ('' when none was): a corrupt or forged identity never widens
    the table, and is never dropped without a word."""
    outside = {k: int(n) for k, n in (bag_info.get("outside") or {}).items() if n}
    if not outside:
        return ""
    total = sum(outside.values())
    return (
        f"{total} message{'s' if total != 1 else ''} outside the announced run set aside ("
        + ", ".join(f"{k} {n}" for k, n in sorted(outside.items()))
        + ")"
    )


def left_out_note(bag_info: Mapping[str, Any]) -> str:
    """One line saying what a partly scorable bag left out ('' when nothing was)."""
    parts = []
    left = bag_info.get("left_out") or []
    if left:
        parts.append(
            f"{len(left)} incomplete trajectories left out ({', '.join(map(str, left[:10]))}"
            + (", ..." if len(left) > 10 else "")
            + ")"
        )
    for m, why in (bag_info.get("methods_left_out") or {}).items():
        parts.append(f"method {m} left out: {why}")
    return "; ".join(parts)
