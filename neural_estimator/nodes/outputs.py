"""The estimators' standard outputs: pose (Odometry or PoseWithCovarianceStamped), state vector, TF.

What nav stacks and viewers read, chosen by parameter (:class:`OutputParams`), all with the
estimate's stamp and the node's ``frame_id`` / ``child_frame_id``:

- ``<output>/odometry``: ``nav_msgs/Odometry`` (``pose_output: odometry`` or ``both``) and/or
  ``<output>/pose``: ``geometry_msgs/PoseWithCovarianceStamped`` (``pose`` or ``both``), where the
  state has a pose (``Scenario.pose_states``; a spec's state named x, y, yaw, ...). The 6x6
  covariance blocks are the method's own P_hat (:mod:`neural_estimator.nodes.odometry`); a method
  without a covariance gets variance :data:`~neural_estimator.nodes.odometry.UNKNOWN_VARIANCE` on
  the diagonal (ROS's "not estimated"), never zeros.
- ``<output>/state``: ``std_msgs/Float64MultiArray``, every method and every scenario: a (dx, 1 + dx)
  row-major matrix whose column 0 is the estimate and columns 1..dx the covariance P_hat; (dx, 1)
  for a method without a covariance (the covariance is left out, not zero-filled).
  ``layout.dim[0].label`` lists the state names (``state:x,y,vx,vy``), ``dim[1].label`` is
  ``mean|covariance`` or ``mean``. The message has no header: its time is the receipt (log) time,
  and it is published right after the stamped estimate it belongs to.
- ``/tf``: ``tf2_msgs/TFMessage`` with one transform ``frame_id -> child_frame_id`` (``publish_tf``).
  ``tf2_msgs`` comes with every ROS 2 install but has no pip wheel: in a pip-only environment
  ``publish_tf:=true`` is refused at start-up in one line.

No rclpy import here: the message classes are passed in, so the arithmetic is testable without ROS.
"""

from __future__ import annotations

import dataclasses
import math
import re
import time
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from neural_estimator.nodes.odometry import POSE_KEYS, block, has_pose, make_odometry, quaternion

POSE_OUTPUTS = ("odometry", "pose", "both", "none")


def _param(default: Any, help: str) -> Any:  # noqa: A002 - the dataclass metadata key of nodes.common.param
    return dataclasses.field(default=default, metadata={"help": help})


@dataclasses.dataclass(frozen=True)
class OutputParams:
    """The output parameters shared by the estimator and robot estimator nodes (params/*.yaml)."""

    pose_output: str = _param(
        "odometry",
        "pose message where the state has a pose: odometry (nav_msgs/Odometry on <output>/odometry), "
        "pose (geometry_msgs/PoseWithCovarianceStamped on <output>/pose), both or none",
    )
    publish_state: bool = _param(
        True, "publish std_msgs/Float64MultiArray [estimate | covariance] on <output>/state (every method)"
    )
    publish_tf: bool = _param(False, "broadcast frame_id -> child_frame_id on /tf (needs tf2_msgs) at every estimate")
    set_pose_topic: str = _param(
        "set_pose", "filters: PoseWithCovarianceStamped topic that restarts the state at a pose ('' = off)"
    )


class OutputError(ValueError):
    """An output parameter cannot be served (one line)."""


# The ceilings of a set_pose message. A position beyond SET_POSE_MAX_ABS metres is not a pose on
# Earth in any frame a robot uses (ECEF coordinates stay below 6.4e6 m); a variance above
# SET_POSE_MAX_VARIANCE (a standard deviation of 1e6 m, or of 1e6 rad) says "unknown", which the
# all-zero covariance (keep the prior P0) says without overflowing the filter's arithmetic.
SET_POSE_MAX_ABS = 1e7
SET_POSE_MAX_VARIANCE = 1e12


