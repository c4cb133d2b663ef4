"""Real-time scheduling of node processes (nodes/realtime.py): the request, and what applying it does."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from neural_estimator.nodes.realtime import REALTIME_ENV, RealtimeError, apply_realtime_priority, requested_priority


@pytest.mark.parametrize("raw, want", [("", 0), ("0", 0), (" 10 ", 10), ("99", 99)])
def test_the_requested_priority(raw, want):
    assert requested_priority({REALTIME_ENV: raw}) == want
    assert requested_priority({}) == 0


@pytest.mark.parametrize("raw", ["ten", "1.5", "-1", "100"])
def test_a_bad_priority_is_one_line_naming_the_variable(raw):
    with pytest.raises(RealtimeError, match=f"{REALTIME_ENV} must be an integer from 1 to 99"):
        requested_priority({REALTIME_ENV: raw})


def test_applying_it_makes_the_process_fifo_or_says_why_not():
    # in a child process: the test runner's own scheduling is left alone
    code = (
        "import json, os\n"
        "from neural_estimator.nodes.realtime import apply_realtime_priority\n"
        "ok, line = apply_realtime_priority(5)\n"
        "print(json.dumps({'ok': ok, 'line': line, 'fifo': os.sched_getscheduler(0) == os.SCHED_FIFO,\n"
        "                  'prio': os.sched_getparam(0).sched_priority}))\n"
    )
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, env=env)
    assert out.returncode == 0, out.stderr
    res = json.loads(out.stdout.strip().splitlines()[-1])
    if res["ok"]:  # allowed here (root or CAP_SYS_NICE)
        assert res["fifo"] and res["prio"] == 5 and "SCHED_FIFO priority 5" in res["line"]
    else:  # refused: normal scheduling, and the line says what is needed
        assert not res["fifo"] and "refused" in res["line"] and "normal priority" in res["line"]


def test_zero_changes_nothing():
    assert apply_realtime_priority(0) == (False, "normal scheduling")
