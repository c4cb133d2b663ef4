"""nav_msgs/Odometry from an estimate, for scenarios that declare a pose (``Scenario.pose_states``).

RViz, robot_localization and nav2 consume ``nav_msgs/Odometry``; the estimator node publishes one
per estimate when the scenario says which state components are the pose and its rates (bearings:
x, y, vx, vy; quadrotor: x, z, pitch and rates). Pose order is ROS's (x, y, z, roll, pitch, yaw),
twist order (vx, vy, vz, wx, wy, wz); the 6x6 covariances are the matching blocks of P_hat.
Components the scenario does not have are 0 with variance :data:`UNKNOWN_VARIANCE` (ROS's way of
saying "not estimated"; robot_localization's two_d_mode ignores them for planar scenarios).
The twist is given in the parent frame's axes (the scenarios' velocities are world-frame).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

POSE_KEYS = ("x", "y", "z", "roll", "pitch", "yaw")
TWIST_KEYS = ("vx", "vy", "vz", "wx", "wy", "wz")
UNKNOWN_VARIANCE = 1e6


def has_pose(pose_states: Mapping[str, int]) -> bool:
    return any(k in pose_states for k in POSE_KEYS)


def quaternion(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """(x, y, z, w) of the rotation R = Rz(yaw) Ry(pitch) Rx(roll)."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
        cr * cp * cy + sr * sp * sy,
    )


def block(x: np.ndarray, P: np.ndarray | None, pose_states: Mapping[str, int], keys: tuple[str, ...]):
    """(6 values, 36 row-major covariance) of ``keys`` from the state and its covariance."""
    idx = [pose_states.get(k) for k in keys]
    values = [float(x[i]) if i is not None else 0.0 for i in idx]
    cov = np.zeros((6, 6))
    for a, i in enumerate(idx):
        for b, j in enumerate(idx):
            if i is not None and j is not None and P is not None:
                cov[a, b] = P[i, j]
        if i is None or P is None:
            cov[a, a] = UNKNOWN_VARIANCE
    return values, cov.reshape(-1).tolist()


def make_odometry(
    msg_cls,
    stamp_ns: int,
    frame_id: str,
    child_frame_id: str,
    x: np.ndarray,
    P: np.ndarray | None,
    pose_states: Mapping[str, int],
):
    """A ``nav_msgs.msg.Odometry`` (``msg_cls``) of the estimate ``x`` (dx,) with covariance ``P``."""
    msg = msg_cls()
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
    msg.header.frame_id = frame_id
    msg.child_frame_id = child_frame_id
    pose, pose_cov = block(x, P, pose_states, POSE_KEYS)
    twist, twist_cov = block(x, P, pose_states, TWIST_KEYS)
    p = msg.pose.pose
    p.position.x, p.position.y, p.position.z = pose[:3]
    q = quaternion(*pose[3:])
    p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w = q
    msg.pose.covariance = pose_cov
    t = msg.twist.twist
    t.linear.x, t.linear.y, t.linear.z = twist[:3]
    t.angular.x, t.angular.y, t.angular.z = twist[3:]
    msg.twist.covariance = twist_cov
    return msg
