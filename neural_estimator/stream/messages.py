"""The message layout of every stream, live on ROS 2 topics and in MCAP bags.

Only standard common_interfaces types are used, so ``ros2 topic echo``, rosbag2, Foxglove and
PlotJuggler read every stream without this package. CDR bytes are produced and parsed with the
rosbags type store of ROS 2 Jazzy (no rclpy here): the nodes publish these bytes as they are
(``Publisher.publish(bytes)``) and record what they receive from raw subscriptions, so a live
stream, a recorded bag and an offline replay carry identical bytes.

Vector streams: ``sensor_msgs/msg/JointState``
-----------------------------------------------
Topic names are relative (``observation``), so that nodes can be namespaced and remapped; bags
store the resolved absolute name (``/observation``, ``/robot1/observation``).

=================================  ====================  =================================================
topic                              header.frame_id       name[2:] (values in position[2:])
=================================  ====================  =================================================
``observation``                    scenario name         ``scenario.obs_names`` (y_k), then
                                                         ``u_prev/<control name>`` (u_{k-1}, zeros at k=0)
                                                         where the scenario has controls
``ground_truth``                   scenario name         ``scenario.state_names`` (x_k)
``estimates/<method>``             method name           ``scenario.state_names`` (x_hat_k)
``estimates/<method>/covariance``  method name           ``P[i,j]``, i, j = 0..dx-1 row-major (P_hat_k)
=================================  ====================  =================================================

Every vector message starts with its identity, carried in-band because messages on different
topics arrive in any order:

- ``name[0] = "trajectory"``, ``position[0]`` = trajectory index n;
- ``name[1] = "step"``, ``position[1]`` = step index k (0-based);
- ``header.stamp`` = simulation time of the step, ``start + (n * T + k) * dt`` for the run's start
  time, horizon T and the scenario's dt (integer nanoseconds; strictly increasing within a run);
  an estimate carries the stamp of the observation it answers;
- ``velocity`` and ``effort`` are empty.

Timing convention (see :mod:`neural_estimator.scenarios.base`): the observation of step k carries
z_k = (y_k, u_{k-1}), exactly what an estimator consumes at step k, so a single message is one
estimator step.

Run streams: ``std_msgs/msg/String`` holding JSON
-------------------------------------------------
- ``scenario``: ``scenario.describe()`` plus ``"run": {"seed", "trajectories", "horizon",
  "rate_hz", "start_ns", "dt_ns", ...}``; published reliable + transient_local so that late
  joiners and the recorder get it. :func:`neural_estimator.scenarios.scenario_from_description`
  rebuilds the scenario from it.
- ``run_status``: ``{"status": "started" | "complete", "trajectories", "horizon", "messages"}``
  so that a recorder knows when the run ended and how many observations to expect.

Everything here is a pure function between arrays and message bytes (or rosbags message
objects); malformed input raises :class:`~neural_estimator.bags.errors.MessageError`.
"""

from __future__ import annotations

import json
import math
import struct
from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np
from rosbags.typesys import Stores, get_typestore

from neural_estimator.stream.errors import MessageError

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)

JOINT_STATE = "sensor_msgs/msg/JointState"
STRING = "std_msgs/msg/String"

OBSERVATION = "observation"
GROUND_TRUTH = "ground_truth"
SCENARIO = "scenario"
RUN_STATUS = "run_status"
ESTIMATES = "estimates"
COVARIANCE_SUFFIX = "covariance"

ID_NAMES = ("trajectory", "step")
CONTROL_PREFIX = "u_prev/"

STATUS_STARTED = "started"
STATUS_COMPLETE = "complete"

_JointState = TYPESTORE.types[JOINT_STATE]
_Header = TYPESTORE.types["std_msgs/msg/Header"]
_Time = TYPESTORE.types["builtin_interfaces/msg/Time"]
_String = TYPESTORE.types[STRING]
_EMPTY = np.zeros(0, dtype=np.float64)
_ZERO8 = bytes(8)  # the empty velocity and effort arrays after position[]
_MAX_INDEX = 2**53  # identities are float64 in position[]: integers are exact below this


