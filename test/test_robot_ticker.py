"""The robot estimator's per-message computation (robot/ticker.py) is the one `evaluate` scores:
a recording replayed message by message gives, trajectory for trajectory, the estimates of the
model run on the recording's dataset; ticks on the recording's clock, whatever the playing order."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from neural_estimator.cli import main
from neural_estimator.data import load_trajectories
from neural_estimator.methods.registry import make_estimator
from neural_estimator.robot import DataScenario, load_spec
from neural_estimator.robot.ticker import Ticker, replay_bag

ROOT = Path(__file__).resolve().parents[1]
SPEC = ROOT / "examples" / "robot_spec.yaml"
sys.path.insert(0, str(ROOT / "examples"))
import robot_bag  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_torch_thread")
LENGTH = 60  # steps per dataset trajectory (the card's horizon: the node's default restart_every)


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """Two 30-second runs of the example robot, their dataset, and a GRU trained briefly on it."""
    d = tmp_path_factory.mktemp("ticker")
    bag = robot_bag.write_bag(d / "bag", runs=2, seconds=30.0, seed=3)
    data = d / "data.npz"
    assert main(["dataset", str(bag), "--spec", str(SPEC), "--length", str(LENGTH), "--out", str(data), "--quiet"]) == 0
    model = d / "gru"
    args = ["train", "--data", str(data), "--model", "gru", "--out", str(model), "--epochs", "1"]
    assert main(args + ["--windows-per-epoch", "16", "--window", "20", "--warmup", "2", "--quiet"]) == 0
    trajectories, _ = load_trajectories(data)
    return bag, trajectories, model


def _estimator(trajectories, model):
    return make_estimator("gru", DataScenario(trajectories.meta), checkpoint=model)


def _trajectories(estimates, length):
    """The estimates grouped by restart, the groups of ``length`` steps only (a run's remainder is
    estimated live but is in no dataset trajectory)."""
    groups = []
    for e in estimates:
        if e.restarted:
            groups.append([])
        groups[-1].append(e)
    return [g for g in groups if len(g) == length]


@pytest.mark.slow
def test_a_replayed_recording_gives_the_estimates_evaluate_scored(recording):
    bag, data, model = recording
    offline = _estimator(data, model).run(data.y, data.u).x  # what evaluate scores
    card_horizon = DataScenario(data.meta).config.horizon
    assert card_horizon == LENGTH
    live = replay_bag(bag, load_spec(SPEC), _estimator(data, model), restart_every=card_horizon)
    groups = _trajectories(live, LENGTH)
    assert len(groups) == data.n
    x = np.array([[e.x for e in g] for g in groups])
    np.testing.assert_allclose(x, offline, atol=1e-4)  # float32 steps vs the parallel form
    # stamped with the tick: multiples of 0.1 s on the recording's clock, one per tick, in order
    stamps = np.array([e.stamp for e in live])
    assert np.all(stamps % 100_000_000 == 0) and np.all(np.diff(stamps) > 0)
    assert stamps[0] >= 1_700_000_000 * 10**9  # the recording's clock (robot_bag.py starts there), not the node's
    # never restarted, the model runs on contexts it was not scored on and the estimates differ
    unbounded = replay_bag(bag, load_spec(SPEC), _estimator(data, model), restart_every=0)
    assert sum(e.restarted for e in unbounded) == 2  # once per run (the gap between the runs)
    later = np.array([e.x for e in unbounded[LENGTH : 2 * LENGTH]])
    assert np.abs(later - x[1]).max() > 1e-3


@pytest.mark.slow
def test_playing_order_and_speed_do_not_change_the_ticks(recording):
    """Topics interleaved differently (as DDS delivers them) give the same estimates: a tick runs only
    once every input has passed it."""
    bag, data, model = recording
    from neural_estimator.bags import open_bag
    from neural_estimator.robot.dataset import message_stamp
    from neural_estimator.robot.spec import topic_values

    spec = load_spec(SPEC)
    reference = replay_bag(bag, spec, _estimator(data, model), restart_every=LENGTH)
    ticker = Ticker(spec, _estimator(data, model), LENGTH)
    with open_bag(bag) as reader:
        msgs = [
            (c.topic, message_stamp(m, t, spec), topic_values(m, ticker.fields[c.topic], c.msgtype))
            for c, t, m in reader.decoded(list(ticker.fields))
        ]
    # each topic in its own order, but topics shifted against each other by up to 0.3 s of stamps
    shift = {t: i * 100_000_000 for i, t in enumerate(ticker.fields)}
    msgs.sort(key=lambda m: m[1] + shift[m[0]])
    got = [e for topic, stamp, values in msgs for e in ticker.push(topic, stamp, values)] + ticker.flush()
    assert [e.stamp for e in got] == [e.stamp for e in reference]
    np.testing.assert_allclose([e.x for e in got], [e.x for e in reference], atol=1e-6)
    assert ticker.counts["late"] == 0


def test_a_silent_input_stales_its_ticks_after_the_settle_delay():
    """A topic that stops holds the ticks back only until the others' stamps are settle_delay past."""
    spec = load_spec({"rate": 10, "max_age": 0.15, "observation": {"/a": ["v"], "/b": ["v"]}, "state": {"/c": ["v"]}})

    class Echo:
        covariance = None

        def reset(self, batch):
            pass

        def step(self, y, u):
            return y[:, :1]

    ticker = Ticker(spec, Echo(), restart_every=0, settle_delay=1.0)
    ms = 1_000_000
    out = []
    for k in range(0, 31):  # /a every 0.1 s for 3 s; /b only for the first 0.5 s
        out += ticker.push("/a", k * 100 * ms, np.array([float(k)]))
        if k <= 5:
            out += ticker.push("/b", k * 100 * ms, np.array([0.0]))
    assert [e.stamp // (100 * ms) for e in out] == [0, 1, 2, 3, 4, 5, 6]  # /b at 0.5 s is fresh until 0.65 s
    assert ticker.counts["ticks"] == 21  # up to 3.0 s - settle_delay
    assert ticker.counts["stale"] == 21 - 7
    late = ticker.push("/b", 100 * ms, np.array([0.0]))
    assert late == [] and ticker.counts["late"] == 1