def check_output_params(p: OutputParams) -> None:
    if p.pose_output not in POSE_OUTPUTS:
        raise OutputError(f"parameter pose_output must be one of {', '.join(POSE_OUTPUTS)}, got {p.pose_output!r}")


def _stamp(header: Any, stamp_ns: int, frame_id: str) -> None:
    header.stamp.sec, header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
    header.frame_id = frame_id


def make_pose(
    msg_cls, stamp_ns: int, frame_id: str, x: np.ndarray, P: np.ndarray | None, pose_states: Mapping[str, int]
):
    """A ``geometry_msgs/PoseWithCovarianceStamped`` (``msg_cls``) of the estimate's pose block."""
    msg = msg_cls()
    _stamp(msg.header, stamp_ns, frame_id)
    pose, cov = block(x, P, pose_states, POSE_KEYS)
    p = msg.pose.pose
    p.position.x, p.position.y, p.position.z = pose[:3]
    p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w = quaternion(*pose[3:])
    msg.pose.covariance = cov
    return msg


def make_state(msg_cls, dim_cls, x: np.ndarray, P: np.ndarray | None, names: Sequence[str]):
    """A ``std_msgs/Float64MultiArray`` (``msg_cls``, ``dim_cls`` = MultiArrayDimension): the
    (dx, 1 + dx) matrix [x | P], or (dx, 1) = x when ``P`` is None."""
    x = np.asarray(x, dtype=np.float64).reshape(-1)
    n = x.shape[0]
    cols = 1 if P is None else 1 + n
    data = x[:, None] if P is None else np.concatenate([x[:, None], np.asarray(P, dtype=np.float64)], axis=1)
    msg = msg_cls()
    msg.layout.dim = [
        dim_cls(label="state:" + ",".join(names), size=n, stride=n * cols),
        dim_cls(label="mean" if P is None else "mean|covariance", size=cols, stride=cols),
    ]
    msg.layout.data_offset = 0
    msg.data = data.reshape(-1).tolist()
    return msg


class StateEncoder:
    """The CDR bytes of :func:`make_state`'s message, without building a Python message per estimate.

    The layout (labels, sizes) is the same for every estimate of a stream, so its bytes are written
    once per (dx, with covariance); an estimate's message is those bytes, the data's length and the
    data as little-endian float64 (XCDR1 little endian, what rmw serialises; ``rclpy.serialization``
    reads it back as :func:`make_state`'s message: test/test_ros_outputs.py). At Lorenz 96's 40
    states with covariance that is one copy of 1,640 doubles instead of a 1,640-element Python list
    converted in the publish.
    """

    def __init__(self, names: Sequence[str]) -> None:
        self.names = tuple(names)
        self._heads: dict[tuple[int, bool], bytes] = {}

    def _head(self, n: int, cov: bool) -> bytes:
        """Encapsulation, layout and data_offset; the body ends 4-aligned (the data's length follows)."""
        key = (n, cov)
        if key not in self._heads:
            cols = 1 + n if cov else 1
            body = bytearray()
            body += (2).to_bytes(4, "little")  # layout.dim: 2 dimensions
            for label, size, stride in (
                ("state:" + ",".join(self.names), n, n * cols),
                ("mean|covariance" if cov else "mean", cols, cols),
            ):
                text = label.encode() + b"\0"
                body += len(text).to_bytes(4, "little") + text
                body += b"\0" * (-len(body) % 4)
                body += size.to_bytes(4, "little") + stride.to_bytes(4, "little")
            body += (0).to_bytes(4, "little")  # layout.data_offset
            self._heads[key] = b"\0\1\0\0" + bytes(body)
        return self._heads[key]

    def encode(self, x: np.ndarray, P: np.ndarray | None) -> bytes:
        x = np.asarray(x, dtype=np.float64).reshape(-1)
        n = x.shape[0]
        head = self._head(n, P is not None)
        data = np.empty((n, 1 if P is None else 1 + n), dtype="<f8")
        data[:, 0] = x
        if P is not None:
            data[:, 1:] = P
        # the length (uint32), then padding to 8 bytes from the body's start (after the 4-byte encapsulation)
        pad = b"\0" * (-(len(head) - 4 + 4) % 8)
        return b"".join((head, data.size.to_bytes(4, "little"), pad, data.tobytes()))


