"""The input specification of a robot's recorded data: which message fields make the vectors.

A spec names the observation vector (and optionally the control vector) and the ground-truth state
as fields of messages on topics, a sample rate, and how messages on different topics are aligned.
It is YAML (or the same structure as a dict)::

    rate: 20.0            # Hz: one sample every 1 / rate seconds
    max_age: 0.15         # s: at a tick, an input older than this makes the tick stale (default 2 / rate)
    trigger: /imu         # optional: one tick per message on this topic instead of a fixed rate
    stamp: header         # header: a message's header.stamp where it has one, else the log time; log
    observation:
      /imu: [angular_velocity.z, linear_acceleration.x]
      /wheel_odom: [twist.twist.linear.x]
    control:              # optional
      /cmd_vel: [linear.x, angular.z]
    state:
      /mocap/pose: [pose.position.x, pose.position.y, yaw(pose.orientation)]
    estimates:            # optional: estimators recorded in the bag, each mapped onto the state
      robot_ekf:
        /odometry/filtered: [pose.pose.position.x, pose.pose.position.y, yaw(pose.pose.orientation)]
    names:                # optional, per vector: default the field expressions
      state: [x, y, yaw]
    units:                # optional, per vector: default ""
      state: [m, m, rad]
    model:                # optional: the system's equations, a registered scenario (built-in or plugin)
      scenario: quadrotor
      preset: v4          # optional
      set: {dt: 0.05}     # optional: constants

With ``model:`` the named scenario must have the spec's dimensions (as many states, observations
and controls as the vectors have fields), the same angle components (the fields marked as angles
are the model's angle_states and angle_obs) and the period 1 / rate (to a relative 1e-9); the
names and units default to the model's. ``state:`` may then be left out: a recording without
ground truth, whose dataset has the model's state names, units and angles and no labelled step
(a hybrid trains on it with ``--supervision observations``). The digest covers ``model:``.

A field is an attribute path of the decoded message (``pose.position.x``; ``[i]`` indexes an
array: ``position[2]``, ``covariance[35]``) or a conversion of one:

    yaw(q), roll(q), pitch(q)   Euler angles (ZYX) of a quaternion q with fields x, y, z, w [rad]
    norm(v)                     Euclidean norm of a vector with fields x, y, z
    angle(p)                    p itself, marked as an angle (wrapped in errors and innovations)

yaw, roll, pitch and angle components are angles: the dataset marks them so that errors are wrapped
to (-pi, pi] and circular means used, as for the simulated scenarios. Fields are read through the
message's own attributes (the classes rosbags builds from each bag's schemas), so any message
type works without per-type code; an unknown field is refused with the message's field list.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from neural_estimator.core.safe_yaml import YamlError, load_yaml
from neural_estimator.robot.data_scenario import model_scenario_of
from neural_estimator.scenarios.base import Scenario, ScenarioError

VECTORS = ("observation", "control", "state")
ESTIMATE_PREFIX = "estimate/"
STAMPS = ("header", "log")
ANGLE_FUNCS = ("yaw", "roll", "pitch", "angle")
FUNCS = ANGLE_FUNCS + ("norm",)
_PATH = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(\[\d+\])*(\.[A-Za-z_][A-Za-z0-9_]*(\[\d+\])*)*")
_STEP = re.compile(r"([A-Za-z_][A-Za-z0-9_]*)((?:\[\d+\])*)")
_TOPIC = re.compile(r"/?[A-Za-z_~{][A-Za-z0-9_/{}~]*")
MAX_COMPONENTS = 1024  # per vector, the package's dimension bound


MAX_RATE = 10_000.0  # Hz: a spec's sample rate (each tick is a row of every recorded stream)
MAX_TICKS = 20_000_000  # samples of one bag (rate x the bag's span), checked before allocating


class SpecError(ValueError):
    """A spec that cannot be used, or a message that does not have a field the spec names."""


@dataclasses.dataclass(frozen=True)
class Field:
    """One component: a function (None, or one of FUNCS) of an attribute path of a topic's messages."""

    topic: str
    expr: str  # as written in the spec
    func: str | None
    path: tuple[tuple[str, tuple[int, ...]], ...]  # (attribute, indices) steps

    @property
    def is_angle(self) -> bool:
        return self.func in ANGLE_FUNCS


