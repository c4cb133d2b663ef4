"""Message fuzzer of the nodes: every subscription and service of every node, random and hostile input.

    .venv/bin/python scripts/fuzz_nodes.py                       # every node x input, 3 s each
    .venv/bin/python scripts/fuzz_nodes.py --seconds 10 --seed 7 --nodes estimator_ekf,evaluator

The nodes are started as ``neural-estimator live`` starts them, in one ROS domain of their own
(``--domain``, else ``ROS_DOMAIN_ID`` when set, else a random one in 200..229; discovery kept to
this machine): an EKF and a GRU estimator node (``bearings``), the lifecycle estimator (configured
and activated by this script), the evaluator (``exit_when_done:=false``, so it stays up after a
run it was told ended), the robot estimator (a GRU this script first trains on a short recording of
examples/robot_bag.py's robot, served on that robot's own sensor topics), and a simulator and a
player, each in a namespace of its own where nobody
subscribes, so they wait (their only inputs are their parameter services). Then, for each node and
each of its inputs (a subscription or a service), for ``--seconds``, this script sends messages
or requests of the input's type drawn at random from families of hostile values:

- vector streams (``observation``, ``ground_truth``, ``estimates/<method>``): well-formed messages
  with extreme floats (NaN, +-inf, +-1e308, 5e-324), identities out of range (negative, 2^53,
  1e308, NaN), stamps at the int32 edges, wrong widths and names, frames ('moon', 10 kB), up to
  200,000 values, and garbage: random bytes, truncated and bit-flipped valid messages;
- JSON streams (``scenario``, ``run_status``): valid announcements with hostile fields (horizon
  10^18, start_ns "x", messages -1 or 1e308, status 5), random JSON, 100,000-deep nesting,
  invalid UTF-8, 900 kB strings;
- the robot's own sensor topics (``/imu``, ``/wheel_odom``, ``/gps/fix``: Imu, Odometry,
  PointStamped): every float field extreme, stamps at the int32 and uint32 edges, foreign and
  10 kB frames, and garbage made from such messages;
- ``set_pose``: poses and covariances with extreme floats, asymmetric or indefinite covariances,
  zero quaternions, foreign frames, and garbage bytes;
- services: lifecycle ``change_state`` with random transition ids (0..255) and labels, in any
  order; ``~/reset``; every node's ``set_parameters`` with random names and values of every
  parameter type (wrong types, extremes, 100 kB strings).

After each (node, input) it checks that the node's process is alive and answers a service call
(``list_parameters``), and classifies the cell from what the node did in that time:
``counted`` (its /diagnostics counters rose), ``refused`` (WARN / ERROR log lines, or service
requests answered success=False), ``alive``
(taken or ignored without a word: a well-formed input) or ``DEAD`` (the process exited, stopped
answering, or logged a traceback). It prints the table node x input -> outcome (messages sent)
and exits 1 if any node died. Only this script and the nodes use rclpy.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import struct
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from neural_estimator.stream import messages as MSG  # noqa: E402
from neural_estimator.nodes.launch import ESTIMATOR, EVALUATOR, isolated_env, node_command, start_node  # noqa: E402
from neural_estimator.scenarios import make_scenario  # noqa: E402

SCENARIO = "bearings"
LIFECYCLE = "neural_estimator.nodes.lifecycle_estimator_node"
SIMULATOR = "neural_estimator.nodes.simulator_node"
PLAYER = "neural_estimator.nodes.player_node"
ROBOT = "neural_estimator.nodes.robot_estimator_node"
EXTREMES = (float("nan"), float("inf"), -float("inf"), 1e308, -1e308, 5e-324, 0.0, -0.0, 1e-300, 2.0**53)
POSE = "geometry_msgs/msg/PoseWithCovarianceStamped"
TS = MSG.TYPESTORE


# ---- hostile messages (CDR bytes, the rosbags type store: no rclpy) -------------------------------------
def _float(rng: random.Random) -> float:
    r = rng.random()
    if r < 0.5:
        return rng.choice(EXTREMES)
    return rng.gauss(0.0, 10.0 ** rng.randint(0, 12))


def _text(rng: random.Random) -> str:
    return rng.choice(["", "map", "moon", "bearings", "ekf", "\u00e9\u4e2d", "x" * 10_000, "/../etc"])


def _garbage(rng: random.Random, valid: bytes) -> bytes:
    kind = rng.randrange(4)
    if kind == 0:
        return bytes(rng.getrandbits(8) for _ in range(rng.randrange(0, 2000)))
    if kind == 1:
        return valid[: rng.randrange(0, len(valid) + 1)]
    b = bytearray(valid)
    for _ in range(rng.randint(1, 8)):
        b[rng.randrange(len(b))] ^= 1 << rng.randrange(8)
    return bytes(b) if kind == 2 else b"\x00\x01\x00\x00" + struct.pack("<I", 0xFFFFFFF0) + bytes(b[8:])


def _joint_state(stamp: tuple[int, int], frame: str, names: list[str], position: np.ndarray) -> bytes:
    msg = TS.types["sensor_msgs/msg/JointState"](
        header=TS.types["std_msgs/msg/Header"](stamp=TS.types["builtin_interfaces/msg/Time"](*stamp), frame_id=frame),
        name=names,
        position=np.asarray(position, dtype=np.float64),
        velocity=np.zeros(0),
        effort=np.zeros(0),
    )
    return bytes(TS.serialize_cdr(msg, "sensor_msgs/msg/JointState"))


def vector_message(rng: random.Random, frame: str, labels: tuple[str, ...]) -> bytes:
    """A hostile message of a vector stream whose valid messages have ``frame`` and ``labels``."""
    n, k = rng.randrange(3), rng.randrange(1000)
    values = np.array([_float(rng) if rng.random() < 0.3 else rng.gauss(0, 50) for _ in labels])
    valid = MSG.encode_vector(MSG.step_stamp_ns(10**18, k, 10**7), frame, n, k, labels, values)
    family = rng.randrange(6)
    if family == 0:
        return valid  # extreme values, valid shape
    stamp = (rng.choice([0, 2**31 - 1, -(2**31), rng.randrange(2**31)]), rng.choice([0, 999_999_999, 2**32 - 1]))
    if family == 1:  # identities out of range
        ident = [rng.choice([-1.0, 2.0**53, 1e308, float("nan"), float(rng.randrange(10**9)), 0.5]) for _ in range(2)]
        return _joint_state(stamp, frame, [*MSG.ID_NAMES, *labels], np.array([*ident, *values]))
    if family == 2:  # wrong width or names, foreign frame
        width = rng.choice([0, 1, len(labels) + 1, 50])
        names = [*MSG.ID_NAMES, *[_text(rng)[:20] or "v" for _ in range(width)]]
        return _joint_state(stamp, _text(rng), names, np.array([n, k, *[_float(rng) for _ in range(width)]]))
    if family == 3:  # a huge array
        width = rng.choice([10_000, 200_000])
        return _joint_state(stamp, frame, [*MSG.ID_NAMES, *["v"] * width], np.zeros(width + 2))
    if family == 4:  # names and positions of different lengths
        return _joint_state(stamp, frame, list(MSG.ID_NAMES), np.zeros(rng.randrange(0, 100)))
    return _garbage(rng, valid)


def json_message(rng: random.Random, valid: dict) -> bytes:
    """A hostile ``std_msgs/String`` JSON message in the shape of ``valid``."""
    family = rng.randrange(6)
    if family == 0:  # a valid object with hostile field values
        obj = json.loads(json.dumps(valid))
        run = obj.setdefault("run", {}) if "scenario" in obj else obj
        keys = ["messages"] if "status" in obj and rng.random() < 0.5 else []  # a "complete" with a bad count
        keys += rng.sample(sorted(set(run) | {"horizon", "start_ns", "messages", "status", "dt_ns"}), 2)
        for key in keys:
            run[key] = rng.choice([-1, 0, 10**18, 10**400, 1e308, "x", None, [], {}, True, 5])
        return MSG.encode_string(json.dumps(obj))
    if family == 1:
        value = rng.choice([[], 5, "x", None, {"status": 5}, {"scenario": 1, "state_names": 2}])
        return MSG.encode_string(json.dumps(value))
    if family == 2:
        depth = rng.choice([1000, 100_000])
        return MSG.encode_string("[" * depth + "]" * depth)
    if family == 3:  # invalid UTF-8 in a String
        body = b"\xff\xfe{" + bytes(rng.getrandbits(8) for _ in range(64)) + b"\x00"
        return b"\x00\x01\x00\x00" + struct.pack("<I", len(body)) + body
    if family == 4:
        return MSG.encode_string(json.dumps({"status": "x" * 900_000}))
    return _garbage(rng, MSG.encode_string(json.dumps(valid)))


def pose_message(rng: random.Random) -> bytes:
    """A hostile ``set_pose`` message (PoseWithCovarianceStamped)."""
    t = TS.types
    cov = np.zeros(36)
    family = rng.randrange(5)
    if family == 1:
        cov = np.array([_float(rng) for _ in range(36)])
    elif family == 2:
        d = np.array([rng.choice([1e308, 1e200, -4.0, 1.0, 1e12]) for _ in range(6)])
        cov = np.diag(d).reshape(-1)
    q = [rng.choice([0.0, 1.0, _float(rng)]) for _ in range(4)]
    msg = t[POSE](
        header=t["std_msgs/msg/Header"](
            stamp=t["builtin_interfaces/msg/Time"](0, 0), frame_id=rng.choice(["map", "map", "moon", ""])
        ),
        pose=t["geometry_msgs/msg/PoseWithCovariance"](
            pose=t["geometry_msgs/msg/Pose"](
                position=t["geometry_msgs/msg/Point"](*[_float(rng) for _ in range(3)]),
                orientation=t["geometry_msgs/msg/Quaternion"](*q),
            ),
            covariance=cov.astype(np.float64),
        ),
    )
    raw = bytes(TS.serialize_cdr(msg, POSE))
    return _garbage(rng, raw) if family == 4 else raw


def _header(rng: random.Random, frame: str):
    t = TS.types
    sec = rng.choice([0, 1_700_000_000, 2**31 - 1, -(2**31), rng.randrange(2**31)])
    nsec = rng.choice([0, 999_999_999, 2**32 - 1, rng.randrange(10**9)])
    return t["std_msgs/msg/Header"](
        stamp=t["builtin_interfaces/msg/Time"](sec, nsec), frame_id=rng.choice([frame, frame, _text(rng)])
    )


def _vec(rng: random.Random, name: str) -> object:
    return TS.types[f"geometry_msgs/msg/{name}"](*[_float(rng) for _ in range(4 if name == "Quaternion" else 3)])


def _cov(rng: random.Random, n: int) -> np.ndarray:
    return np.array([_float(rng) if rng.random() < 0.3 else 0.0 for _ in range(n)], dtype=np.float64)


def robot_message(rng: random.Random, msgtype: str) -> bytes:
    """A hostile message of a robot's own sensor topic (Imu, Odometry or PointStamped, the types of
    examples/robot_bag.py's recording): every float field extreme or random, stamps at the int32 and
    uint32 edges, foreign and 10 kB frames; or garbage made from such a message."""
    t = TS.types
    header = _header(rng, "base_link")
    if msgtype == "sensor_msgs/msg/Imu":
        msg = t[msgtype](
            header=header,
            orientation=_vec(rng, "Quaternion"),
            orientation_covariance=_cov(rng, 9),
            angular_velocity=_vec(rng, "Vector3"),
            angular_velocity_covariance=_cov(rng, 9),
            linear_acceleration=_vec(rng, "Vector3"),
            linear_acceleration_covariance=_cov(rng, 9),
        )
    elif msgtype == "nav_msgs/msg/Odometry":
        pose = t["geometry_msgs/msg/Pose"](position=_vec(rng, "Point"), orientation=_vec(rng, "Quaternion"))
        twist = t["geometry_msgs/msg/Twist"](linear=_vec(rng, "Vector3"), angular=_vec(rng, "Vector3"))
        msg = t[msgtype](
            header=header,
            child_frame_id=_text(rng),
            pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=_cov(rng, 36)),
            twist=t["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=_cov(rng, 36)),
        )
    else:
        msg = t[msgtype](header=header, point=_vec(rng, "Point"))
    raw = bytes(TS.serialize_cdr(msg, msgtype))
    return _garbage(rng, raw) if rng.random() < 0.2 else raw


ROBOT_TOPICS = (  # the spec's observation topics (examples/robot_spec.yaml) and their types
    ("/imu", "sensor_msgs/msg/Imu"),
    ("/wheel_odom", "nav_msgs/msg/Odometry"),
    ("/gps/fix", "geometry_msgs/msg/PointStamped"),
)


def robot_checkpoint(workdir: Path) -> Path:
    """A small GRU trained on a recording of examples/robot_bag.py's robot (dataset + train, as
    docs/robot.md does; one epoch of 16 windows: the node's plumbing, not accuracy)."""
    sys.path.insert(0, str(ROOT / "examples"))
    import robot_bag

    from neural_estimator.cli import main as cli

    out = workdir / "robot-gru"
    if (out / "card.json").is_file():
        return out
    bag = robot_bag.write_bag(workdir / "robot-bag", runs=1, seconds=8.0, seed=4)
    data = workdir / "robot-data.npz"
    data.unlink(missing_ok=True)
    spec = str(ROOT / "examples" / "robot_spec.yaml")
    if cli(["dataset", str(bag), "--spec", spec, "--length", "30", "--out", str(data), "--quiet"]):
        raise SystemExit("could not make the robot dataset")
    args = ["train", "--data", str(data), "--model", "gru", "--out", str(out), "--epochs", "1", "--quiet"]
    if cli(args + ["--windows-per-epoch", "16", "--window", "20", "--warmup", "2", "--val-fraction", "0.5"]):
        raise SystemExit("could not train the robot model")
    return out


