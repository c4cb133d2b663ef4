#!/usr/bin/env python3
"""Coverage-guided fuzzing (atheris / libFuzzer) of everything that parses bytes a stranger controls.

Targets (each takes one byte string from the fuzzer):

* ``mcap``: the bytes as a ``.mcap`` file, opened with :func:`neural_estimator.bags.open_bag` and
  read to the end, every message decoded as the stream it claims to be (what ``metrics``,
  ``replay`` and the player do with a bag they are given);
* ``rosbag2``: the bytes as the ``metadata.yaml`` of a rosbag2 directory beside a valid bag;
* ``cdr``: the bytes as a CDR message on every stream the nodes accept (observation, ground truth,
  estimate, covariance: :class:`~neural_estimator.stream.messages.VectorCodec` and
  :func:`~neural_estimator.stream.messages.decode_vector`);
* ``scenario``: the bytes as a ``scenario`` topic message, decoded and turned into a scenario as
  the estimator node does (:func:`~neural_estimator.scenarios.scenario_from_description`).

The only outcomes allowed are success and the package's clear errors (``BagError``,
``MessageError``, ``ScenarioError``; for ``scenario`` also the few the node catches). Anything else
(an uncaught exception, a hang beyond ``-timeout``, memory beyond ``-rss_limit_mb``) is a crash:
libFuzzer writes the input to ``crash-*`` / ``timeout-*`` / ``oom-*`` and the exit status is non-zero.
Each target starts from a seed corpus of valid inputs written by the package itself.

    python scripts/fuzz.py mcap -max_total_time=600 -rss_limit_mb=1024 -print_final_stats=1
    python scripts/fuzz.py cdr -runs=20000

Every argument after the target goes to libFuzzer. ``--corpus DIR`` keeps the corpus (default: a
temporary directory). Found crashes are fixed and kept as regression inputs in
``test/data/fuzz/<target>/`` (the test suite replays them).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import warnings
from pathlib import Path

import atheris

with atheris.instrument_imports(include=["neural_estimator"]):
    import numpy as np

    from neural_estimator.stream import messages as MSG
    from neural_estimator.bags.directory import open_bag
    from neural_estimator.bags.errors import BagError, BagWarning, MessageError
    from neural_estimator.scenarios import ScenarioError, make_scenario, scenario_from_description

TARGETS = ("mcap", "rosbag2", "cdr", "scenario")
# What `ros2 bag record -s mcap` writes (abridged to the fields a reader uses), naming the bag beside it.
ROSBAG2_METADATA = """rosbag2_bagfile_information:
  version: 9
  storage_identifier: mcap
  duration: {nanoseconds: 3000000}
  starting_time: {nanoseconds_since_epoch: 0}
  message_count: 9
  topics_with_message_count:
    - topic_metadata: {name: /observation, type: sensor_msgs/msg/JointState, serialization_format: cdr,
                       offered_qos_profiles: []}
      message_count: 3
  compression_format: ""
  compression_mode: ""
  relative_file_paths: [dir_0.mcap]
  files:
    - path: dir_0.mcap
      starting_time: {nanoseconds_since_epoch: 0}
      duration: {nanoseconds: 3000000}
      message_count: 9
