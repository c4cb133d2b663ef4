"""The estimator node's reporting rules, without ROS (neural_estimator/nodes/estimator_stats.py)."""

from __future__ import annotations

import json

from neural_estimator.nodes.estimator_stats import (
    ERROR,
    OK,
    WARN,
    EstimatorStats,
    diagnostic_values,
    health,
    stats_summary,
)


def test_health_levels_and_problems_over_a_window():
    s = EstimatorStats()
    first = s.window(0.0)
    assert health(s, first, waiting=False, foreign=set()) == (OK, [])
    assert health(s, first, waiting=True, foreign=set()) == (WARN, ["waiting for the scenario"])
    s.estimated, s.bad, s.gap_steps = 100, 2, 5
    s.latency.extend([0.001] * 100)
    w = s.window(1.0)
    level, problems = health(s, w, waiting=False, foreign={"/x (std_msgs/msg/String)"})
    assert level == WARN and problems == [
        "2 bad messages",
        "5 missing steps",
        "foreign publishers: /x (std_msgs/msg/String)",
    ]
    assert w["rate"] == 100.0 and abs(w["p50"] - 0.001) < 1e-12
    assert health(s, s.window(2.0), waiting=False, foreign=set()) == (OK, [])  # the window moved on
    s.errors, s.diverged = 1, True
    level, problems = health(s, s.window(3.0), waiting=False, foreign=set())
    assert level == ERROR and problems[0].startswith("diverged") and "failures inside the method" in problems[1]


def test_values_and_the_stats_file_are_plain_text_and_json():
    s = EstimatorStats(estimated=3, bad=1, early=1)
    s.latency.extend([0.002, 0.004])
    values = diagnostic_values(s, s.window(1.0), "ukf")
    assert (
        values["bad messages"] == "2" and values["method"] == "ukf" and all(isinstance(v, str) for v in values.values())
    )
    summary = stats_summary(s, "/est", "ukf")
    assert json.loads(json.dumps(summary))["latency_samples"] == 2 and summary["bad"] == 2
