"""Estimation per observation message: the one code path of the live estimator node and of replay.

:class:`OnlineEstimator` turns one observation message (CDR bytes, layout of
:mod:`neural_estimator.stream.messages`) into the estimate message (and covariance message) of that
step. The estimator node calls it from its subscription callback; bag replay
(:func:`neural_estimator.evaluation.replay.replay`) calls it for every observation of a bag at full speed,
without DDS. Same bytes in, same calls, same estimates out.

Stream rules (one estimator, B = 1), applied in arrival order (replay uses the bag's order, the
order a live node received the messages in, so both give the same estimates):

- the first message (or the first after a reset) starts a stream: the estimator is reset to its prior;
- the natural successor of the last processed message (the next step of its trajectory, or, where
  the run's horizon is known, step 0 of the next trajectory after the last step), stamped later,
  is estimated at once; an exact repeat (same identity and stamp) is skipped as ``duplicate``;
- anything else is a jump (a later or earlier trajectory, a step forward past a gap or back, a
  stamp that went back) and no single message is trusted with one: it is *held* (quarantined,
  at most ``confirm - 1`` messages) until the following messages agree with it (``confirm``
  messages in all: a later step of its trajectory or its successor), or ``quarantine_seconds``
  pass with nothing refuting it (:meth:`OnlineEstimator.poll`; :meth:`OnlineEstimator.flush` at
  the end of the input). If instead the current stream goes on ``confirm`` more messages, the
  held ones are dropped (``stale`` when they were older than the stream, late deliveries;
  ``unconfirmed`` otherwise); a held message that becomes the next step of the current stream
  (reordered delivery) is estimated in order. An accepted jump within the trajectory is a gap;
  any other starts a new stream from the prior (``new_run`` when its stamps went back: a
  restarted publisher). A message whose y_k is not finite carries no observation, so it is no
  evidence for a jump: it is never held and never confirms one (dropped at once, ``stale`` or
  ``unconfirmed``); only the current stream's successor is estimated from it (predict only).
  So one stray, forged or corrupted identity costs at most itself, any number of corrupt
  (non-finite) ones cost only themselves, never the real stream, and a restarted publisher's new
  run takes over after ``confirm`` messages with observations;
- a gap (a step later than the next one, accepted) means observations were lost: the missing steps are run as
  predict-only steps (observation NaN, the last received control held), so that the estimate of
  step k is still an estimate of x_k. The bridge is bounded: more than ``max_gap`` missing steps,
  or predict-only steps running longer than ``max_gap_seconds``, restart the stream from the prior
  at this message, so one accepted step jump costs at most about ``max_gap_seconds``;
- a non-finite value in y_k is used as "no observation" (filters predict only, neural models see
  their training mean, per the estimator contract) and reported; a non-finite control, wrong names
  or widths, an empty or unparsable message raise :class:`~neural_estimator.bags.errors.MessageError`
  and leave the estimator state untouched.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import NamedTuple

import numba as nb
import numpy as np

from neural_estimator.stream import messages as MSG
from neural_estimator.stream.errors import MessageError
from neural_estimator.methods import table
from neural_estimator.methods.registry import Estimator, EstimatorError

DEFAULT_MAX_GAP = 1_000
DEFAULT_MAX_GAP_SECONDS = 0.25
DEFAULT_CONFIRM = 2  # a jump is accepted when the message after it agrees
DEFAULT_QUARANTINE_SECONDS = 0.5  # ... or when nothing refuted it for this long


class StepResult(NamedTuple):
    """Outcome of one observation message (a held message has two: ``held``, then its release).

    Immutable; a NamedTuple rather than a frozen dataclass because it is made once per message and
    a frozen dataclass's fourteen guarded attribute writes cost more than the rest of its making."""

    status: str  # see STATUSES
    trajectory: int
    step: int
    stamp_ns: int
    estimate: bytes | None = None  # estimate message (when estimated)
    covariance: bytes | None = None  # covariance message (when estimated and published)
    x_hat: np.ndarray | None = None  # (dx,)
    reset: bool = False  # this message started a new stream
    filled: int = 0  # missing steps run as predict-only before this one
    restarted: bool = False  # the gap exceeded max_gap (or max_gap_seconds): the stream restarted here
    nonfinite: bool = False  # y_k had NaN/inf: predict only
    diverged: bool = False  # the estimator's stream is diverged (estimates NaN until reset)
    new_run: bool = False  # the stream started here is a new run of the publisher (its stamps went back)
    P: np.ndarray | None = None  # (dx, dx) the method's covariance of this estimate, where it has one
    # observations of the stream between the previous estimate and this one that never arrived
    # (bridged as ``filled`` or skipped by a restart; across a trajectory's end where the horizon is known)
    missed: int = 0


