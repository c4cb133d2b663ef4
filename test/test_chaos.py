"""The fault-injection harness (scripts/chaos.py), short: four of its cases through the live chain.

Marked slow (about two minutes on 2 cores): ``pytest -m "not slow"`` leaves it out. The whole harness:
``python scripts/chaos.py`` (every case, a table).
"""

from __future__ import annotations

import pytest

from conftest import load_script

pytest.importorskip("rclpy")
pytestmark = [pytest.mark.slow, pytest.mark.ros]  # minutes of live ROS 2 runs


@pytest.mark.parametrize("case", ["forged-trajectory", "step-1e9", "restart", "oversize"])
def test_the_live_chain_survives_the_case(case, tmp_path):
    chaos = load_script("scripts/chaos.py")
    (spec,) = [c for c in chaos.CASES if c.name == case]
    row = chaos.run_case(spec, tmp_path)
    assert row["verdict"] == "PASS", row
    assert not row["tracebacks"] and row["ukf_rmse"] is not None
    if case == "restart":
        assert row["publisher_restarts"] == {"ekf": 1, "ukf": 1}  # detected in-band, with a log line
        log = (tmp_path / case / "ukf.log").read_text()
        assert "the publisher restarted" in log
    else:
        assert row["worst_level"]["ukf"] >= 1  # the diagnostics said WARN (or ERROR), never a silent OK
