"""Which run a recorded message belongs to: two publishers of one run, detected in-band.

A run announces itself once on ``/scenario`` with ``run.start_ns`` (the simulation time of its
first step), ``run.horizon`` T and ``run.dt_ns``; every observation of it is stamped
``start_ns + (n * T + k) * dt_ns`` (:func:`neural_estimator.stream.messages.step_stamp_ns`). So each
observation carries its run's identity in-band, recoverable exactly in integers:

    start(message) = stamp_ns - (n * T + k) * dt_ns

Two simulators publishing on one topic (or a restarted one) start at different times, so their
messages name different starts, even when their (trajectory, step) identities and their
scenario are the same. :class:`RunIdentity` compares every observation's start with the announced
one and counts the others per start; a second announcement (``/scenario`` with another start, or
``run_status`` "started" again) is reported too. Without an announced start (a robot's own
publisher, a bag without ``/scenario``) there is nothing to compare and nothing is reported.

Plain Python (no rclpy): the evaluator node calls it from its recorder.
"""

from __future__ import annotations

from neural_estimator.stream import messages as MSG
from neural_estimator.bags.errors import MessageError

MAX_STARTS = 16  # foreign starts counted one by one; beyond this, together (a bounded dict)


class RunIdentity:
    """The announced run and the observations that belong to another (see the module docstring)."""

    def __init__(self) -> None:
        self.start_ns: int | None = None
        self.horizon: int | None = None
        self.dt_ns: int | None = None
        self.announcements: list[int] = []  # distinct starts announced on /scenario, in order (the first 17)
        self.started = 0  # run_status "started" messages
        self.checked = 0  # observations compared with the announced run
        self.foreign: dict[int | None, int] = {}  # start -> observations of that other run (None: beyond MAX_STARTS)
        self._codec: MSG.VectorCodec | None = None
        self._announced_twice = False

    def on_scenario(self, raw: bytes) -> str | None:
        """A ``/scenario`` message: the first announced start is the run; another one is reported."""
        try:
            desc = MSG.decode_scenario(raw)
        except MessageError:
            return None  # the evaluator's loss lines and the scoring report unreadable announcements
        run = desc.get("run") if isinstance(desc.get("run"), dict) else {}
        start, horizon, dt = run.get("start_ns"), run.get("horizon"), run.get("dt_ns")
        if not all(isinstance(v, int) and not isinstance(v, bool) for v in (start, horizon, dt)):
            return None
        if not (0 <= start < 2**63 and 0 < horizon < 2**53 and 0 < dt < 2**63):  # int64 nanoseconds
            return None
        if start not in self.announcements and len(self.announcements) <= MAX_STARTS:
            self.announcements.append(start)
        if self.start_ns is None:
            self.start_ns, self.horizon, self.dt_ns = start, horizon, dt
            try:
                self._codec = MSG.VectorCodec(str(desc["scenario"]), MSG.observation_labels(desc))
            except (KeyError, TypeError, ValueError):
                self._codec = None
            return None
        if start != self.start_ns and not self._announced_twice:
            self._announced_twice = True
            return (
                f"a second run was announced on /scenario (start_ns {self.start_ns}, then {start}): "
                "two publishers on one topic, or a restarted one; the recording mixes runs"
            )
        return None

    def on_started(self) -> str | None:
        """A ``run_status`` "started": a second one means a second run on the same topics."""
        self.started += 1
        if self.started == 2:
            return "run_status 'started' received twice: a second publisher (or a restarted one) runs on these topics"
        return None

    def on_observation(self, raw: bytes) -> str | None:
        """Compare one observation's start with the announced run's; a text the first time a start
        of another run is seen (the evaluator logs it), else None."""
        if self.start_ns is None or self._codec is None:
            return None
        try:
            vec = self._codec.decode(raw)
        except MessageError:
            return None  # malformed: counted by the scoring as such
        self.checked += 1
        start = vec.stamp_ns - (vec.trajectory * self.horizon + vec.step) * self.dt_ns
        if start == self.start_ns:
            return None
        key = start if start in self.foreign or len(self.foreign) < MAX_STARTS else None
        first = key not in self.foreign
        self.foreign[key] = self.foreign.get(key, 0) + 1
        if not first:
            return None
        other = "an unannounced start" if key is None else f"start_ns {start}"
        return (
            f"observation {vec.trajectory}/{vec.step} belongs to another run ({other}, announced "
            f"start_ns {self.start_ns}): two publishers on one topic; the recording mixes runs"
        )

    @property
    def mixed(self) -> bool:
        return bool(self.foreign) or len(self.announcements) > 1 or self.started > 1

    def report(self) -> list[str]:
        """The end-of-run lines (empty when every checked observation belonged to the announced run)."""
        if not self.mixed:
            return []
        n = sum(self.foreign.values())
        lines = [
            f"MIXED RUNS: {n} of {self.checked} observations belong to another run than the one announced "
            f"(start_ns {self.start_ns}); {len(self.announcements)} runs announced on /scenario, "
            f"run_status 'started' {self.started} times. The table scores what the announced run's "
            "identities received, whichever publisher sent them: do not trust it; run one simulator "
            "per namespace or ROS_DOMAIN_ID."
        ]
        for start, count in sorted(self.foreign.items(), key=lambda kv: -kv[1]):
            lines.append(f"  {count} observations of start_ns {start if start is not None else '(others)'}")
        return lines