# ---- topic names ---------------------------------------------------------------------------------
def estimate_topic(method: str) -> str:
    """Relative topic of a method's estimates, e.g. ``estimates/ukf``."""
    return f"{ESTIMATES}/{method}"


def covariance_topic(method: str) -> str:
    """Relative topic of a method's covariances, e.g. ``estimates/ukf/covariance``."""
    return f"{ESTIMATES}/{method}/{COVARIANCE_SUFFIX}"


def resolve_topic(relative: str, namespace: str = "/") -> str:
    """The absolute name of a relative topic in ``namespace`` (``/`` -> ``/observation``)."""
    ns = "/" + namespace.strip("/")
    return (ns.rstrip("/") + "/" + relative.strip("/")) if ns != "/" else "/" + relative.strip("/")


class TopicRole(NamedTuple):
    """What a topic carries: ``kind`` is observation, ground_truth, scenario, run_status, estimate
    or covariance; ``method`` is set for the last two."""

    kind: str
    method: str | None = None


def topic_role(topic: str, namespace: str = "/") -> TopicRole | None:
    """Classify an absolute topic of this layout under ``namespace``; None for foreign topics."""
    prefix = resolve_topic("", namespace).rstrip("/") + "/"
    if not topic.startswith(prefix):
        return None
    rel = topic[len(prefix) :]
    if rel in (OBSERVATION, GROUND_TRUTH, SCENARIO, RUN_STATUS):
        return TopicRole(rel)
    parts = rel.split("/")
    if parts[0] != ESTIMATES or len(parts) not in (2, 3) or not parts[1]:
        return None
    if len(parts) == 2:
        return TopicRole("estimate", parts[1])
    if parts[2] == COVARIANCE_SUFFIX:
        return TopicRole("covariance", parts[1])
    return None


# ---- labels ----------------------------------------------------------------------------------------
def observation_labels(scenario: Any) -> tuple[str, ...]:
    """Value names of an observation: obs names, then ``u_prev/<control>`` (a Scenario or its
    ``describe()`` dict)."""
    obs, ctl = _names(scenario, "obs_names"), _names(scenario, "control_names")
    return tuple(obs) + tuple(CONTROL_PREFIX + c for c in ctl)


def state_labels(scenario: Any) -> tuple[str, ...]:
    """Value names of ground truth and estimates: the scenario's state names."""
    return tuple(_names(scenario, "state_names"))


def covariance_labels(dx: int) -> tuple[str, ...]:
    """``P[i,j]`` for i, j in 0..dx-1, row-major."""
    return tuple(f"P[{i},{j}]" for i in range(dx) for j in range(dx))


def _names(scenario: Any, key: str) -> Sequence[str]:
    if isinstance(scenario, Mapping):
        return list(scenario.get(key, ()))
    return list(getattr(scenario, key))


# ---- time ------------------------------------------------------------------------------------------
def dt_ns(dt: float) -> int:
    """A sampling period in integer nanoseconds (rounded)."""
    return int(round(float(dt) * 1e9))


def step_stamp_ns(start_ns: int, global_step: int, period_ns: int) -> int:
    """Stamp of the ``global_step``-th step of a run: ``start + global_step * dt`` (integer ns)."""
    return int(start_ns) + int(global_step) * int(period_ns)


def split_ns(t_ns: int) -> tuple[int, int]:
    """(sec, nanosec) of a builtin_interfaces/Time for integer nanoseconds (floor division)."""
    sec, nsec = divmod(int(t_ns), 1_000_000_000)
    return sec, nsec