# ---- the nodes and their inputs ----------------------------------------------------------------------
class Input(NamedTuple):
    name: str  # the table's column
    kind: str  # "topic" or a service kind ("change_state", "trigger", "parameters")
    target: str  # the topic or service name, relative to the node's namespace
    msgtype: str  # topic type (topics)
    make: Callable[[random.Random], bytes] | None  # topic message generator


class Target(NamedTuple):
    name: str
    module: str
    params: dict
    namespace: str
    inputs: list[Input]


def targets(scen) -> list[Target]:
    desc = scen.describe()
    announce = json.loads(MSG.decode_string(MSG.encode_scenario(desc, trajectories=1, horizon=100, start_ns=10**18)))
    obs = (scen.name, MSG.observation_labels(scen))
    truth = (scen.name, MSG.state_labels(scen))
    est = ("ekf", MSG.state_labels(scen))
    observation = Input("observation", "topic", "observation", MSG.JOINT_STATE, lambda r: vector_message(r, *obs))
    scenario = Input("scenario", "topic", "scenario", MSG.STRING, lambda r: json_message(r, announce))
    params = Input("parameters", "parameters", "", "", None)
    estimator_inputs = [
        observation,
        scenario,
        Input("set_pose", "topic", "set_pose", POSE, pose_message),
        Input("~/reset", "trigger", "reset", "", None),
        params,
    ]
    status = {"status": "complete", "trajectories": 1, "horizon": 100, "messages": 100}
    return [
        Target("estimator_ekf", ESTIMATOR, {"method": "ekf", "scenario": SCENARIO}, "/", estimator_inputs),
        Target("estimator_gru", ESTIMATOR, {"method": "gru", "scenario": SCENARIO}, "/", estimator_inputs),
        Target(
            "lifecycle_estimator",
            LIFECYCLE,
            {"method": "ukf", "scenario": SCENARIO},
            "/",
            [observation, Input("change_state", "change_state", "change_state", "", None), params],
        ),
        Target(
            "evaluator",
            EVALUATOR,
            {"exit_when_done": False, "idle_timeout": 0.0, "completion_timeout": 2.0, "methods": ["ekf"]},
            "/",
            [
                observation,
                Input("ground_truth", "topic", "ground_truth", MSG.JOINT_STATE, lambda r: vector_message(r, *truth)),
                Input("estimates/ekf", "topic", "estimates/ekf", MSG.JOINT_STATE, lambda r: vector_message(r, *est)),
                scenario,
                Input("run_status", "topic", "run_status", MSG.STRING, lambda r: json_message(r, status)),
                params,
            ],
        ),
        Target(
            "robot_estimator",
            ROBOT,
            {"checkpoint": ""},  # filled in by run(): a model trained on a recording (robot_checkpoint)
            "/",
            [Input(topic, "topic", topic, kind, lambda r, k=kind: robot_message(r, k)) for topic, kind in ROBOT_TOPICS]
            + [params],
        ),
        Target("simulator", SIMULATOR, {"scenario": SCENARIO, "wait_timeout": 0.0}, "/fuzz_sim", [params]),
        Target(
            "player",
            PLAYER,
            {"bag": str(ROOT / "bags" / "bearings.mcap"), "wait_for_subscribers": 1, "wait_timeout": 0.0},
            "/fuzz_play",
            [params],
        ),
    ]