"""
_SCENARIO = make_scenario("ballistic")
_CODECS = [
    MSG.VectorCodec(_SCENARIO.name, MSG.observation_labels(_SCENARIO)),
    MSG.VectorCodec(_SCENARIO.name, MSG.state_labels(_SCENARIO)),
    MSG.VectorCodec("ekf", MSG.state_labels(_SCENARIO)),
    MSG.VectorCodec("ekf", MSG.covariance_labels(_SCENARIO.dx)),
]


def read_bag(path: Path) -> int:
    """Open a bag, read every message and decode the vector streams: the number of messages read."""
    n = 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", BagWarning)
        with open_bag(path) as reader:
            for conn, _, raw in reader.messages():
                n += 1
                if conn.msgtype == MSG.JOINT_STATE:
                    try:
                        MSG.decode_vector(raw)
                    except MessageError:
                        pass
                elif conn.msgtype == MSG.STRING:
                    try:
                        MSG.decode_string(raw)
                    except MessageError:
                        pass
    return n


def decode_streams(data: bytes) -> None:
    for codec in _CODECS:
        try:
            codec.decode(data)
        except MessageError:
            pass


def scenario_message(data: bytes) -> None:
    """The bytes as a whole ``scenario`` message (CDR string), and as the JSON text inside one (so
    the fuzzer reaches the description's contents, not only the CDR framing)."""
    for raw in (data, MSG.encode_string(data.decode("utf-8", errors="replace"))):
        try:
            scenario_from_description(MSG.decode_scenario(raw))
        except (MessageError, ScenarioError, KeyError, TypeError, ValueError):  # as the estimator node catches them
            pass


class Target:
    """One fuzz target: ``run(data)`` raises only on a bug; ``seeds()`` are valid inputs."""

    def __init__(self, name: str, workdir: Path) -> None:
        self.name, self.workdir = name, workdir
        self.bag = workdir / "input.mcap"
        self.bagdir = workdir / "dir"
        if name == "rosbag2":
            from neural_estimator.bags.dataset import arrays_to_bag
            from neural_estimator.data import simulate

            data = simulate(_SCENARIO, 1, 3, seed=0)
            self.bagdir.mkdir(exist_ok=True)
            arrays_to_bag(self.bagdir / "dir_0.mcap", _SCENARIO, data.x, data.y, data.u)

    def run(self, data: bytes) -> None:
        if self.name == "mcap":
            self.bag.write_bytes(data)
            try:
                read_bag(self.bag)
            except BagError:
                pass
        elif self.name == "rosbag2":
            (self.bagdir / "metadata.yaml").write_bytes(data)
            try:
                read_bag(self.bagdir)
            except BagError:
                pass
        elif self.name == "cdr":
            decode_streams(data)
        else:
            scenario_message(data)


def seeds(name: str) -> list[bytes]:
    """Valid inputs of each target, written by the package (the fuzzer mutates from them)."""
    from neural_estimator.bags.dataset import arrays_to_bag
    from neural_estimator.data import simulate

    data = simulate(_SCENARIO, 2, 4, seed=1)
    if name in ("mcap", "rosbag2"):
        with tempfile.TemporaryDirectory() as tmp:
            path = arrays_to_bag(Path(tmp) / "seed.mcap", _SCENARIO, data.x, data.y, data.u)
            if name == "mcap":
                return [path.read_bytes()]
            return [ROSBAG2_METADATA.encode()]
    if name == "cdr":
        return [c.encode(123, 1, 2, np.arange(len(c.names), dtype=float)) for c in _CODECS]
    messages = [
        MSG.encode_scenario(make_scenario(s).describe(), trajectories=2) for s in ("ballistic", "nlink", "lorenz96")
    ]
    return messages + [MSG.decode_string(m).encode() for m in messages]  # and their JSON text


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("target", choices=TARGETS)
    parser.add_argument("--corpus", help="corpus directory (kept; default: a temporary one)")
    args, libfuzzer = parser.parse_known_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        corpus = Path(args.corpus or Path(tmp) / "corpus")
        corpus.mkdir(parents=True, exist_ok=True)
        for i, seed in enumerate(seeds(args.target)):
            (corpus / f"seed-{i}").write_bytes(seed)
        regress = Path(__file__).resolve().parents[1] / "test" / "data" / "fuzz" / args.target
        dirs = [str(corpus)] + ([str(regress)] if regress.is_dir() else [])
        target = Target(args.target, Path(tmp))
        atheris.Setup([sys.argv[0], *libfuzzer, *dirs], target.run)
        atheris.Fuzz()
    return 0


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    sys.exit(main())
