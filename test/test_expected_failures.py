"""Expected failures are marked in the printed tables, with one line saying why."""

import numpy as np

from neural_estimator import metrics as M
from neural_estimator.evaluation.bag_report import BagReport
from neural_estimator.paper.expected_failures import EXPECTED_FAILURES, MARK, mark_rows, notes


def _report(rng, scale):
    x = rng.standard_normal((4, 10, 2))
    return M.compute_metrics(x, x + scale * rng.standard_normal(x.shape))


def test_bag_summary_marks_the_expected_failure_and_says_why(tmp_path):
    rng = np.random.default_rng(0)
    rep = BagReport(
        path=tmp_path / "run.mcap",
        scenario="lorenz96",
        n_trajectories=4,
        horizon=10,
        dt=0.05,
        reports={"ekf": _report(rng, 0.05), "pf": _report(rng, 5.0)},
        bag={},
    )
    text = rep.summary()
    rows = {line.split(" ", 1)[0]: line for line in text.splitlines()}
    assert rows["pf"].endswith(MARK) and not rows["ekf"].endswith(MARK)
    why = [line for line in text.splitlines() if line.startswith(f"{MARK} pf:")]
    assert len(why) == 1 and EXPECTED_FAILURES["lorenz96", "pf"] in why[0]


def test_no_marks_where_nothing_is_expected_to_fail():
    table = "Method RMSE\npf 0.1\n"
    assert mark_rows(table, "bearings") == table  # the bearings PF works (docs/fidelity.md)
    assert notes("bearings", ["ekf", "pf"]) == []
