"""Write a recording of a ground robot made of standard ROS 2 messages only (the worked example of
docs/robot.md).

A unicycle robot drives on a plane (position x, y, heading yaw, speed v, turn rate w; v and w
wander as Ornstein-Uhlenbeck processes, the robot turns back towards the origin when it strays).
The recording holds what a real robot's bag holds:

    /imu                  sensor_msgs/msg/Imu             100 Hz  gyro z (noise 0.02 rad/s, bias 0.01), accel x
    /wheel_odom           nav_msgs/msg/Odometry            50 Hz  wheel speed (noise 0.05 m/s, 3 % scale error)
    /gps/fix              geometry_msgs/msg/PointStamped   5 Hz   position (noise 0.5 m)
    /mocap/pose           geometry_msgs/msg/PoseStamped   100 Hz  ground truth: x, y, yaw (quaternion)
    /odometry/filtered    nav_msgs/msg/Odometry            50 Hz  "the robot's own filter": dead reckoning
                                                                  corrected towards each GPS fix (gain 0.2)

Each run is separated from the next by a 2-second gap without messages, so the dataset builder
cuts the bag into one segment per run. ``--truth-gaps S`` makes the ground truth partial: in each
run the robot leaves the motion-capture volume for S seconds from 40 % of the run (no
/mocap/pose messages then; every other topic goes on), as a lab's volume does; the dataset then
marks those steps unlabelled (docs/robot.md, "Partial ground truth").

Written with rosbags' rosbag2 writer (MCAP storage, or sqlite3 with ``--storage sqlite3``), i.e. by
another tool than this package's own bag writer.

    python examples/robot_bag.py --out runs/robot_bag --runs 6 --seconds 120
    neural-estimator dataset runs/robot_bag --spec examples/robot_spec.yaml --length 200 --out runs/robot.npz
"""

from __future__ import annotations

import argparse
import math
import shutil
import sys
from pathlib import Path

import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

TS = get_typestore(Stores.ROS2_JAZZY)
T = TS.types
DT = 0.01  # simulation step [s] (100 Hz)


def quaternion(yaw: float):
    return T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))


def header(t_ns: int, frame: str):
    return T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=t_ns // 10**9, nanosec=t_ns % 10**9), frame_id=frame
    )


def vec3(x=0.0, y=0.0, z=0.0):
    return T["geometry_msgs/msg/Vector3"](x=float(x), y=float(y), z=float(z))


def odometry(t_ns: int, x: float, y: float, yaw: float, v: float, w: float):
    pose = T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=0.0), orientation=quaternion(yaw)
    )
    twist = T["geometry_msgs/msg/Twist"](linear=vec3(v), angular=vec3(z=w))
    return T["nav_msgs/msg/Odometry"](
        header=header(t_ns, "odom"),
        child_frame_id="base_link",
        pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)),
    )


def simulate_run(rng: np.random.Generator, seconds: float) -> np.ndarray:
    """(K, 5) true states [x, y, yaw, v, w] at 100 Hz."""
    K = int(round(seconds / DT))
    s = np.zeros((K, 5))
    x, y, yaw, v, w = rng.normal(0, 2), rng.normal(0, 2), rng.uniform(-math.pi, math.pi), 0.5, 0.0
    for k in range(K):
        home = math.atan2(-y, -x) - yaw  # turn back when far from the origin
        pull = 0.3 * math.atan2(math.sin(home), math.cos(home)) * min(1.0, math.hypot(x, y) / 15.0)
        v += 0.5 * (0.8 - v) * DT + 0.3 * math.sqrt(DT) * rng.normal()
        w += 1.0 * (pull - w) * DT + 0.5 * math.sqrt(DT) * rng.normal()
        x += v * math.cos(yaw) * DT
        y += v * math.sin(yaw) * DT
        yaw = math.atan2(math.sin(yaw + w * DT), math.cos(yaw + w * DT))
        s[k] = x, y, yaw, v, w
    return s


def truth_gap(seconds: float, gap: float) -> tuple[float, float]:
    """[start, stop) [s from the run's start] of the run's time outside the motion-capture volume."""
    start = 0.4 * seconds
    return start, min(seconds, start + gap)