# ---- vector streams --------------------------------------------------------------------------------
class Vector(NamedTuple):
    """One decoded vector message (any of the JointState streams)."""

    stamp_ns: int
    frame_id: str
    trajectory: int
    step: int
    names: tuple[str, ...]  # value names, identity entries removed
    values: np.ndarray  # (len(names),) float64


def vector_to_message(
    stamp_ns: int, frame_id: str, trajectory: int, step: int, names: Sequence[str], values: Any
) -> Any:
    """A rosbags ``sensor_msgs/msg/JointState`` object of this layout."""
    values = np.asarray(values, dtype=np.float64).reshape(-1)
    if len(names) != values.shape[0]:
        raise MessageError(f"{len(names)} names for {values.shape[0]} values")
    sec, nsec = split_ns(stamp_ns)
    position = np.empty(values.shape[0] + 2, dtype=np.float64)
    position[0], position[1] = trajectory, step
    position[2:] = values
    return _JointState(
        header=_Header(stamp=_Time(sec=sec, nanosec=nsec), frame_id=str(frame_id)),
        name=[*ID_NAMES, *names],
        position=position,
        velocity=_EMPTY,
        effort=_EMPTY,
    )


def encode_vector(stamp_ns: int, frame_id: str, trajectory: int, step: int, names: Sequence[str], values: Any) -> bytes:
    """CDR bytes of a vector message (see the module docstring)."""
    msg = vector_to_message(stamp_ns, frame_id, trajectory, step, names, values)
    return bytes(TYPESTORE.serialize_cdr(msg, JOINT_STATE))


def vector_from_message(msg: Any) -> Vector:
    """Validate a JointState object (rosbags or any object with the same fields) of this layout."""
    names = tuple(msg.name)
    position = np.asarray(msg.position, dtype=np.float64)
    if len(names) != position.shape[0]:
        raise MessageError(f"JointState has {len(names)} names but {position.shape[0]} positions")
    if not names:
        raise MessageError("empty JointState (no names, no positions): not a neural_estimator stream")
    if len(names) < 2 or names[:2] != ID_NAMES:
        raise MessageError(
            f"JointState does not start with the identity entries {list(ID_NAMES)} (got {list(names[:2])}); "
            "not a neural_estimator stream"
        )
    traj, step = float(position[0]), float(position[1])
    for label, v in (("trajectory", traj), ("step", step)):
        if not (math.isfinite(v) and v == int(v) and 0 <= v < _MAX_INDEX):
            raise MessageError(f"{label} index must be a non-negative integer, got {v!r}")
    stamp = msg.header.stamp
    return Vector(
        stamp_ns=int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec),
        frame_id=str(msg.header.frame_id),
        trajectory=int(traj),
        step=int(step),
        names=names[2:],
        values=position[2:],
    )


MAX_JSON_BYTES = 1 << 20  # scenario and run_status messages: a description is a few kB


def decode_vector(raw: bytes | memoryview) -> Vector:
    """Parse CDR bytes of a vector message; anything malformed is a :class:`MessageError`."""
    if not len(raw):
        raise MessageError("empty message (0 bytes)")
    try:
        msg = TYPESTORE.deserialize_cdr(raw, JOINT_STATE)
    except Exception as exc:  # rosbags raises several types for malformed CDR
        raise MessageError(f"cannot parse {len(raw)} bytes as {JOINT_STATE}: {exc}") from None
    return vector_from_message(msg)


def check_labels(vec: Vector, expected: Sequence[str], what: str) -> np.ndarray:
    """The values of ``vec`` after checking its names equal ``expected``; else a clear error."""
    expected = tuple(expected)
    if vec.names != expected:
        if len(vec.names) != len(expected):
            raise MessageError(
                f"{what} has {len(vec.names)} values {list(vec.names)[:8]} but {len(expected)} are expected "
                f"{list(expected)[:8]}"
            )
        wrong = [(a, b) for a, b in zip(vec.names, expected) if a != b]
        raise MessageError(f"{what} has unexpected names (got {wrong[0][0]!r} where {wrong[0][1]!r} is expected)")
    return vec.values