@dataclasses.dataclass(frozen=True)
class Spec:
    """A parsed spec. ``vectors[name]`` is the tuple of Fields of observation, control, state and of
    every recorded estimate (key ``estimate/<name>``, as many fields as the state)."""

    rate: float
    max_age: float
    trigger: str | None
    stamp: str
    vectors: dict[str, tuple[Field, ...]]
    names: dict[str, tuple[str, ...]]
    units: dict[str, tuple[str, ...]]
    source: dict[str, Any]  # the spec as given (JSON-able), recorded in datasets and cards
    model: Scenario | None = None  # the scenario ``model:`` names, or None

    @property
    def has_state(self) -> bool:
        """Whether the spec reads a ground-truth state (without ``model:`` it always does)."""
        return bool(self.vectors["state"])

    @property
    def dt(self) -> float:
        return 1.0 / self.rate

    @property
    def topics(self) -> tuple[str, ...]:
        """Every topic the vectors read, in order of first use (state last)."""
        seen: dict[str, None] = {}
        for name in self.vectors:
            for f in self.vectors[name]:
                seen.setdefault(f.topic, None)
        return tuple(seen)

    @property
    def estimates(self) -> tuple[str, ...]:
        """Names of the recorded estimates."""
        return tuple(k.split("/", 1)[1] for k in self.vectors if k.startswith(ESTIMATE_PREFIX))

    def angles(self, vector: str) -> tuple[int, ...]:
        if vector == "state" and not self.has_state and self.model is not None:
            return tuple(self.model.angle_states)
        return tuple(i for i, f in enumerate(self.vectors[vector]) if f.is_angle)

    def digest(self) -> str:
        """SHA-256 of the spec's canonical JSON: what a checkpoint's inputs were."""
        return hashlib.sha256(json.dumps(self.source, sort_keys=True).encode()).hexdigest()


MAX_SPEC_BYTES = 1_000_000  # characters of a spec file (a real one is a few hundred)


def load_spec(spec: str | Path | Mapping[str, Any]) -> Spec:
    """Parse a spec from a YAML file or a mapping; errors name the key and the problem in one line."""
    where = "spec"
    if not isinstance(spec, Mapping):
        import yaml

        path = Path(spec)
        where = str(path)
        try:
            text = path.read_text()
        except OSError as exc:
            raise SpecError(f"{path}: cannot read the spec ({exc.strerror or exc})") from None
        loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)  # libyaml: linear, nesting bounded at 1,000
        try:
            if len(text) > MAX_SPEC_BYTES:
                raise YamlError(f"{path}: a spec of {len(text)} characters, over the bound of {MAX_SPEC_BYTES}")
            # anchors and aliases are refused before anything is built: a few aliases nested a few
            # levels deep expand a 51 KB file to gigabytes wherever the spec is walked or serialized
            if any(isinstance(ev, yaml.AliasEvent) for ev in yaml.parse(text, Loader=loader)):
                raise SpecError(f"{path}: YAML aliases (*name) are not allowed in a spec: write each value out")
            spec = load_yaml(text, str(path), 4 * MAX_SPEC_BYTES)  # characters -> at most 4 bytes each
        except yaml.YAMLError as exc:
            raise SpecError(f"{path}: not valid YAML ({' '.join(str(exc).split())[:200]})") from None
        except RecursionError:  # the pure-Python loader, where PyYAML lacks libyaml
            raise SpecError(f"{path}: YAML nested too deeply") from None
        except YamlError as exc:
            raise SpecError(str(exc)) from None
        if not isinstance(spec, Mapping):
            raise SpecError(f"{path}: the spec must be a mapping with rate, observation and state")
    return _parse(dict(spec), where)


