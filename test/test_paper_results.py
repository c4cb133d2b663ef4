"""The paper's numbers shipped as data equal the paper's LaTeX tables, and are self-consistent."""

from __future__ import annotations

import json
import os
import math
from pathlib import Path

import pytest

from neural_estimator.paper import RESULTS_FILE, paper_results, paper_value
from neural_estimator.paper.transcribe import TranscriptionError, cell_value, transcribe

HERE = Path(__file__).parent
SHIPPED_TABLES = HERE / "data" / "paper_tables.tex"  # verbatim copy of the paper's tables
# The paper's LaTeX source, where one has it: NEURAL_ESTIMATOR_PAPER_TEX=/path/to/paper.tex
SHARED_PAPER = Path(os.environ.get("NEURAL_ESTIMATOR_PAPER_TEX", ""))


def _file_data():
    return json.loads(RESULTS_FILE.read_text())


def test_shipped_data_equals_the_shipped_latex_tables():
    assert transcribe(SHIPPED_TABLES.read_text()) == _file_data()


def test_shipped_data_equals_the_paper_source():
    if not SHARED_PAPER.is_file():
        pytest.skip("NEURAL_ESTIMATOR_PAPER_TEX names no file (the shipped copy of its tables is checked above)")
    assert transcribe(SHARED_PAPER.read_text()) == _file_data()


def test_hand_checked_cells():
    # read off the PDF by hand: the parser must not shift columns or rows
    assert paper_value("accuracy_main", "ballistic", "ekf") == {"rmse": 5.289, "nrmse": 1.571}
    assert paper_value("accuracy_main", "quadrotor", "mamba2") == {"rmse": 5.702, "nrmse": 0.175}
    assert math.isinf(paper_value("accuracy_main", "bearings", "enkf")["rmse"])
    assert paper_value("extended", "nlink", "pf", "nrmse") is not None
    assert paper_value("extended", "ballistic", "enkf", "full_rmse") == {"median": 2.166, "iqr": 0.068}
    assert paper_value("extended", "bearings", "enkf", "drift_ratio") is None
    assert paper_value("stability", "nlink", "pf") == {"outlier_ratio": 0.272, "drift_ratio": 71.143}
    assert paper_value("data_ratio_main", "1", "filterformer") == 0.339
    assert paper_value("runtime_full", "cpu", "ballistic", "lstm") == 1466.3
    assert paper_value("runtime_full", "cpu", "l96", "mamba") is None  # no such scenario id
    assert paper_value("runtime_full", "cpu", "lorenz96", "mamba") is None  # the paper's N/A
    assert paper_value("runtime_summary", "pf") == {"cpu": 1372.4, "gpu": 1654.9, "cpu_gpu_ratio": 0.83}
    assert paper_value("nrmse_avg_all", "ekf") == {"median": 0.014, "iqr": 0.993}


def test_tables_agree_with_each_other():
    """Cross-checks between tables the paper derives from one another (catch transcription slips)."""
    d = paper_results()
    for s in d["scenarios"]:
        m2 = d["accuracy_main"][s]["mamba2"]["rmse"]
        for m in d["methods"]:
            acc, ext, stab = d["accuracy_main"][s][m], d["extended"][s][m], d["stability"][s][m]
            # the main table is the extended tables' medians
            for k in ("rmse", "nrmse"):
                assert (acc[k] == ext[k]) if math.isinf(acc[k]) else acc[k] == ext[k]["median"], (s, m, k)
            assert stab == {"outlier_ratio": ext["outlier_ratio"], "drift_ratio": ext["drift_ratio"]}, (s, m)
            # relative score = 100 RMSE(Mamba-2) / RMSE(m), to the table's one decimal (RMSEs rounded to 3)
            # (the rounding interval of both RMSEs, +-0.0005, bounds it: L96's 0.052 / 0.049 -> 104 to 108)
            score = d["relative_score"][s][m]
            if math.isinf(acc["rmse"]):
                assert score == 0.0, (s, m)
                continue
            lo = 100 * (m2 - 5e-4) / (acc["rmse"] + 5e-4) - 0.05
            hi = 100 * (m2 + 5e-4) / (acc["rmse"] - 5e-4) + 0.05
            assert lo <= score <= hi, (s, m, score, lo, hi)
    # the 20:1 column is the main comparison: median NRMSE across scenarios of accuracy_main
    for m in d["data_ratio_main"]["20"]:
        per_scenario = sorted(d["accuracy_main"][s][m]["nrmse"] for s in d["scenarios"])
        assert d["data_ratio_main"]["20"][m] == per_scenario[2] == d["nrmse_avg_all"][m]["median"], m
    # runtime summary's CPU/GPU averages are the per-scenario table's means
    for m, row in d["runtime_summary"].items():
        for dev in ("cpu", "gpu"):
            vals = [d["runtime_full"][dev][s][m] for s in d["scenarios"]]
            if row[dev] is None:
                assert all(v is None for v in vals), (m, dev)
            else:
                # both tables round to 0.1: the mean of five rounded cells and the rounded mean differ by <= 0.1
                assert row[dev] == pytest.approx(sum(vals) / len(vals), abs=0.1 + 1e-9), (m, dev)


def test_paper_results_is_a_fresh_copy_and_inf_is_a_float():
    a = paper_results()
    a["accuracy_main"]["ballistic"]["ekf"]["rmse"] = -1
    assert paper_results()["accuracy_main"]["ballistic"]["ekf"]["rmse"] == 5.289
    assert a["extended"]["bearings"]["enkf"]["rmse"] == float("inf")


def test_transcription_errors_name_the_problem():
    with pytest.raises(TranscriptionError, match="tab:accuracy_main"):
        transcribe("no tables here")
    with pytest.raises(TranscriptionError, match="not a number"):
        cell_value("abc")
    assert cell_value(r"\textbf{0.631$\pm$0.049}") == {"median": 0.631, "iqr": 0.049}
    assert cell_value(r"\textit{N/A}") is None and cell_value(r"$\infty$") == "inf"