class VectorCodec:
    """Fast CDR encoding and decoding of one vector stream (fixed frame_id and value names).

    The bytes are exactly those of :func:`encode_vector` (the rosbags serializer), written with
    precomputed parts: a few microseconds instead of tens, which matters at kilohertz rates.
    :meth:`decode` takes a fast path when a message has exactly the expected names and falls back
    to :func:`decode_vector` otherwise, so malformed input gets the same clear errors.
    """

    _ENCAPSULATION = b"\x00\x01\x00\x00"  # CDR, little endian

    def __init__(self, frame_id: str, names: Sequence[str]) -> None:
        self.frame_id = str(frame_id)
        self.names = tuple(names)
        frame = _cdr_string(self.frame_id)
        labels = [*ID_NAMES, *self.names]
        block = bytearray(struct.pack("<I", len(labels)))
        for label in labels:
            block += _pad4(len(block)) + _cdr_string(label)
        self._block = bytes(block + _pad4(len(block)) + struct.pack("<I", len(labels)))
        self._n = len(labels)
        # offsets are counted from the end of the 4-byte encapsulation header
        self._prefix_after_stamp = frame + _pad4(8 + len(frame))
        start = 8 + len(self._prefix_after_stamp)
        end = start + len(self._block)
        self._mid = self._prefix_after_stamp + self._block + b"\x00" * ((-end) % 8)
        self._values_at = end + (-end) % 8
        # A valid message of this stream is about _values_at + 8 n bytes; allow other frame_ids and
        # names (the slow path's clear errors) but refuse before decoding anything much larger (a
        # JointState with millions of entries costs time and memory to parse, and is wrong anyway).
        self.max_bytes = 2 * (self._values_at + 8 * self._n) + 65536

    def encode(self, stamp_ns: int, trajectory: int, step: int, values: Any) -> bytes:
        values = np.asarray(values, dtype=np.float64).reshape(-1)
        if values.shape[0] != self._n - 2:
            raise MessageError(f"{len(self.names)} names for {values.shape[0]} values")
        sec, nsec = split_ns(stamp_ns)
        return b"".join(
            (
                self._ENCAPSULATION,
                struct.pack("<iI", sec, nsec),
                self._mid,
                struct.pack("<dd", trajectory, step),
                values.tobytes(),
                b"\x00" * 8,
            )
        )

    def decode_values(self, raw: bytes | memoryview) -> tuple[int, int, int, np.ndarray] | None:
        """(stamp_ns, trajectory, step, values) of a message of exactly this stream's names, with
        ``values`` (n,) float64 (its own aligned, writable copy: the message's bytes put them at an
        address that is not a multiple of 8); nothing else is made (no Vector, no frame_id string:
        the per-message path of the estimator node). None for anything else, which :meth:`decode`
        then decodes or refuses with its clear error."""
        if type(raw) is not bytes:
            raw = bytes(raw)
        if len(raw) > self.max_bytes or not raw.startswith(self._ENCAPSULATION):
            return None
        try:
            sec, nsec, flen = struct.unpack_from("<iII", raw, 4)
        except struct.error:
            return None
        o = 12 + flen  # end of frame_id (offset from the payload start)
        o += (-o) % 4
        if not raw.startswith(self._block, 4 + o):
            return None
        o += len(self._block)
        o += (-o) % 8
        end = o + 8 * self._n
        if len(raw) < 4 + end + 8 or not raw.startswith(_ZERO8, 4 + end):
            return None
        position = np.frombuffer(raw, dtype="<f8", count=self._n, offset=4 + o)
        traj, step = float(position[0]), float(position[1])
        if not (0 <= traj < _MAX_INDEX and 0 <= step < _MAX_INDEX and traj == int(traj) and step == int(step)):
            return None  # NaN fails the range test too
        return sec * 1_000_000_000 + nsec, int(traj), int(step), position[2:].copy()

    def decode(self, raw: bytes | memoryview) -> Vector:
        n_raw = len(raw)
        if n_raw > self.max_bytes:
            raise MessageError(
                f"message of {n_raw} bytes is larger than any valid one of this stream ({len(self.names)} "
                f"values, at most {self.max_bytes} bytes): refused before decoding"
            )
        try:
            if bytes(raw[:4]) == self._ENCAPSULATION:
                sec, nsec, flen = struct.unpack_from("<iII", raw, 4)
                o = 12 + flen  # end of frame_id (offset from the payload start)
                o += (-o) % 4
                if bytes(raw[4 + o : 4 + o + len(self._block)]) == self._block:
                    o += len(self._block)
                    o += (-o) % 8
                    end = o + 8 * self._n
                    if n_raw >= 4 + end + 8 and bytes(raw[4 + end : 4 + end + 8]) == b"\x00" * 8:
                        position = np.frombuffer(raw, dtype="<f8", count=self._n, offset=4 + o)
                        traj, step = float(position[0]), float(position[1])
                        if all(math.isfinite(v) and v == int(v) and 0 <= v < _MAX_INDEX for v in (traj, step)):
                            frame = bytes(raw[16 : 16 + flen - 1]).decode("utf-8", errors="replace")
                            return Vector(
                                sec * 1_000_000_000 + nsec,
                                frame,
                                int(traj),
                                int(step),
                                self.names,
                                position[2:].astype(np.float64),
                            )
        except struct.error:
            pass
        return decode_vector(raw)