STATUSES = (
    "estimated",  # estimate (and covariance) computed
    "duplicate",  # same identity and stamp as the last processed message: skipped
    "held",  # a jump in the stream, quarantined until the following messages confirm it
    "stale",  # a held message behind the current stream that nothing confirmed (a late message): dropped
    "unconfirmed",  # a held jump that the following messages did not confirm: dropped
)


class _Obs(NamedTuple):
    trajectory: int
    step: int
    stamp_ns: int
    y: np.ndarray  # (1, dy)
    u_prev: np.ndarray  # (1, du)
    finite: bool = True  # y holds no NaN or inf (an observation, not a predict-only step)


@nb.njit(nogil=True, cache=True)
def finite_parts(values: np.ndarray, dy: int) -> tuple[bool, bool]:
    """(every y is finite, every u_prev is finite) of an observation's values [y, u_prev], in one
    pass (two numpy reductions on a few numbers cost ten times more)."""
    y_ok, u_ok = True, True
    for j in range(values.shape[0]):
        if not np.isfinite(values[j]):
            if j < dy:
                y_ok = False
            else:
                u_ok = False
    return y_ok, u_ok


class OnlineEstimator:
    """One estimator (B = 1) fed with observation messages (see the module docstring).

    Args:
        estimator: any of the ten methods, built for the scenario of the stream.
        method: the method name (the estimates' frame_id unless ``frame_id`` is given).
        publish_covariance: build covariance messages where the method has a covariance.
        max_gap: the most missing steps filled with predict-only steps.
        max_gap_seconds: the most seconds spent filling one gap (0 = no time bound).
        frame_id: header.frame_id of the estimate and covariance messages (default: the method).
        confirm: messages that must agree before a jump in the stream is accepted (the jump itself
            included; 1 = accept every jump at once, the rule before quarantine existed).
        quarantine_seconds: the most seconds a jump is held unconfirmed before it is accepted anyway.
        horizon: steps per trajectory where known (the run's announcement): then step 0 of the next
            trajectory right after the last step is the natural successor, not a jump.
    """

    def __init__(
        self,
        estimator: Estimator,
        method: str,
        *,
        publish_covariance: bool = True,
        max_gap: int = DEFAULT_MAX_GAP,
        max_gap_seconds: float = DEFAULT_MAX_GAP_SECONDS,
        frame_id: str | None = None,
        confirm: int = DEFAULT_CONFIRM,
        quarantine_seconds: float = DEFAULT_QUARANTINE_SECONDS,
        horizon: int | None = None,
    ) -> None:
        if confirm < 1 or quarantine_seconds < 0:
            raise EstimatorError(
                f"confirm must be >= 1 and quarantine_seconds >= 0, got {confirm} and {quarantine_seconds}"
            )
        self.estimator = estimator
        self.scenario = estimator.scenario
        self.method = method
        self.publish_covariance = bool(publish_covariance and estimator.has_covariance)
        self.max_gap = int(max_gap)
        self.max_gap_seconds = float(max_gap_seconds)
        self.confirm = int(confirm)
        self.quarantine_seconds = float(quarantine_seconds)
        self.horizon = int(horizon) if horizon else None
        self._obs_labels = MSG.observation_labels(self.scenario)
        self._obs_codec = MSG.VectorCodec(self.scenario.name, self._obs_labels)
        frame = method if frame_id is None else frame_id
        self._est_codec = MSG.VectorCodec(frame, MSG.state_labels(self.scenario))
        self._cov_codec = MSG.VectorCodec(frame, MSG.covariance_labels(self.scenario.dx))
        self._dy = self.scenario.dy
        self.trajectory: int | None = None
        self.step = -1
        self._u_hold = np.zeros((1, self.scenario.du))
        self._last_stamp: int | None = None  # stamp of the last processed message
        self._held: list[_Obs] = []  # the quarantined jump (at most ``confirm - 1`` messages)
        self._held_since = 0.0  # when its first message arrived (the caller's clock)
        self._since_held = 0  # messages of the current stream processed since then
        self._last_arrival: float | None = None  # when the current stream's last message arrived
        self._interval: float | None = None  # its typical inter-arrival time (running mean)

    @property
    def max_message_bytes(self) -> int:
        """The size bound of an observation message: larger ones are refused before decoding."""
        return self._obs_codec.max_bytes

    @property
    def held(self) -> int:
        """Messages now in quarantine."""
        return len(self._held)

    def reset(self) -> None:
        """Forget the current stream (and any quarantined message); the next message starts from the prior."""
        self.trajectory = None
        self.step = -1
        self._last_stamp = None
        self._held = []

    # ---- identity ------------------------------------------------------------------------------------
    def _succeeds(self, m: _Obs, trajectory: int, step: int, stamp_ns: int) -> bool:
        """True when ``m`` is the natural successor of (trajectory, step, stamp): the next step of
        the trajectory, or step 0 of the next one after its last step (horizon known), stamped later."""
        if m.stamp_ns <= stamp_ns:
            return False
        if m.trajectory == trajectory:
            return m.step == step + 1
        return self.horizon is not None and step == self.horizon - 1 and m.trajectory == trajectory + 1 and m.step == 0

    def _ahead(self, m: _Obs) -> bool:
        """True for a later step of the current trajectory, stamped later (a forward gap)."""
        return m.trajectory == self.trajectory and m.step > self.step and m.stamp_ns > self._last_stamp

    def _continues_held(self, m: _Obs) -> bool:
        """True when ``m`` agrees with the quarantined jump: later in its trajectory (gaps allowed)
        or its natural successor, stamped later; and it is not rather the current stream going on
        past a gap (that confirms only a held forward jump of the current trajectory)."""
        last = self._held[-1]
        if self._ahead(m) and not self._ahead(self._held[0]):
            return False
        if m.trajectory == last.trajectory:
            return m.step > last.step and m.stamp_ns > last.stamp_ns
        return self._succeeds(m, last.trajectory, last.step, last.stamp_ns)

    def _behind(self, m: _Obs) -> bool:
        """True for a message older than the current stream (a late message rather than a jump)."""
        if m.trajectory != self.trajectory:
            return m.trajectory < self.trajectory and m.stamp_ns <= self._last_stamp
        return m.step < self.step and m.stamp_ns < self._last_stamp

    # ---- the rules -----------------------------------------------------------------------------------
    def feed(self, raw: bytes | memoryview, now: float | None = None) -> list[StepResult]:
        """Consume one observation message: the results it caused, in order (an estimate of this
        message, its ``held`` status, or a ``duplicate``; plus quarantined messages it released or
        dropped). ``now`` (seconds, any monotonic clock; default time.monotonic) times the quarantine.
        Raises MessageError for a message that cannot be used (the state is untouched)."""
        now = time.monotonic() if now is None else float(now)
        m = self._decode(raw)
        out: list[StepResult] = []
        if self.trajectory is None:  # the first message (or after a reset) starts a stream
            out.append(self._estimate(m, new=True))
            self._last_arrival, self._interval = now, None
        elif self._succeeds(m, self.trajectory, self.step, self._last_stamp):
            out.append(self._estimate(m, new=m.trajectory != self.trajectory))
            self._arrived(now)
            self._since_held += 1
            self._release_successors(out)
            if self._held and self._since_held >= self.confirm:  # the stream went on without the jump
                out += self._drop_held()
        elif m.trajectory == self.trajectory and m.step == self.step and m.stamp_ns == self._last_stamp:
            out.append(StepResult("duplicate", m.trajectory, m.step, m.stamp_ns))
        elif not m.finite:  # a jump carried by no observation is no evidence for it: dropped at once
            out.append(StepResult("stale" if self._behind(m) else "unconfirmed", m.trajectory, m.step, m.stamp_ns))
        elif self._held and self._continues_held(m):
            self._held.append(m)
            if len(self._held) >= self.confirm:  # confirmed: the jump and this message are estimated
                out += self._accept_held()
            else:
                out.append(StepResult("held", m.trajectory, m.step, m.stamp_ns))
        else:
            out += self._drop_held()
            self._held, self._held_since, self._since_held = [m], now, 0
            out.append(StepResult("held", m.trajectory, m.step, m.stamp_ns))
            if self.confirm <= 1:
                out += self._accept_held()
        return out

    def poll(self, now: float | None = None) -> list[StepResult]:
        """Accept a held jump when the stream fell silent: no message of the current stream since it
        arrived, for ``quarantine_seconds`` or four of the stream's inter-arrival times, whichever is
        longer (so a slow stream's next message still gets to refute it). Call it periodically."""
        now = time.monotonic() if now is None else float(now)
        wait = max(self.quarantine_seconds, 4 * (self._interval or 0.0))
        if self._held and not self._since_held and now - self._held_since >= wait:
            return self._accept_held()
        return []

    def _arrived(self, now: float) -> None:
        if self._last_arrival is not None and now >= self._last_arrival:
            gap = now - self._last_arrival
            self._interval = gap if self._interval is None else 0.9 * self._interval + 0.1 * gap
        self._last_arrival = now

    def flush(self) -> list[StepResult]:
        """Accept a held jump now (the end of the input: nothing more can confirm or refute it)."""
        return self._accept_held() if self._held else []

    def _release_successors(self, out: list[StepResult]) -> None:
        """Held messages that became the current stream's next steps (reordered delivery) are processed."""
        while self._held and self._succeeds(self._held[0], self.trajectory, self.step, self._last_stamp):
            h = self._held.pop(0)
            out.append(self._estimate(h, new=h.trajectory != self.trajectory))

    def _drop_held(self) -> list[StepResult]:
        held, self._held = self._held, []
        return [
            StepResult("stale" if self._behind(h) else "unconfirmed", h.trajectory, h.step, h.stamp_ns) for h in held
        ]

    def _accept_held(self) -> list[StepResult]:
        """The held jump becomes the stream: a later step of the current trajectory is bridged (or
        restarted) as a gap, anything else starts a new stream from the prior."""
        held, self._held = self._held, []
        first = held[0]
        same = self._ahead(first)
        new_run = self._last_stamp is not None and first.stamp_ns <= self._last_stamp
        out = [self._estimate(first, new=not same, new_run=new_run)]
        out += [self._estimate(h, new=h.trajectory != self.trajectory) for h in held[1:]]
        return out

    def _decode(self, raw: bytes | memoryview) -> _Obs:
        fast = self._obs_codec.decode_values(raw)  # this stream's exact layout: no Vector, no name check
        if fast is None:  # anything else: the full decoding, its checks and their one-line errors
            vec = self._obs_codec.decode(raw)
            fast = vec.stamp_ns, vec.trajectory, vec.step, MSG.check_labels(vec, self._obs_labels, "observation")
        stamp_ns, trajectory, step, values = fast
        y_finite, u_finite = finite_parts(values, self._dy)
        if not u_finite:
            raise MessageError(f"observation {trajectory}/{step}: control u_prev contains NaN or inf")
        return _Obs(trajectory, step, stamp_ns, values[None, : self._dy], values[None, self._dy :], y_finite)

    # ---- one estimator step ------------------------------------------------------------------------
    def _start(self, trajectory: int) -> None:
        self.estimator.reset(1)
        self.trajectory = trajectory
        self.step = -1
        self._u_hold = np.zeros((1, self.scenario.du))

    def _bridge(self, gap: int) -> tuple[int, bool]:
        """Run ``gap`` predict-only steps; (steps run, False), or (0, True) when they would take
        longer than ``max_gap_seconds`` (checked as they run: the cost per step is method-dependent)."""
        nan_y = np.full((1, self._dy), np.nan)
        deadline = time.perf_counter() + self.max_gap_seconds if self.max_gap_seconds > 0 else None
        for i in range(gap):
            self.estimator.step(nan_y, self._u_hold)
            if deadline is not None and time.perf_counter() > deadline and i + 1 < gap:
                return 0, True
        return gap, False

    def _missed(self, m: _Obs, new_run: bool) -> int:
        """Steps of the stream between the last processed message (n', k') and ``m`` = (n, k) that
        never arrived: k - k' - 1 in one trajectory; into a later trajectory with the horizon H
        known, (H - 1 - k') + (n - n' - 1) H + k (a node that fell behind and lost whole
        trajectories from its queue); otherwise (H unknown, a new run, an earlier trajectory) at
        least the k steps of m's trajectory before it."""
        if self.trajectory is None or self.step < 0:
            return 0
        if m.trajectory == self.trajectory and not new_run:
            return max(0, m.step - self.step - 1)
        if self.horizon is not None and m.trajectory > self.trajectory and not new_run and self.step < self.horizon:
            return self.horizon - 1 - self.step + (m.trajectory - self.trajectory - 1) * self.horizon + m.step
        return m.step

    def _estimate(self, m: _Obs, *, new: bool = False, new_run: bool = False) -> StepResult:
        missed = self._missed(m, new_run)
        if new:
            self._start(m.trajectory)
        gap = m.step - self.step - 1
        restarted = False
        if gap > self.max_gap:
            gap, restarted = 0, True
        elif gap:
            gap, restarted = self._bridge(gap)
        if restarted:  # too long to bridge: estimate from the prior from here on
            self._start(m.trajectory)
        try:
            x_hat = self.estimator.step(m.y, m.u_prev)[0]
        except EstimatorError as exc:  # the checks in _decode should make this unreachable
            raise MessageError(f"observation {m.trajectory}/{m.step}: {exc}") from None
        self.step = m.step
        self._last_stamp = m.stamp_ns
        self._u_hold = m.u_prev
        est = self._est_codec.encode(m.stamp_ns, m.trajectory, m.step, x_hat)
        cov = None
        P = None if self.estimator.covariance is None else self.estimator.covariance[0].copy()
        if self.publish_covariance and P is not None:
            cov = self._cov_codec.encode(m.stamp_ns, m.trajectory, m.step, P)
        diverged = bool(self.estimator.diverged[0]) if len(self.estimator.diverged) else False
        return StepResult(
            "estimated",
            m.trajectory,
            m.step,
            m.stamp_ns,
            est,
            cov,
            x_hat,
            reset=new,
            filled=gap,
            restarted=restarted,
            nonfinite=not m.finite,
            diverged=diverged,
            new_run=new_run,
            P=P,
            missed=missed,
        )


