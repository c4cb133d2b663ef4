"""Recorded-data estimation one message at a time, on the recording's clock: the dataset's rule, live.

``neural-estimator evaluate`` scores a model on the trajectories of :mod:`~neural_estimator.robot.dataset`;
:class:`Ticker` gives, message by message, the estimates a model makes on exactly those samples, so
the robot estimator node (and :func:`replay_bag`, offline) serve what ``evaluate`` scored:

* **Ticks** are the multiples of the spec's period ``dt`` on the messages' own clock (their header
  stamps, or their log / receipt times for ``stamp: log``), or the stamps of the ``trigger``
  topic's messages: the dataset builder's ticks (:func:`~neural_estimator.robot.dataset.tick_times`).
* **Inputs at a tick** T: each observation and control topic's latest message stamped at or before
  T, no older than ``max_age``; a tick with a topic missing or stale, or a non-finite value, gives
  no estimate (the dataset drops it).
* **When a tick runs**: once every input has delivered a message stamped at or after T (messages of
  one topic arrive in stamp order; one arriving late is slotted in by its stamp, or counted ``late``
  when its tick has already run), or once some input's stamps are ``settle_delay`` seconds past T
  (an input that went silent). Both depend on stamps only, so a bag played at any speed, or
  replayed at full speed offline, gives the same ticks and inputs.
* **Trajectories**: the dataset cuts each run of valid ticks into trajectories of ``horizon`` steps,
  and ``evaluate`` starts the model afresh on each. The ticker restarts the model (state reset,
  ``u_{-1} = 0``) at the first valid tick after an invalid one and every ``restart_every`` valid
  ticks after that (the card's horizon by default): a model trained and evaluated on trajectories
  of that length is never run on a longer context than it was scored on. ``restart_every = 0``
  never restarts within a run of valid ticks.

Each estimate is stamped with its tick T, the time of the observation it answers.
"""

from __future__ import annotations

import bisect
import collections
import dataclasses
from collections.abc import Iterable

import numpy as np

from neural_estimator.robot.dataset import topic_fields
from neural_estimator.robot.spec import Spec

HISTORY = 10_000  # messages kept per topic while a tick waits (bounds memory when a topic floods)
MAX_SKIP = 100_000  # ticks: a larger jump of the stamps is skipped (counted stale), not stepped through


@dataclasses.dataclass(frozen=True)
class TickEstimate:
    """One estimate: its tick [ns on the recording's clock], the state, its covariance (or None),
    and whether the model was restarted at this tick (the first step of a trajectory)."""

    stamp: int
    x: np.ndarray
    cov: np.ndarray | None
    restarted: bool


def input_topics(spec: Spec) -> dict[str, tuple]:
    """{topic: the fields read from it} of the spec's observation, control and trigger topics, in order."""
    fields = topic_fields(spec)
    topics = [f.topic for name in ("observation", "control") for f in spec.vectors[name]]
    if spec.trigger:
        topics.append(spec.trigger)
    return {t: fields.get(t, ()) for t in dict.fromkeys(topics)}