def write_bag(out: Path, runs: int, seconds: float, seed: int, storage: str = "mcap", truth_gaps: float = 0.0) -> Path:
    rng = np.random.default_rng(seed)
    if out.exists():
        shutil.rmtree(out)
    plugin = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}[storage]
    with Writer(out, version=9, storage_plugin=plugin) as bag:
        conns = {
            topic: bag.add_connection(topic, msgtype, typestore=TS)
            for topic, msgtype in (
                ("/imu", "sensor_msgs/msg/Imu"),
                ("/wheel_odom", "nav_msgs/msg/Odometry"),
                ("/gps/fix", "geometry_msgs/msg/PointStamped"),
                ("/mocap/pose", "geometry_msgs/msg/PoseStamped"),
                ("/odometry/filtered", "nav_msgs/msg/Odometry"),
            )
        }

        def put(topic, t_ns, msg):
            bag.write(conns[topic], t_ns, TS.serialize_cdr(msg, conns[topic].msgtype))

        t0 = 1_700_000_000 * 10**9
        for run in range(runs):
            s = simulate_run(rng, seconds)
            bias, scale = 0.01 * rng.normal(), 1.0 + 0.03 * rng.normal()
            fx, fy, fyaw = s[0, 0], s[0, 1], s[0, 2]  # the robot's own filter starts at the truth
            gap = truth_gap(seconds, truth_gaps) if truth_gaps > 0 else (math.inf, math.inf)
            for k in range(len(s)):
                x, y, yaw, v, w = s[k]
                t = t0 + int(round(k * DT * 1e9))
                accel = (s[k, 3] - s[k - 1, 3]) / DT if k else 0.0
                if not gap[0] <= k * DT < gap[1]:  # outside the volume: no ground truth (no RNG draw either)
                    put(
                        "/mocap/pose",
                        t,
                        T["geometry_msgs/msg/PoseStamped"](
                            header=header(t, "map"),
                            pose=T["geometry_msgs/msg/Pose"](
                                position=T["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=0.0),
                                orientation=quaternion(yaw),
                            ),
                        ),
                    )
                gyro = w + bias + 0.02 * rng.normal()
                put(
                    "/imu",
                    t,
                    T["sensor_msgs/msg/Imu"](
                        header=header(t, "imu"),
                        orientation=quaternion(0.0),
                        orientation_covariance=np.full(9, -1.0),
                        angular_velocity=vec3(z=gyro),
                        angular_velocity_covariance=np.zeros(9),
                        linear_acceleration=vec3(accel + 0.1 * rng.normal()),
                        linear_acceleration_covariance=np.zeros(9),
                    ),
                )
                if k % 2 == 0:
                    speed = scale * v + 0.05 * rng.normal()
                    put("/wheel_odom", t, odometry(t, 0.0, 0.0, 0.0, speed, gyro))
                    # the robot's own filter: dead reckoning on wheel speed and gyro, pulled to each fix
                    fyaw = math.atan2(math.sin(fyaw + gyro * 2 * DT), math.cos(fyaw + gyro * 2 * DT))
                    fx += speed * math.cos(fyaw) * 2 * DT
                    fy += speed * math.sin(fyaw) * 2 * DT
                if k % 20 == 0:
                    gx, gy = x + 0.5 * rng.normal(), y + 0.5 * rng.normal()
                    put(
                        "/gps/fix",
                        t,
                        T["geometry_msgs/msg/PointStamped"](
                            header=header(t, "map"), point=T["geometry_msgs/msg/Point"](x=float(gx), y=float(gy), z=0.0)
                        ),
                    )
                    fx, fy = fx + 0.2 * (gx - fx), fy + 0.2 * (gy - fy)
                if k % 2 == 0:
                    put("/odometry/filtered", t, odometry(t, fx, fy, fyaw, speed, gyro))
            t0 += int(round((seconds + 2.0) * 1e9))  # a 2 s gap between runs
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default="runs/robot_bag", help="rosbag2 directory to write (replaced)")
    p.add_argument("--runs", type=int, default=6)
    p.add_argument("--seconds", type=float, default=120.0, help="length of each run")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--storage",
        choices=("mcap", "sqlite3"),
        default="mcap",
        help="rosbag2 storage (sqlite3: .db3, the older default)",
    )
    p.add_argument(
        "--truth-gaps",
        type=float,
        default=0.0,
        metavar="S",
        help="partial ground truth: no /mocap/pose for S seconds of each run, from 40 %% of the run",
    )
    a = p.parse_args(argv)
    if not 0.0 <= a.truth_gaps < a.seconds:
        p.error(f"--truth-gaps must be in [0, --seconds) = [0, {a.seconds:g}), got {a.truth_gaps:g}")
    out = write_bag(Path(a.out), a.runs, a.seconds, a.seed, a.storage, a.truth_gaps)
    print(f"{out}: {a.runs} runs x {a.seconds:g} s of /imu, /wheel_odom, /gps/fix, /mocap/pose, /odometry/filtered")
    if a.truth_gaps:
        lo, hi = truth_gap(a.seconds, a.truth_gaps)
        print(f"ground truth (/mocap/pose) missing from {lo:g} s to {hi:g} s of each run")
    return 0


if __name__ == "__main__":
    sys.exit(main())