def set_torch_threads(methods: Sequence[str], threads: int) -> None:
    """torch intra-op threads for per-message neural steps (B = 1): one thread is 10-25x faster
    than torch's default of one per core on these small matrices; 0 keeps torch's default.
    Only touches torch when a neural method is among ``methods``."""
    if threads < 0:
        raise EstimatorError(f"threads must be >= 0 (0 = torch's default), got {threads}")
    if threads and any(table.has(m, uses_torch=True) for m in methods):
        import torch

        torch.set_num_threads(int(threads))


WARM_UP_STEPS = 3


def warm_up(est, scenario) -> None:
    """A few steps on a zero observation, then a reset: compiled kernels (numba, torch's first-call
    set-up) are built now, not on the first observations, where the EKF's compile took 2.9 s of the
    run's first second (measured). Three steps, not one: the first step from the prior and the
    later ones take different paths (the EKF's second step loaded another kernel, 19 ms, measured).
    The stream starts from the prior anyway (OnlineEstimator resets)."""
    try:
        est.reset(1)
        for _ in range(WARM_UP_STEPS):
            est.step(np.zeros((1, scenario.dy)), np.zeros((1, scenario.du)))
    except Exception:  # a scenario where zeros are not a valid observation: warm up at the first message
        pass
    est.reset(1)