def _parse(raw: dict[str, Any], where: str) -> Spec:
    known = {"rate", "max_age", "trigger", "stamp", "names", "units", "estimates", "model", *VECTORS}
    unknown = sorted(set(raw) - known)
    if unknown:
        raise SpecError(f"{where}: unknown key(s) {unknown}; known: {sorted(known)}")
    rate, max_age, trigger, stamp = _timing(raw, where)
    model = _model(raw.get("model"), rate, where)
    vectors = {}
    estimates = raw.get("estimates") or {}
    if not isinstance(estimates, Mapping) or not all(
        isinstance(k, str) and re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", k) for k in estimates
    ):
        raise SpecError(f"{where}: estimates must map names (letters, digits, _) to topic: [fields] mappings")
    for name in (*VECTORS, *(ESTIMATE_PREFIX + k for k in estimates)):
        entry = raw.get(name) if name in VECTORS else estimates[name[len(ESTIMATE_PREFIX) :]]
        # with a model the ground truth may be absent: a recording with no state topic
        fields = () if name == "state" and entry is None and model is not None else _vector_fields(name, entry, where)
        vectors[name] = fields
        if not name.startswith(ESTIMATE_PREFIX):
            continue
        dx = len(vectors["state"]) or (model.dx if model is not None else 0)
        if len(fields) != dx:
            raise SpecError(
                f"{where}: {name} has {len(fields)} fields; an estimate needs one per state component ({dx})"
            )
    if model is not None:
        _check_model(model, vectors, where)
    theirs = {key: model_labels(model, key) for key in ("names", "units")} if model is not None else {}
    names = _labels(raw.get("names"), "names", vectors, where, lambda f: f.expr, theirs.get("names"))
    units = _labels(
        raw.get("units"), "units", vectors, where, lambda f: "rad" if f.is_angle else "", theirs.get("units")
    )
    return Spec(rate, max_age, trigger, stamp, vectors, names, units, _source(raw, estimates, where), model)


def _model(entry: Any, rate: float, where: str) -> Scenario | None:
    """The scenario ``model:`` names (None without one), its period checked against 1 / rate."""
    if entry is None:
        return None
    try:
        model = model_scenario_of(entry)
    except ScenarioError as exc:
        raise SpecError(f"{where}: {exc}") from None
    if abs(model.dt - 1.0 / rate) > 1e-9 / rate:
        raise SpecError(
            f"{where}: the model {entry['scenario']!r} has dt = {model.dt:.12g} s, but rate {rate:g} Hz samples "
            f"every {1.0 / rate:.12g} s: add set: {{dt: {1.0 / rate:.12g}}} to model, or change the rate"
        )
    return model


def _check_model(model: Scenario, vectors: dict[str, tuple[Field, ...]], where: str) -> None:
    """The vectors have the model's dimensions, and their angle components are the model's."""
    name = model.name
    for vector, n in (("state", model.dx), ("observation", model.dy), ("control", model.du)):
        fields = vectors[vector]
        if vector == "state" and not fields:
            continue
        if len(fields) != n:
            raise SpecError(f"{where}: {vector} has {len(fields)} fields, but the model {name!r} has {n} {vector}s")
    for vector, theirs in (("state", model.angle_states), ("observation", model.angle_obs)):
        ours = [i for i, f in enumerate(vectors[vector]) if f.is_angle]
        if vectors[vector] and ours != list(theirs):
            raise SpecError(
                f"{where}: the {vector}'s angle components are {ours}, the model {name!r}'s are {list(theirs)} "
                "(mark an angle with angle(...))"
            )


def _timing(raw: dict[str, Any], where: str) -> tuple[float, float, str | None, str]:
    """(rate, max_age, trigger, stamp) of a spec, checked."""
    rate = _positive(raw.get("rate"), "rate", where)
    if rate > MAX_RATE:
        raise SpecError(f"{where}: rate {rate:g} Hz is over the bound of {MAX_RATE:g} Hz")
    max_age = _positive(raw.get("max_age", 2.0 / rate), "max_age", where)
    trigger = raw.get("trigger")
    if trigger is not None and (not isinstance(trigger, str) or not _TOPIC.fullmatch(trigger)):
        raise SpecError(f"{where}: trigger must be a topic name, got {trigger!r}")
    stamp = raw.get("stamp", "header")
    if stamp not in STAMPS:
        raise SpecError(f"{where}: stamp must be one of {list(STAMPS)}, got {stamp!r}")
    return rate, max_age, trigger, stamp


def _vector_fields(name: str, entry: Any, where: str) -> tuple:
    """The fields of vector (or estimate) ``name`` from its ``topic: [fields]`` entry, checked; an
    absent ``control`` has none."""
    if entry is None:
        if name != "control":
            raise SpecError(f"{where}: missing {name!r} (a mapping topic: [fields])")
        entry = {}
    pairs = _topic_pairs(entry)
    if pairs is None:
        raise SpecError(f"{where}: {name!r} must map topics to lists of fields, got {type(entry).__name__}")
    fields = []
    for topic, exprs in pairs:
        if not isinstance(topic, str) or not _TOPIC.fullmatch(topic):
            raise SpecError(f"{where}: {name}: {topic!r} is not a topic name")
        if isinstance(exprs, str):
            exprs = [exprs]
        if not isinstance(exprs, list) or not exprs:
            raise SpecError(f"{where}: {name}: {topic}: expected a list of fields, got {exprs!r}")
        fields += [parse_field(topic, e, f"{where}: {name}: {topic}") for e in exprs]
    if name != "control" and not fields:
        raise SpecError(f"{where}: {name!r} names no field")
    if len(fields) > MAX_COMPONENTS:
        raise SpecError(f"{where}: {name!r} has {len(fields)} components, more than {MAX_COMPONENTS}")
    return tuple(fields)