def read_state(
    data: Sequence[float], dims: Sequence[tuple[str, int]]
) -> tuple[list[str], np.ndarray, np.ndarray | None]:
    """(names, x, P or None) of a state message's ``data`` and ``[(label, size), ...]`` (the inverse of
    :func:`make_state`; for tests and readers of a recording)."""
    (label, n), (_, cols) = dims
    names = label.split(":", 1)[1].split(",") if ":" in label else []
    m = np.asarray(data, dtype=np.float64).reshape(n, cols)
    return names, m[:, 0].copy(), (m[:, 1:].copy() if cols > 1 else None)


def make_transform(msg_cls, stamp_ns: int, frame_id: str, child_frame_id: str, x: np.ndarray, pose_states):
    """A ``geometry_msgs/TransformStamped`` (``msg_cls``) frame_id -> child_frame_id at the estimated pose."""
    msg = msg_cls()
    _stamp(msg.header, stamp_ns, frame_id)
    msg.child_frame_id = child_frame_id
    pose, _ = block(x, None, pose_states, POSE_KEYS)
    t = msg.transform
    t.translation.x, t.translation.y, t.translation.z = pose[:3]
    t.rotation.x, t.rotation.y, t.rotation.z, t.rotation.w = quaternion(*pose[3:])
    return msg


def euler(qx: float, qy: float, qz: float, qw: float) -> tuple[float, float, float]:
    """(roll, pitch, yaw) of a quaternion, R = Rz(yaw) Ry(pitch) Rx(roll) (the inverse of
    :func:`~neural_estimator.nodes.odometry.quaternion`)."""
    norm = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
    if not norm > 0 or not math.isfinite(norm):
        raise OutputError("orientation quaternion has zero or non-finite norm")
    qx, qy, qz, qw = qx / norm, qy / norm, qz / norm, qw / norm
    roll = math.atan2(2 * (qw * qx + qy * qz), 1 - 2 * (qx * qx + qy * qy))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (qw * qy - qz * qx))))
    yaw = math.atan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz))
    return roll, pitch, yaw


def pose_values(msg) -> dict[str, float]:
    """{x, y, z, roll, pitch, yaw} of a ``geometry_msgs/PoseWithCovarianceStamped``."""
    p = msg.pose.pose
    o = p.orientation
    values = dict(zip(POSE_KEYS, (p.position.x, p.position.y, p.position.z, *euler(o.x, o.y, o.z, o.w))))
    if not all(math.isfinite(v) for v in values.values()):
        raise OutputError("pose contains NaN or inf")
    big = [k for k in ("x", "y", "z") if abs(values[k]) > SET_POSE_MAX_ABS]
    if big:
        raise OutputError(f"pose position {', '.join(big)} beyond the ceiling of {SET_POSE_MAX_ABS:g} m")
    return values


def state_at_pose(base: np.ndarray, pose: Mapping[str, float], pose_states: Mapping[str, int]) -> np.ndarray:
    """``base`` (dx,) with the components the scenario maps to a pose replaced by ``pose``'s values."""
    if not has_pose(pose_states):
        raise OutputError("this state has no pose components (Scenario.pose_states is empty)")
    x = np.array(base, dtype=np.float64)
    for key in POSE_KEYS:
        i = pose_states.get(key)
        if i is not None:
            x[i] = pose[key]
    return x