def _cdr_string(text: str) -> bytes:
    data = text.encode() + b"\x00"
    return struct.pack("<I", len(data)) + data


def _pad4(n: int) -> bytes:
    return b"\x00" * ((-n) % 4)


def encode_observation(
    scenario: Any, stamp_ns: int, trajectory: int, step: int, y: Any, u_prev: Any | None = None
) -> bytes:
    """Observation message of step k: z_k = (y_k, u_{k-1})."""
    y = np.asarray(y, dtype=np.float64).reshape(-1)
    u_prev = np.zeros(0) if u_prev is None else np.asarray(u_prev, dtype=np.float64).reshape(-1)
    name = scenario["scenario"] if isinstance(scenario, Mapping) else scenario.name
    return encode_vector(stamp_ns, name, trajectory, step, observation_labels(scenario), np.concatenate([y, u_prev]))


def split_observation(vec: Vector, scenario: Any) -> tuple[np.ndarray, np.ndarray]:
    """(y_k (dy,), u_{k-1} (du,)) of a decoded observation, names checked against the scenario."""
    values = check_labels(vec, observation_labels(scenario), "observation")
    dy = len(_names(scenario, "obs_names"))
    return values[:dy], values[dy:]


# ---- run streams -----------------------------------------------------------------------------------
def encode_string(text: str) -> bytes:
    """CDR bytes of a ``std_msgs/msg/String``."""
    return bytes(TYPESTORE.serialize_cdr(_String(data=str(text)), STRING))


def decode_string(raw: bytes | memoryview) -> str:
    """Text of a ``std_msgs/msg/String``."""
    try:
        return str(TYPESTORE.deserialize_cdr(raw, STRING).data)
    except Exception as exc:
        raise MessageError(f"cannot parse {len(raw)} bytes as {STRING}: {exc}") from None


def _decode_json(raw: bytes | memoryview, what: str) -> dict[str, Any]:
    if len(raw) > MAX_JSON_BYTES:
        raise MessageError(f"{what} message of {len(raw)} bytes is larger than the {MAX_JSON_BYTES} accepted: refused")
    text = decode_string(raw)
    try:
        obj = json.loads(text)
    except json.JSONDecodeError as exc:
        raise MessageError(f"{what} message is not JSON: {exc.msg} in {text[:80]!r}") from None
    except RecursionError:  # "[[[[..." nested deeper than the interpreter's stack
        raise MessageError(f"{what} message nests JSON too deeply") from None
    if not isinstance(obj, dict):
        raise MessageError(f"{what} message must be a JSON object, got {type(obj).__name__}")
    return obj