def _source(raw: dict[str, Any], estimates: Mapping[str, Any], where: str) -> dict[str, Any]:
    """The spec as recorded (checked to be JSON): the vectors as [topic, fields] pairs, since datasets
    and cards store the spec as JSON with sorted keys, which would lose the order of the topics (the
    order of the model's inputs); the digest covers it."""
    source = {k: raw[k] for k in sorted(raw)}
    for name in VECTORS:
        if name in source and source[name] is not None:
            source[name] = _pairs_source(source[name])
    if estimates:
        source["estimates"] = {k: _pairs_source(v) for k, v in estimates.items()}
    try:
        json.dumps(source)
    except (TypeError, ValueError):
        raise SpecError(f"{where}: holds values that are not plain text, numbers or lists") from None
    return source


def _topic_pairs(entry: Any) -> list[tuple[Any, Any]] | None:
    """A vector's (topic, fields) pairs in order: from a mapping (YAML) or from a list of
    ``[topic, fields]`` pairs (the form datasets and cards record); None for anything else."""
    if isinstance(entry, Mapping):
        return list(entry.items())
    if isinstance(entry, list) and all(isinstance(p, (list, tuple)) and len(p) == 2 for p in entry):
        return [(p[0], p[1]) for p in entry]
    return None


def topic_order_lost(source: Mapping[str, Any]) -> bool:
    """Whether a recorded spec (a card's or a dataset's) keeps its inputs' topics as a mapping of more
    than one topic: recorded before the spec kept their order (JSON with sorted keys reorders a
    mapping), so the model's input order cannot be told from it."""
    return any(isinstance(source.get(v), Mapping) and len(source[v]) > 1 for v in ("observation", "control"))


def _pairs_source(entry: Any) -> list[list[Any]]:
    return [[topic, exprs if isinstance(exprs, list) else [exprs]] for topic, exprs in _topic_pairs(entry)]