def random_parameter(rng: random.Random, names: list[str]):
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue

    v = ParameterValue()
    kind = rng.choice(
        [ParameterType.PARAMETER_BOOL, ParameterType.PARAMETER_INTEGER, ParameterType.PARAMETER_DOUBLE]
        + [ParameterType.PARAMETER_STRING, ParameterType.PARAMETER_STRING_ARRAY, ParameterType.PARAMETER_DOUBLE_ARRAY]
    )
    v.type = kind
    if kind == ParameterType.PARAMETER_BOOL:
        v.bool_value = rng.random() < 0.5
    elif kind == ParameterType.PARAMETER_INTEGER:
        v.integer_value = rng.choice([-(2**63), -1, 0, 2**63 - 1, rng.randrange(10**6)])
    elif kind == ParameterType.PARAMETER_DOUBLE:
        v.double_value = _float(rng)
    elif kind == ParameterType.PARAMETER_STRING:
        v.string_value = _text(rng) if rng.random() < 0.7 else "x" * 100_000
    elif kind == ParameterType.PARAMETER_STRING_ARRAY:
        v.string_array_value = [_text(rng)[:50] for _ in range(rng.randrange(0, 20))]
    else:
        v.double_array_value = [_float(rng) for _ in range(rng.randrange(0, 20))]
    name = rng.choice(names) if names and rng.random() < 0.8 else _text(rng)[:40] or "x"
    return Parameter(name=name, value=v)


