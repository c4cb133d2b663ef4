"""The estimator node's staying-current counters and their diagnostics (no ROS)."""

from __future__ import annotations

from neural_estimator.nodes.estimator_stats import OK, WARN, EstimatorStats, diagnostic_values, health, stats_summary


def test_a_node_that_falls_behind_says_so():
    s = EstimatorStats()
    s.window(0.0)
    s.estimated = 100
    s.delay.extend([0.002] * 100)  # observations answered within 2 ms
    s.wakeups, s.max_batch = 40, 7
    w = s.window(1.0)
    assert health(s, w, waiting=False, foreign=set(), delay_warn=0.1) == (OK, [])
    s.delay.extend([0.5] * 10)  # then half a second behind
    w = s.window(2.0)
    level, problems = health(s, w, waiting=False, foreign=set(), delay_warn=0.1)
    assert level == WARN and problems == ["behind: observations wait 500 ms (p99) for their estimate"]
    assert health(s, w, waiting=False, foreign=set(), delay_warn=0.0) == (OK, [])  # 0: no warning
    s.late_dropped = 30
    w = s.window(3.0)
    level, problems = health(s, w, waiting=False, foreign=set(), delay_warn=0.1)
    assert level == WARN and problems == ["behind: 30 late observations dropped"]
    w = s.window(4.0)  # nothing new in this window: back to OK
    assert health(s, w, waiting=False, foreign=set(), delay_warn=0.1) == (OK, [])
    values = diagnostic_values(s, w, "gru")
    assert values["late observations dropped"] == "30"
    assert values["wake-ups"] == "40" and values["largest backlog taken"] == "7"
    assert float(values["observation delay p99 since start (ms)"]) >= 2.0
    summary = stats_summary(s, "/estimator_gru", "gru")
    assert summary["late_dropped"] == 30 and summary["max_batch"] == 7 and summary["delay_p50_ms"] > 1.9
