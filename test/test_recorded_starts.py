"""How the filters started travels with the bag: `metrics` on a bag made with --init observation
(replay, or the live evaluator's `starts`) marks the rows [y] as the run itself did."""

from __future__ import annotations

from pathlib import Path

from neural_estimator.evaluation.bag_report import recorded_starts
from neural_estimator.cli import main

BAG = Path(__file__).resolve().parents[1] / "bags" / "lorenz96.mcap"


def test_metrics_on_a_bag_keeps_the_start_marks(tmp_path, capsys):
    out = tmp_path / "obs.mcap"
    assert main(["replay", str(BAG), "--methods", "ekf", "--init", "observation", "--out", str(out)]) == 0
    assert recorded_starts(out) == {"ekf": "observation"}
    capsys.readouterr()
    assert main(["metrics", str(out)]) == 0
    text = capsys.readouterr().out
    assert "ekf [y]" in text and "[y] filter started from the first observation" in text
    # a run from the prior records nothing and is marked as before
    prior = tmp_path / "prior.mcap"
    assert main(["replay", str(BAG), "--methods", "ekf", "--out", str(prior)]) == 0
    assert recorded_starts(prior) == {}
    capsys.readouterr()
    assert main(["metrics", str(prior)]) == 0
    assert "[y]" not in capsys.readouterr().out
    # --start still overrides what the bag says
    assert main(["metrics", str(out), "--start", "ekf=prior"]) == 0
    assert "ekf [y]" not in capsys.readouterr().out