class Ticker:
    """Feed messages with :meth:`push`; it returns the estimates of the ticks that became settled."""

    def __init__(self, spec: Spec, estimator, restart_every: int, settle_delay: float = 2.0) -> None:
        self.spec, self.est = spec, estimator
        self.restart_every = int(restart_every)
        self.fields = input_topics(spec)
        # each vector's components as (topic, column of that topic's values), resolved once
        self.columns = {
            name: [(f.topic, self.fields[f.topic].index(f)) for f in spec.vectors[name]]
            for name in ("observation", "control")
        }
        self.period = int(round(spec.dt * 1e9))
        self.max_age = int(round(spec.max_age * 1e9))
        self.delay = int(round(settle_delay * 1e9))
        self.history = {t: collections.deque(maxlen=HISTORY) for t in self.fields}
        self.triggers: collections.deque[int] = collections.deque(maxlen=HISTORY)
        self.next_tick: int | None = None  # fixed rate: the next tick [ns]
        self.done: int | None = None  # the last tick run [ns]
        self.steps: int | None = None  # valid ticks since the last restart; None: restart at the next
        self.u_prev = np.zeros((1, len(spec.vectors["control"])))
        self.counts = {"ticks": 0, "estimates": 0, "stale": 0, "nonfinite": 0, "restarts": 0, "late": 0}

    def push(self, topic: str, stamp: int, values: np.ndarray) -> list[TickEstimate]:
        """Take one message of an input topic (stamp in ns, the spec's field values) and run every
        tick now settled."""
        stamp = int(stamp)
        if self.done is not None and stamp <= self.done:
            self.counts["late"] += 1  # its ticks have run; the dataset would have used it
            return []
        queue = self.history[topic]
        if len(queue) == queue.maxlen:
            queue.popleft()  # a flood while a tick waits: the oldest cannot matter to a later tick
        if queue and stamp < queue[-1][0]:  # out of order within the topic: slot it in by stamp
            queue.insert(bisect.bisect_right([s for s, _ in queue], stamp), (stamp, values))
        else:
            queue.append((stamp, values))
        if topic == self.spec.trigger:
            if len(self.triggers) == self.triggers.maxlen:
                self.triggers.popleft()
            if self.triggers and stamp < self.triggers[-1]:
                self.triggers.insert(bisect.bisect_right(list(self.triggers), stamp), stamp)
            else:
                self.triggers.append(stamp)
        return self._run(self._settled())

    def flush(self) -> list[TickEstimate]:
        """At the end of a recording: run the ticks up to the last stamp every input reached."""
        marks = [q[-1][0] for q in self.history.values() if q]
        return self._run(min(marks)) if len(marks) == len(self.history) else []

    # ---- which ticks can run -------------------------------------------------------------------------
    def _settled(self) -> int | None:
        """The latest time every tick up to which has all the messages it will get."""
        marks = [q[-1][0] if q else None for q in self.history.values()]
        newest = max((m for m in marks if m is not None), default=None)
        if newest is None:
            return None
        both = newest - self.delay  # an input silent for settle_delay of the others' stamps
        return max(min(marks), both) if None not in marks else both

    def _due(self, until: int) -> Iterable[int]:
        if self.spec.trigger:
            while self.triggers and self.triggers[0] <= until:
                yield self.triggers.popleft()
            return
        if self.next_tick is None:
            first = min(q[0][0] for q in self.history.values() if q)
            self.next_tick = -(-first // self.period) * self.period  # the first multiple of dt
        skipped = (until - self.next_tick) // self.period - MAX_SKIP
        if skipped > 0:  # a jump of the stamps (a clock reset): no input at those ticks
            self.counts["ticks"] += int(skipped)
            self.counts["stale"] += int(skipped)
            self.next_tick += int(skipped) * self.period
            self.steps = None
        while self.next_tick <= until:
            tick, self.next_tick = self.next_tick, self.next_tick + self.period
            yield tick

    def _run(self, until: int | None) -> list[TickEstimate]:
        if until is None:
            return []
        out = []
        for tick in self._due(until):
            self.done = tick
            est = self._tick(tick)
            if est is not None:
                out.append(est)
        return out

    # ---- one tick ------------------------------------------------------------------------------------
    def _at(self, tick: int) -> dict[str, tuple[int, np.ndarray]]:
        """{topic: (stamp, values)} of each input's latest message stamped at or before ``tick``;
        older messages that no later tick can use are dropped."""
        out = {}
        for topic, queue in self.history.items():
            while len(queue) > 1 and queue[1][0] <= tick:
                queue.popleft()
            if queue and queue[0][0] <= tick:
                out[topic] = queue[0]
        return out

    def _tick(self, tick: int) -> TickEstimate | None:
        self.counts["ticks"] += 1
        latest = self._at(tick)
        if any(t not in latest or tick - latest[t][0] > self.max_age for t in self.fields):
            self.counts["stale"] += 1
            self.steps = None
            return None
        y, u = self._vector("observation", latest), self._vector("control", latest)
        if not (np.all(np.isfinite(y)) and np.all(np.isfinite(u))):
            self.counts["nonfinite"] += 1
            self.steps = None
            return None
        restarted = self.steps is None or (self.restart_every > 0 and self.steps >= self.restart_every)
        if restarted:
            self.est.reset(1)
            self.u_prev = np.zeros_like(self.u_prev)
            self.steps = 0
            self.counts["restarts"] += 1
        x = np.asarray(self.est.step(y[None], self.u_prev), dtype=np.float64)[0]
        self.u_prev = u[None]
        self.steps += 1
        self.counts["estimates"] += 1
        cov = getattr(self.est, "covariance", None)
        return TickEstimate(tick, x, None if cov is None else np.asarray(cov)[0], restarted)

    def _vector(self, name: str, latest: dict[str, tuple[int, np.ndarray]]) -> np.ndarray:
        return np.array([latest[topic][1][col] for topic, col in self.columns[name]], dtype=np.float64)


def replay_bag(bag, spec: Spec, estimator, restart_every: int, settle_delay: float = 2.0) -> list[TickEstimate]:
    """Every estimate :class:`Ticker` gives on a recording's input topics, in the order a player
    plays them (log time), then :meth:`Ticker.flush`: what the robot estimator node publishes
    when the recording is played into it, at any speed."""
    from neural_estimator.bags import open_bag
    from neural_estimator.robot.dataset import message_stamp
    from neural_estimator.robot.spec import topic_values

    ticker = Ticker(spec, estimator, restart_every, settle_delay)
    out: list[TickEstimate] = []
    with open_bag(bag) as reader:
        for conn, t_log, msg in reader.decoded(list(ticker.fields)):
            values = topic_values(msg, ticker.fields[conn.topic], conn.msgtype)
            out += ticker.push(conn.topic, message_stamp(msg, t_log, spec), values)
    return out + ticker.flush()