def encode_scenario(description: Mapping[str, Any], **run: Any) -> bytes:
    """The ``scenario`` message: ``scenario.describe()`` with the run info under ``"run"``."""
    return encode_string(json.dumps({**description, "run": run}, sort_keys=True))


def decode_scenario(raw: bytes | memoryview) -> dict[str, Any]:
    """The description dict (with ``"run"``) of a ``scenario`` message, its shape checked.

    Every reader sizes its streams from the name lists and indexes the angle lists, so a message
    whose fields have other types (``{"scenario": 1, "state_names": 2}``) is refused here, as a
    :class:`MessageError`, rather than failing wherever a field is first used."""
    obj = _decode_json(raw, "scenario")
    if "scenario" not in obj or "state_names" not in obj:
        raise MessageError("scenario message lacks 'scenario' / 'state_names': not a scenario description")
    problem = _description_problem(obj)
    if problem:
        raise MessageError(f"scenario message: {problem}: not a scenario description")
    return obj


def _description_problem(obj: Mapping[str, Any]) -> str:
    """What is wrong with the fields of a scenario description ('' when nothing is)."""
    if not isinstance(obj["scenario"], str) or not obj["scenario"]:
        return f"'scenario' must be a non-empty string, got {str(obj['scenario'])[:40]!r}"
    sizes = {}
    for key in ("state_names", "obs_names", "control_names"):
        if key == "obs_names" and key not in obj:
            return "'obs_names' is missing"
        names = obj.get(key, [])
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            return f"{key!r} must be a list of strings"
        sizes[key] = len(names)
    if sizes["state_names"] == 0:
        return "'state_names' is empty"
    for key, size in (("angle_states", sizes["state_names"]), ("angle_obs", sizes["obs_names"])):
        index = obj.get(key, [])
        ok = isinstance(index, list) and all(type(i) is int and 0 <= i < size for i in index)
        if not ok:
            return f"{key!r} must be a list of indices below {size}"
    for key in ("config", "run"):
        if not isinstance(obj.get(key, {}), dict):
            return f"{key!r} must be an object"
    return ""


def encode_run_status(status: str, **info: Any) -> bytes:
    """The ``run_status`` message: ``{"status": ..., **info}``."""
    return encode_string(json.dumps({"status": status, **info}, sort_keys=True))


def decode_run_status(raw: bytes | memoryview) -> dict[str, Any]:
    """The dict of a ``run_status`` message."""
    obj = _decode_json(raw, "run_status")
    if "status" not in obj:
        raise MessageError("run_status message lacks 'status'")
    return obj


__all__ = [
    "COVARIANCE_SUFFIX",
    "CONTROL_PREFIX",
    "ESTIMATES",
    "GROUND_TRUTH",
    "ID_NAMES",
    "JOINT_STATE",
    "OBSERVATION",
    "RUN_STATUS",
    "SCENARIO",
    "STATUS_COMPLETE",
    "STATUS_STARTED",
    "STRING",
    "TYPESTORE",
    "TopicRole",
    "Vector",
    "VectorCodec",
    "check_labels",
    "covariance_labels",
    "covariance_topic",
    "decode_run_status",
    "decode_scenario",
    "decode_string",
    "decode_vector",
    "dt_ns",
    "encode_observation",
    "encode_run_status",
    "encode_scenario",
    "encode_string",
    "encode_vector",
    "estimate_topic",
    "observation_labels",
    "resolve_topic",
    "split_ns",
    "split_observation",
    "state_labels",
    "step_stamp_ns",
    "topic_role",
    "vector_from_message",
    "vector_to_message",
]
