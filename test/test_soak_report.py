"""benchmarks/soak.py's memory figures: the RSS slope after the warm-up (least squares over every
sample) and its row in the report, on synthetic samples (no ROS: the soak itself is a measurement)."""

from __future__ import annotations

import pytest

from conftest import load_script


@pytest.fixture(scope="module")
def soak():
    return load_script("benchmarks/soak.py")


def test_the_slope_is_the_least_squares_trend_not_last_minus_first(soak):
    flat = [(t, 200.0 + (3.0 if t == 120 else 0.0)) for t in range(60, 600, 10)]  # one sample in a GC
    assert abs(soak.rss_slope(flat)) < 0.002  # one spike among 54 samples is not a trend
    leak = [(t, 100.0 + 0.02 * t) for t in range(60, 600, 10)]
    assert soak.rss_slope(leak) == pytest.approx(0.02)
    assert soak.rss_slope([(0.0, 1.0), (1.0, 2.0)]) is None  # too few samples for a trend


def test_the_report_prints_the_slope_per_node(soak):
    r = {
        "command": "benchmarks/soak.py --minutes 1",
        "scenario": "bearings",
        "methods": ["ekf"],
        "observations": 100,
        "rate_hz": 500.0,
        "streaming_s": 60.0,
        "run_s": 70.0,
        "simulator": "ok",
        "load1": {"min": 1.0, "mean": 1.0, "max": 1.0},
        "cores": 2,
        "returncodes": {},
        "warmup_s": 50.0,
        "memory": {
            "estimator_ekf": {
                "slope_mib_per_s": 0.00031,
                "samples_after_warmup": 12,
                "rss_warm_mib": 200.0,
                "rss_end_mib": 200.1,
                "rss_max_mib": 200.2,
                "growth_mib": 0.1,
                "growth_mib_per_h": 1.0,
            },
            "evaluator": None,
        },
        "estimators": {},
        "streams": {},
        "diagnostics": {},
    }
    text = soak.report(r)
    assert "| estimator_ekf | 200.0 | 200.1 | 200.2 | 0.1 | 1.0 | 0.0003 (12) |" in text
    assert "| evaluator | - | - | - | - | - | no sample after the warm-up |" in text


def test_the_report_prints_what_the_heap_trims_cost(soak):
    base = {k: 0 for k in ("estimates", "not_estimated", "bad", "oversize", "duplicates", "out_of_order")}
    base.update({k: 0 for k in ("unconfirmed", "gap_steps", "method_failures", "quarantined", "restarts")})
    trim = {"period_s": 10.0, "calls": 24, "released": 23, "mean_ms": 2.087, "max_ms": 7.984}
    r = {
        "command": "benchmarks/soak.py --minutes 4",
        "scenario": "bearings",
        "methods": ["ekf", "ukf"],
        "observations": 100,
        "rate_hz": 500.0,
        "streaming_s": 240.0,
        "run_s": 250.0,
        "simulator": "ok",
        "load1": {"min": 1.0, "mean": 1.0, "max": 1.0},
        "cores": 2,
        "returncodes": {},
        "warmup_s": 50.0,
        "memory": {},
        "estimators": {
            "ekf": {**base, "latency_p50_ms": None, "latency_p99_ms": None, "heap_trim": trim},
            "ukf": {**base, "latency_p50_ms": None, "latency_p99_ms": None, "heap_trim": None},  # trims off
        },
        "streams": {},
        "diagnostics": {},
    }
    text = soak.report(r)
    assert "| ekf | 24 (10) | 23 | 2.087 | 7.984 |" in text
    assert "| ukf | " not in text.split("heap trims")[1]  # no row for a node that did not trim