# ---- the run -----------------------------------------------------------------------------------------
def _diagnostics_total(status) -> int:
    """The sum of every count among a node's /diagnostics values (what it counted so far)."""
    total = 0
    for kv in status.values:
        if kv.value.isdigit() and kv.key not in ("trajectory", "step", "wake-ups", "estimates published"):
            total += int(kv.value)
    return total


def _warn_lines(log: Path) -> int:
    text = log.read_text(errors="replace") if log.exists() else ""
    return sum(("[WARN]" in line or "[ERROR]" in line) for line in text.splitlines())


def _dead(proc, log: Path) -> str | None:
    if proc.poll() is not None:
        return f"exited {proc.returncode}"
    text = log.read_text(errors="replace") if log.exists() else ""
    if "Traceback" in text or "[FATAL]" in text:
        return "traceback in its log"
    return None


def run(seconds: float, seed: int, only: set[str] | None, domain: int, workdir: Path) -> tuple[list[dict], int]:
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import ChangeState
    from rcl_interfaces.srv import ListParameters, SetParameters
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import JointState
    from std_msgs.msg import String
    from std_srvs.srv import Trigger

    from neural_estimator.nodes.common import latched_qos, stream_qos

    from geometry_msgs.msg import PointStamped
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import Imu

    types = {MSG.JOINT_STATE: JointState, MSG.STRING: String, POSE: PoseWithCovarianceStamped}
    types.update({"sensor_msgs/msg/Imu": Imu, "nav_msgs/msg/Odometry": Odometry})
    types["geometry_msgs/msg/PointStamped"] = PointStamped
    scen = make_scenario(SCENARIO)
    chosen = [t for t in targets(scen) if only is None or t.name in only]
    env = isolated_env(domain)
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = env["ROS_AUTOMATIC_DISCOVERY_RANGE"]
    procs, logs = {}, {}
    for t in chosen:
        params = dict(t.params)
        if t.module == EVALUATOR:
            params["output"] = str(workdir / "fuzz.mcap")
        if t.module == ROBOT:
            params["checkpoint"] = str(robot_checkpoint(workdir))
        cmd = node_command(sys.executable, t.module, t.name, params)
        if t.namespace != "/":
            cmd += ["-r", f"__ns:={t.namespace}"]
        logs[t.name] = workdir / f"{t.name}.log"
        procs[t.name] = start_node(cmd, logs[t.name], env)
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = rclpy.create_node("fuzzer", context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    diag: dict[str, object] = {}

    def on_diag(msg):
        for st in msg.status:
            diag[st.name.split(":")[0].strip().lstrip("/")] = st

    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 100)

    def spin(sec: float) -> None:
        end = time.monotonic() + sec
        while time.monotonic() < end:
            ex.spin_once(timeout_sec=0.01)

    def call(srv_type, name: str, request, timeout: float = 5.0):
        client = node.create_client(srv_type, name)
        try:
            end = time.monotonic() + timeout
            while not client.service_is_ready():
                if time.monotonic() > end:
                    return None
                spin(0.05)
            future = client.call_async(request)
            while not future.done():
                if time.monotonic() > end:
                    return None
                spin(0.02)
            return future.result()
        finally:
            node.destroy_client(client)

    def fq(t: Target, rel: str) -> str:
        ns = "" if t.namespace == "/" else t.namespace
        return f"{ns}/{t.name}/{rel}" if rel else f"{ns}/{t.name}"

    rng = random.Random(seed)
    rows, deaths = [], 0
    try:
        for t in chosen:  # each node up and answering (the lifecycle one configured and active)
            up_by, answer = time.monotonic() + 60.0, None
            # asked again every 5 s: a response the middleware fails to deliver under load ("failed to send
            # response (timeout)" in the node's log) is lost, not late
            while answer is None and time.monotonic() < up_by:
                answer = call(ListParameters, fq(t, "list_parameters"), ListParameters.Request(), 5.0)
            if answer is None:
                raise SystemExit(f"{t.name} did not come up; its log:\n{logs[t.name].read_text(errors='replace')}")
            if t.module == LIFECYCLE:
                for tid in (Transition.TRANSITION_CONFIGURE, Transition.TRANSITION_ACTIVATE):
                    call(ChangeState, fq(t, "change_state"), ChangeState.Request(transition=Transition(id=tid)), 60.0)
        pubs = {}
        for t in chosen:
            names = call(ListParameters, fq(t, "list_parameters"), ListParameters.Request())
            names = list(names.result.names) if names is not None else []
            for inp in t.inputs:
                sent, answered_no, log0 = 0, 0, _warn_lines(logs[t.name])
                key = t.name  # /diagnostics status names start with the node's name
                diag0 = _diagnostics_total(diag[key]) if key in diag else 0
                if inp.kind == "topic" and (inp.target, inp.msgtype) not in pubs:
                    # the QoS the node's own publishers offer on that topic (JSON streams are latched)
                    qos = latched_qos() if inp.msgtype == MSG.STRING else stream_qos(100, transient_local=False)
                    pubs[(inp.target, inp.msgtype)] = node.create_publisher(types[inp.msgtype], inp.target, qos)
                    spin(2.0)  # discovery: the estimator subscribes when a publisher appears
                end = time.monotonic() + seconds
                while time.monotonic() < end and procs[t.name].poll() is None:
                    if inp.kind == "topic":
                        pubs[(inp.target, inp.msgtype)].publish(inp.make(rng))
                        spin(0.005)
                    elif inp.kind == "change_state":
                        tr = Transition(id=rng.randrange(256))
                        if rng.random() < 0.3:
                            tr.label = rng.choice(["configure", "activate", "cleanup", "shutdown", "x", ""])
                        resp = call(ChangeState, fq(t, "change_state"), ChangeState.Request(transition=tr), 2.0)
                        answered_no += resp is not None and not resp.success
                    elif inp.kind == "trigger":
                        resp = call(Trigger, fq(t, "reset"), Trigger.Request(), 2.0)
                        answered_no += resp is not None and not resp.success
                    else:
                        req = SetParameters.Request(parameters=[random_parameter(rng, names) for _ in range(3)])
                        resp = call(SetParameters, fq(t, "set_parameters"), req, 2.0)
                        answered_no += resp is not None and not all(r.successful for r in resp.results)
                    sent += 1
                spin(1.5)  # the node's diagnostics window and log catch up
                why = _dead(procs[t.name], logs[t.name])
                if why is None and call(ListParameters, fq(t, "list_parameters"), ListParameters.Request()) is None:
                    why = "stopped answering"
                counted = key in diag and _diagnostics_total(diag[key]) > diag0
                refused = _warn_lines(logs[t.name]) - log0
                refused = max(refused, answered_no)  # requests answered success=False, or the lines they logged
                outcome = f"DEAD ({why})" if why else "counted" if counted else "refused" if refused else "alive"
                deaths += bool(why)
                rows.append({"node": t.name, "input": inp.name, "outcome": outcome, "sent": sent, "refusals": refused})
                print(f"{t.name:20s} {inp.name:14s} {outcome:10s} {sent:6d} sent, {refused} refusals", flush=True)
    finally:
        rclpy.try_shutdown(context=ctx)
        for p in procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for p in procs.values():
            try:
                p.wait(timeout=15)
            except Exception:
                p.kill()
    return rows, deaths