class Outputs:
    """The pose / state / TF publishers of one estimate stream, created on a node (rclpy here only
    through ``node``; message modules imported when a publisher needs them).

    Args:
        node: the rclpy node that publishes.
        p: its :class:`OutputParams`.
        out_topic: the estimate topic (outputs go to ``<out_topic>/odometry``, ``/pose``, ``/state``).
        qos: the QoS profile of the streams.
        frame_id, child_frame_id: the frames of every output.
        state_names: the state's component names (dx).
        pose_states: {pose key: state index} (empty: no pose outputs, no TF).
        publish_odometry: the older on/off switch of the pose output (False = none).
        state_qos: the QoS of the state stream (default ``qos``; its messages hold dx * (dx + 1)
            numbers, so a memory-bounded history is shorter).
    """

    def __init__(
        self,
        node,
        p: OutputParams,
        out_topic: str,
        qos,
        frame_id: str,
        child_frame_id: str,
        state_names: Sequence[str],
        pose_states: Mapping[str, int],
        publish_odometry: bool = True,
        state_qos=None,
    ) -> None:
        check_output_params(p)
        self.frame_id, self.child_frame_id = frame_id, child_frame_id
        self.names = list(state_names)
        self.pose_states = dict(pose_states or {})
        pose_output = p.pose_output if publish_odometry else "none"
        pose = has_pose(self.pose_states)
        self.pub_odom = self.pub_pose = self.pub_state = self.pub_tf = None
        if pose and pose_output in ("odometry", "both"):
            from nav_msgs.msg import Odometry

            self._odom_cls = Odometry
            self.pub_odom = node.create_publisher(Odometry, f"{out_topic}/odometry", qos)
        if pose and pose_output in ("pose", "both"):
            from geometry_msgs.msg import PoseWithCovarianceStamped

            self._pose_cls = PoseWithCovarianceStamped
            self.pub_pose = node.create_publisher(PoseWithCovarianceStamped, f"{out_topic}/pose", qos)
        if p.publish_state:
            from std_msgs.msg import Float64MultiArray, MultiArrayDimension

            self._state_cls, self._dim_cls = Float64MultiArray, MultiArrayDimension
            self._state_encoder = StateEncoder(self.names)
            self.pub_state = node.create_publisher(Float64MultiArray, f"{out_topic}/state", state_qos or qos)
        if p.publish_tf:
            if not pose:
                raise OutputError("publish_tf: the state has no pose components to broadcast")
            try:
                from tf2_msgs.msg import TFMessage
            except ImportError:
                raise OutputError(
                    "publish_tf needs the tf2_msgs package (part of every ROS 2 install, "
                    "apt ros-jazzy-tf2-msgs; it has no pip wheel)"
                ) from None
            from geometry_msgs.msg import TransformStamped

            self._tf_cls, self._transform_cls = TFMessage, TransformStamped
            self.pub_tf = node.create_publisher(TFMessage, "/tf", 100)

    def describe(self) -> str:
        """' + odometry + state' for the start-up log line."""
        pubs = (("odometry", self.pub_odom), ("pose", self.pub_pose), ("state", self.pub_state))
        parts = [n for n, pub in pubs if pub is not None]
        return "".join(f" + {n}" for n in parts) + (" + /tf" if self.pub_tf is not None else "")

    def publish(self, stamp_ns: int, x: np.ndarray, P: np.ndarray | None) -> None:
        """Publish every enabled output of the estimate ``x`` (dx,) with covariance ``P`` (dx, dx) or None."""
        if self.pub_odom is not None:
            self.pub_odom.publish(
                make_odometry(self._odom_cls, stamp_ns, self.frame_id, self.child_frame_id, x, P, self.pose_states)
            )
        if self.pub_pose is not None:
            self.pub_pose.publish(make_pose(self._pose_cls, stamp_ns, self.frame_id, x, P, self.pose_states))
        if self.pub_state is not None:
            self.pub_state.publish(self._state_encoder.encode(x, P))  # serialised bytes: no Python message
        if self.pub_tf is not None and np.all(np.isfinite(x)):
            tf = self._tf_cls()
            tf.transforms = [
                make_transform(self._transform_cls, stamp_ns, self.frame_id, self.child_frame_id, x, self.pose_states)
            ]
            self.pub_tf.publish(tf)


