"""scripts/neural_scoreboard.py: the table of the shipped neural models beside the paper's."""

import json

import pytest
from conftest import load_script


@pytest.fixture(scope="module")
def board():
    return load_script("scripts/neural_scoreboard.py")


def _row(rmse, paper):
    return {"rmse": rmse, "iqr": 0.001, "paper": paper, "budget": "20 x 2000"}


def test_best_keeps_ties_and_skips_missing_and_infinite(board):
    assert board.best({"mamba": 0.052, "mamba2": 0.052, "gru": 0.127}) == ["mamba", "mamba2"]
    assert board.best({"gru": None, "lstm": float("inf"), "gpt2": 3.0}) == ["gpt2"]
    assert board.best({"gru": None}) == []


def test_verdict_counts_scenarios_where_an_ssm_leads_and_states_the_l96_distance(board):
    rows = {
        "lorenz96": {"gru": _row(0.15, 0.127), "mamba": _row(0.088, 0.052), "mamba2": _row(0.07, 0.052)},
        "nlink": {"gru": _row(0.12, 0.40), "mamba2": _row(0.17, 0.092)},
    }
    text = "\n".join(board.verdict(rows))
    assert "an SSM is the best neural model in 1 of 2 scenarios (lorenz96)" in text
    assert "nlink: best neural gru (0.12); the paper's: mamba2" in text
    assert "Lorenz 96 mamba: 0.088 against the target 0.08 (10 % above" in text
    assert "Lorenz 96 mamba2: 0.07 against the target 0.08 (met" in text
    md = board.table(rows, ["gru", "mamba", "mamba2"])
    assert "| mamba2 | **0.07 ± 0.001** · **0.052**" in md  # ours and the paper's best both bold
    assert "| mamba | – |" not in md and md.count("\n") == 4


def test_runs_the_shipped_models_and_writes_markdown_and_json(board, tmp_path, monkeypatch):
    monkeypatch.setenv("NEURAL_ESTIMATOR_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "board.md"
    args = ["--scenarios", "lorenz96", "--methods", "gru,mamba", "--trajectories", "2", "--sets", "2"]
    assert board.main([*args, "--out", str(out), "--quiet"]) == 0
    rows = json.loads(out.with_suffix(".json").read_text())
    assert set(rows["lorenz96"]) == {"gru", "mamba"}
    for r in rows["lorenz96"].values():
        assert 0 < r["rmse"] < 3.62  # better than the prior mean (climatology) on Lorenz 96
        assert r["paper"] in (0.127, 0.052)
    text = out.read_text()
    assert "against the target 0.08" in text and "Scored steps: 10.." in text and "this project's choice" in text
    assert rows["lorenz96"]["mamba"]["rmse_every_step"] > 0  # the Lorenz 96 SSMs also over every step
    assert "over every step" in text and "rmse_every_step" not in rows["lorenz96"]["gru"]


def test_budget_names_the_recipe_the_loss_units_and_a_bounded_context(board):
    card = {
        "data": {"windows_per_epoch": 20000},
        "training": {"epochs_run": 59, "recipe": {"epochs": 500, "loss_units": "state", "val_context": 100}},
    }
    assert board.budget(card) == "full (59 ep), state loss, ctx 100"
    card["training"]["recipe"]["val_context"] = 0  # validated the paper's way
    assert board.budget(card) == "full (59 ep), state loss"
    small = {"data": {"windows_per_epoch": 2000}, "training": {"recipe": {"epochs": 20}}}  # an older card
    assert board.budget(small) == "20 x 2000, norm. loss"


def test_verdict_names_the_best_continuous_model_where_a_bounded_variant_leads(board):
    rows = {
        "bearings": {"gru": {**_row(272.0, 191.9), "context": 100}, "mamba2": _row(297.0, 177.8)},
        "lorenz96": {"gru": _row(0.07, 0.127), "mamba": _row(0.051, 0.052)},
    }
    text = "\n".join(board.verdict(rows))
    assert "bearings: best neural gru (272, context 100; run continuously: mamba2 297); the paper's: mamba2" in text
    assert "an SSM is the best neural model in 1 of 2 scenarios (lorenz96)" in text
    assert "among the models run continuously, as the paper runs them" in text and "2 of 2 (bearings, lorenz96)" in text
    only_variant = {"bearings": {"gru": rows["bearings"]["gru"]}}  # e.g. --methods gru: no continuous model to name
    assert "run continuously: none in this selection" in "\n".join(board.verdict(only_variant))
    rows["bearings"]["gru"]["context"] = 0  # the same figures, both run the paper's way: one count, no second line
    text = "\n".join(board.verdict(rows))
    assert "run continuously" not in text and "1 of 2 scenarios" in text


def test_bounded_context_and_outlier_cells_are_marked_and_explained_once(board):
    rows = {
        "bearings": {
            "gru": {**_row(272.4, 191.9), "context": 100, "full_rmse": 272.4},
            "mamba2": {**_row(296.6, 177.8), "context": 0, "full_rmse": 296.6},
        },
        "nlink": {"mamba": {**_row(0.11, 0.093), "context": 0, "full_rmse": 0.43}},
    }
    md = board.table(rows, ["gru", "mamba", "mamba2"])
    row = {line.split("|")[1].strip(): line for line in md.splitlines()[2:]}
    assert "[c]" in row["gru"] and "[o]" not in row["gru"]
    assert "[o] (full 0.43)" in row["mamba"] and "[c]" not in row["mamba"]
    assert "[c]" not in row["mamba2"] and "[o]" not in row["mamba2"]
    legend = board.legend(rows)
    assert [line.split()[1] for line in legend] == ["[c]", "[o]"] and "at most 100 steps" in legend[0]
    assert board.legend({"nlink": {"gru": {**_row(0.1, 0.4), "full_rmse": 0.1}}}) == []