def table(rows: list[dict]) -> str:
    inputs = list(dict.fromkeys(r["input"] for r in rows))
    nodes = list(dict.fromkeys(r["node"] for r in rows))
    cell = {(r["node"], r["input"]): f"{r['outcome']} ({r['sent']})" for r in rows}
    lines = ["| node | " + " | ".join(inputs) + " |", "|---|" + "---|" * len(inputs)]
    for n in nodes:
        lines.append(f"| {n} | " + " | ".join(cell.get((n, i), "") for i in inputs) + " |")
    return "\n".join(lines)


def default_domain() -> int:
    """``ROS_DOMAIN_ID`` when set (other ROS users share the host), else a random one in 200..229."""
    env_domain = os.environ.get("ROS_DOMAIN_ID", "")
    return int(env_domain) if env_domain.isdigit() else random.SystemRandom().randint(200, 229)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=3.0, help="fuzzing time per node and input (default 3)")
    ap.add_argument("--seed", type=int, default=0, help="random seed of the messages (default 0)")
    ap.add_argument("--nodes", default="", help="comma-separated node names (default: all)")
    ap.add_argument("--domain", type=int, default=None, help="ROS domain (default ROS_DOMAIN_ID, else 200..229)")
    ap.add_argument("--out", default="", help="directory for the node logs and the table (default: a temp dir)")
    a = ap.parse_args(argv)
    if a.seconds <= 0:
        ap.error("--seconds must be > 0")
    domain = default_domain() if a.domain is None else a.domain
    workdir = Path(a.out) if a.out else Path(tempfile.mkdtemp(prefix="fuzz_nodes-"))
    workdir.mkdir(parents=True, exist_ok=True)
    only = {n for n in a.nodes.split(",") if n} or None
    print(f"fuzzing in ROS domain {domain}, {a.seconds:g} s per input, seed {a.seed}; logs in {workdir}", flush=True)
    rows, deaths = run(a.seconds, a.seed, only, domain, workdir)
    text = table(rows)
    (workdir / "fuzz_nodes.md").write_text(text + "\n")
    (workdir / "fuzz_nodes.json").write_text(json.dumps(rows, indent=1))
    print(text)
    print(f"{deaths} node deaths in {len(rows)} node x input cells")
    return 1 if deaths else 0


if __name__ == "__main__":
    sys.exit(main())