def pose_covariance(msg) -> np.ndarray | None:
    """The 6x6 covariance of a ``geometry_msgs/PoseWithCovarianceStamped`` (x, y, z, roll, pitch,
    yaw), or None when it is all zeros (not given)."""
    cov = np.asarray(msg.pose.covariance, dtype=np.float64).reshape(6, 6)
    if not np.all(np.isfinite(cov)):
        raise OutputError("pose covariance contains NaN or inf")
    if not cov.any():
        return None
    if np.abs(cov).max() > SET_POSE_MAX_VARIANCE:
        raise OutputError(
            f"pose covariance has an entry beyond the ceiling of {SET_POSE_MAX_VARIANCE:g} (all zeros keeps the prior)"
        )
    # below the ceiling the sums and eigenvalues cannot overflow: |entries| <= 1e12 -> |P + P^T| <= 2e12
    if not np.allclose(cov, cov.T, rtol=1e-9, atol=1e-12 * np.abs(cov).max()):
        raise OutputError("pose covariance is not symmetric")
    if np.linalg.eigvalsh(cov)[0] < -1e-9 * np.abs(cov).max():
        raise OutputError("pose covariance is not positive semi-definite")
    return cov


def state_covariance(P0: np.ndarray, pose_cov: np.ndarray | None, pose_states: Mapping[str, int]) -> np.ndarray:
    """The starting covariance of a state set from a pose: P0, with the rows and columns of the
    components the scenario maps to a pose replaced by the pose covariance's (their correlations with
    the other components dropped). ``pose_cov`` None: P0 unchanged."""
    P = np.array(P0, dtype=np.float64)
    if pose_cov is None:
        return P
    pairs = [(i, pose_states[k]) for i, k in enumerate(POSE_KEYS) if k in pose_states]
    for _, j in pairs:
        P[j, :] = 0.0
        P[:, j] = 0.0
    for a, ja in pairs:
        for b, jb in pairs:
            P[ja, jb] = pose_cov[a, b]
    return P


def set_pose(
    estimator,
    pose: Mapping[str, float],
    pose_states: Mapping[str, int],
    last: np.ndarray | None,
    pose_cov: np.ndarray | None = None,
) -> np.ndarray:
    """Restart a filter's stream at ``pose``: the mean is the last estimate (else the prior mean) with
    its pose components replaced; the covariance is the filter's prior P0 with the pose block taken
    from ``pose_cov`` (6x6, robot_localization's order x, y, z, roll, pitch, yaw; None: P0). The next
    observation is then an update of that state (the filters' step k = 0). Returns the new mean.

    Raises:
        OutputError: the method has no state to set (a neural model), the state has no pose, or the
            covariance is not a covariance.
    """
    from neural_estimator.methods.interface import EstimatorError
    from neural_estimator.filters.base import ClassicalFilter

    if not isinstance(estimator, ClassicalFilter):
        raise OutputError(f"set_pose: {type(estimator).__name__} has no state that can be set (filters only)")
    base = last if last is not None and np.all(np.isfinite(last)) else estimator.m0
    mean = state_at_pose(base, pose, pose_states)
    P = state_covariance(estimator.P0, pose_cov, pose_states)
    try:
        estimator.reset(1, initial_mean=mean[None], initial_cov=P[None])
    except EstimatorError as exc:
        estimator.reset(1)  # the stream is not left half-set
        raise OutputError(f"set_pose refused: {exc}") from None
    return mean


def check_pose_frame(frame: str, frame_id: str) -> None:
    """A set_pose message's ``header.frame_id`` must be the node's ``frame_id`` (the estimate's
    frame): the node has no transform to bring a pose from another frame into it, and an empty
    frame is no frame at all."""
    if frame != frame_id:
        raise OutputError(f"set_pose in frame {frame!r}, but this node estimates in frame {frame_id!r}: ignored")


