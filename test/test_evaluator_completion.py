"""The evaluator's end of run counts only the streams it scores: with a periodic
/diagnostics recorded beside the run and one estimate stream short, every diagnostics message
counted as progress, so completion_timeout never fired (the soak's evaluator waited 585 s for its
wall-clock limit). The decision (EvaluatorNode._check_done) runs here on a stand-in node whose clock
is advanced by hand."""

from __future__ import annotations

import types

import pytest

pytestmark = pytest.mark.ros  # imports the node module (rclpy)


def _evaluator(monkeypatch, clock):
    from neural_estimator.nodes import evaluator_node as E

    monkeypatch.setattr(E.time, "monotonic", lambda: clock[0])
    finished = []
    ev = types.SimpleNamespace(
        p=types.SimpleNamespace(idle_timeout=5.0, completion_timeout=30.0),
        ns="/",
        required_methods=("ekf", "gru"),
        expected=100,
        complete_at=0.0,
        _progress=(0, 0.0),
        closed=False,
        get_logger=lambda: types.SimpleNamespace(warning=lambda text: None, info=lambda text: None),
        _finish=lambda: finished.append(clock[0]),
    )
    ev.counts = {"/observation": 100, "/estimates/ekf": 100, "/estimates/gru": 60, "/diagnostics": 0}
    ev.subs = dict.fromkeys(ev.counts)
    ev._required = lambda: E.EvaluatorNode._required(ev)
    return E, ev, finished


def test_a_periodic_topic_does_not_hold_off_the_completion_timeout(monkeypatch):
    clock = [0.0]
    E, ev, finished = _evaluator(monkeypatch, clock)
    while clock[0] < 120.0 and not finished:
        clock[0] += 1.0
        ev.counts["/diagnostics"] += 1  # 1 Hz diagnostics, recorded, not scored
        E.EvaluatorNode._check_done(ev)
    assert finished and 30.0 < finished[0] <= 32.0  # the GRU stream, short, gave up on after 30 s


def test_a_scored_stream_that_still_moves_is_waited_for(monkeypatch):
    clock = [0.0]
    E, ev, finished = _evaluator(monkeypatch, clock)
    for _ in range(39):  # the GRU catches up one message a second: progress, no time-out
        clock[0] += 1.0
        ev.counts["/estimates/gru"] += 1
        E.EvaluatorNode._check_done(ev)
    assert not finished
    clock[0] += 1.0
    ev.counts["/estimates/gru"] += 1  # 100: every scored stream complete
    E.EvaluatorNode._check_done(ev)
    assert finished == [40.0]


@pytest.mark.parametrize("messages", ["x", None, -1, 1e308, 10**400, True, [5]])
def test_a_complete_status_with_a_bad_count_is_ignored_not_fatal(monkeypatch, messages):
    """Found by scripts/fuzz_nodes.py: int(status["messages"]) raised inside the recorder's timer
    (a dead evaluator) for "x" or null; such a status is now one warning and ignored."""
    from neural_estimator.stream import messages as MSG

    clock = [0.0]
    E, ev, _ = _evaluator(monkeypatch, clock)
    lines = []
    ev.get_logger = lambda: types.SimpleNamespace(warning=lines.append, info=lambda text: None)
    ev.identity = types.SimpleNamespace(on_started=lambda: None)
    ev.expected = ev.complete_at = None
    E.EvaluatorNode._on_status(ev, MSG.encode_run_status(MSG.STATUS_COMPLETE, messages=messages))
    assert ev.expected is None and ev.complete_at is None
    assert len(lines) == 1 and "not a count, ignored" in lines[0]