def _positive(value: Any, key: str, where: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise SpecError(f"{where}: {key} must be a positive number, got {value!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise SpecError(f"{where}: {key} must be a positive number, got {value!r}")
    return v


def model_labels(model: Scenario, key: str) -> dict[str, tuple[str, ...]]:
    """A model's names or units of the three vectors: a spec's defaults where it names a model."""
    return {
        "state": tuple(getattr(model, f"state_{key}")),
        "observation": tuple(getattr(model, f"obs_{key}")),
        "control": tuple(getattr(model, f"control_{key}")),
    }


def _labels(
    raw: Any, key: str, vectors: dict[str, tuple[Field, ...]], where: str, default, model: dict | None = None
) -> dict[str, tuple[str, ...]]:
    """Names or units per vector, as given or by default the model's (``model``, where the spec names
    one: as many as the vector's fields, checked) or else ``default`` of each field."""
    raw = raw or {}
    if not isinstance(raw, Mapping) or set(raw) - set(VECTORS):
        raise SpecError(f"{where}: {key} must map some of {list(VECTORS)} to lists of strings")
    out = {}
    for name in VECTORS:
        given = raw.get(name)
        fallback = tuple(model[name]) if model else tuple(default(f) for f in vectors[name])
        if given is None:
            out[name] = fallback
            continue
        if not isinstance(given, list) or len(given) != len(fallback) or not all(isinstance(s, str) for s in given):
            raise SpecError(f"{where}: {key}.{name} must list {len(fallback)} strings, one per component")
        out[name] = tuple(given)
    return out


def parse_field(topic: str, expr: Any, where: str) -> Field:
    """``path`` or ``func(path)`` -> a Field; one-line errors."""
    if not isinstance(expr, str):
        raise SpecError(f"{where}: a field must be a string, got {expr!r}")
    text = expr.strip()
    func = None
    m = re.fullmatch(r"([a-z]+)\((.*)\)", text)
    if m:
        func, text = m.group(1), m.group(2).strip()
        if func not in FUNCS:
            raise SpecError(f"{where}: unknown conversion {func!r} in {expr!r}; known: {', '.join(FUNCS)}")
    if not _PATH.fullmatch(text):
        raise SpecError(f"{where}: {expr!r} is not a field path such as pose.position.x or position[2]")
    steps = []
    for part in text.split("."):
        sm = _STEP.fullmatch(part)
        indices = tuple(int(i) for i in re.findall(r"\[(\d+)\]", sm.group(2)))
        steps.append((sm.group(1), indices))
    return Field(topic, expr, func, tuple(steps))


# ---- reading fields from messages ---------------------------------------------------------------
def message_fields(msg: Any) -> list[str]:
    """The field names of a decoded message (rosbags messages are dataclasses)."""
    if dataclasses.is_dataclass(msg):
        return [f.name for f in dataclasses.fields(msg) if not f.name.startswith("_")]
    names = getattr(type(msg), "__slots__", None) or getattr(type(msg), "get_fields_and_field_types", lambda: {})()
    return [n.lstrip("_") for n in names]


def resolve(msg: Any, path: tuple[tuple[str, tuple[int, ...]], ...], field: Field, msgtype: str) -> Any:
    """Follow ``path`` through ``msg``; SpecError naming the topic, type and the fields there."""
    obj = msg
    walked = []
    for attr, indices in path:
        if not hasattr(obj, attr) or attr.startswith("_"):
            where = ".".join(walked) or "the message"
            raise SpecError(
                f"topic {field.topic} ({msgtype}): no field {attr!r} in {where} (field {field.expr!r}); "
                f"fields there: {', '.join(message_fields(obj)) or 'none'}"
            )
        obj = getattr(obj, attr)
        walked.append(attr)
        for i in indices:
            try:
                obj = obj[i]
            except (IndexError, TypeError, KeyError):
                size = len(obj) if hasattr(obj, "__len__") else "not an array"
                raise SpecError(
                    f"topic {field.topic} ({msgtype}): {'.'.join(walked)}[{i}] is out of range "
                    f"(length {size}) in field {field.expr!r}"
                ) from None
            walked[-1] += f"[{i}]"
    return obj


def field_value(msg: Any, field: Field, msgtype: str) -> float:
    """The float a Field takes on one decoded message (conversions applied)."""
    obj = resolve(msg, field.path, field, msgtype)
    try:
        if field.func in ("yaw", "roll", "pitch"):
            return euler(float(obj.x), float(obj.y), float(obj.z), float(obj.w))[
                ("roll", "pitch", "yaw").index(field.func)
            ]
        if field.func == "norm":
            return math.sqrt(float(obj.x) ** 2 + float(obj.y) ** 2 + float(obj.z) ** 2)
        return float(obj)
    except AttributeError as exc:
        raise SpecError(
            f"topic {field.topic} ({msgtype}): {field.expr!r} needs a "
            f"{'quaternion (x, y, z, w)' if field.func != 'norm' else 'vector (x, y, z)'}: {exc}"
        ) from None
    except (TypeError, ValueError):
        raise SpecError(
            f"topic {field.topic} ({msgtype}): {field.expr!r} is not a number "
            f"(it is a {type(obj).__name__}); name one of its fields"
        ) from None


def euler(x: float, y: float, z: float, w: float) -> tuple[float, float, float]:
    """(roll, pitch, yaw) of the unit quaternion (x, y, z, w), ZYX convention (REP 103), in radians.

    roll = atan2(2(w x + y z), 1 - 2(x^2 + y^2)), pitch = asin(clip(2(w y - z x), -1, 1)),
    yaw = atan2(2(w z + x y), 1 - 2(y^2 + z^2)); the quaternion is normalised first (a zero
    quaternion gives NaN, which the dataset drops and counts).
    """
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if not n > 0:
        return math.nan, math.nan, math.nan
    x, y, z, w = x / n, y / n, z / n, w / n
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2.0 * (w * y - z * x))))
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return roll, pitch, yaw


def topic_values(msg: Any, fields: tuple[Field, ...], msgtype: str) -> np.ndarray:
    """Every field of one topic on one message, as a float array."""
    return np.array([field_value(msg, f, msgtype) for f in fields], dtype=np.float64)