class SetPose:
    """The ``set_pose`` subscription (geometry_msgs/PoseWithCovarianceStamped, robot_localization's
    topic): each message restarts the filter at that pose (:func:`set_pose`). A message that
    cannot be used (a neural method, no pose in the state, another frame, NaN, a zero quaternion, a
    position beyond :data:`SET_POSE_MAX_ABS`, a covariance that is not symmetric positive
    semi-definite or has an entry beyond :data:`SET_POSE_MAX_VARIANCE`) is refused in one WARN line
    and counted, never fatal; the stream is then as it was (or, if the filter refused the state,
    restarted from the prior).

    Args:
        node: the rclpy node.
        topic: the topic ('' = no subscription).
        get_online: returns the node's :class:`~neural_estimator.stream.online.OnlineEstimator` (None while
            the scenario is unknown).
        frame_id: the node's frame: a pose in any other frame is refused.
    """

    def __init__(self, node, topic: str, get_online, frame_id: str) -> None:
        self.node = node
        self.get_online = get_online
        self.frame_id = frame_id
        self.last: np.ndarray | None = None  # the last published estimate (the base of the new mean)
        self.applied = 0
        self.refused = 0
        self._logged: dict[str, float] = {}  # refusal reason -> when it was last logged (monotonic)
        self.sub = None
        if topic:
            from geometry_msgs.msg import PoseWithCovarianceStamped

            self.sub = node.create_subscription(PoseWithCovarianceStamped, topic, self._on_pose, 10)

    def _on_pose(self, msg) -> None:
        online = self.get_online()
        log = self.node.get_logger()
        try:
            if online is None:
                raise OutputError("set_pose before the scenario is known: ignored")
            check_pose_frame(msg.header.frame_id, self.frame_id)
            pose, pose_cov = pose_values(msg), pose_covariance(msg)
            mean = set_pose(online.estimator, pose, getattr(online.scenario, "pose_states", {}), self.last, pose_cov)
        except OutputError as exc:
            self.refused += 1
            text = str(exc) if str(exc).startswith("set_pose") else f"set_pose refused: {exc}"
            # one line per refusal, each reason at most once a second: a flood of bad poses must not
            # flood the log, and one reason must not hide another (the reason: the text without its
            # quoted values, so 'moon' and 'mars' are one reason; a few dozen templates at most)
            now, reason = time.monotonic(), re.sub(r"'[^']*'", "''", text)
            if now - self._logged.get(reason, -1e9) >= 1.0:
                if len(self._logged) >= 64:
                    self._logged.clear()
                self._logged[reason] = now
                log.warning(f"{text} ({self.refused} refused so far)")
            return
        self.applied += 1
        self.last = mean
        where = "the prior P0" if pose_cov is None else "the message's pose block"
        log.info(f"set_pose: state restarted at {np.array2string(mean, precision=4)} (covariance: {where})")


OUTPUT_SUFFIXES = ("odometry", "pose", "state")
TRUTH_ODOMETRY = "ground_truth/odometry"  # the simulator's truth as nav_msgs/Odometry (relative name)


def is_output_topic(topic: str, namespace: str = "/") -> bool:
    """True for ``<ns>/estimates/<method>/{odometry,pose,state}`` and ``<ns>/ground_truth/odometry``
    (what the evaluator records beside the scored streams, for viewers such as Foxglove and pose
    tools such as evo; they are not scored)."""
    ns = "/" + namespace.strip("/")
    if topic == ("" if ns == "/" else ns) + "/" + TRUTH_ODOMETRY:
        return True
    prefix = ("" if ns == "/" else ns) + "/estimates/"
    if not topic.startswith(prefix):
        return False
    parts = topic[len(prefix) :].split("/")
    return len(parts) == 2 and bool(parts[0]) and parts[1] in OUTPUT_SUFFIXES
