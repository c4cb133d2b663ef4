"""experiments/paper_equivalent_epoch.py: the epoch of our training whose validation loss puts the
network at the paper's figure."""

import math

import pytest
from conftest import ROOT, load_script


@pytest.fixture(scope="module")
def exp():
    return load_script("experiments/paper_equivalent_epoch.py")


def test_an_epochs_rmse_scales_with_the_root_of_its_validation_loss(exp):
    history = [{"val_loss": 4.0}, {"val_loss": 2.0}, {"val_loss": 1.0}, {"val_loss": 1.5}]
    curve = exp.equivalent_rmse(history, best_loss=1.0, best_rmse=0.1)
    assert curve == pytest.approx([0.2, 0.1 * math.sqrt(2), 0.1, 0.1 * math.sqrt(1.5)])
    assert exp.epoch_reaching(curve, 0.15) == "2"  # 0.141 <= 0.15: the first epoch there
    assert exp.epoch_reaching(curve, 0.25) == "1"  # the paper's figure is worse than our first epoch
    assert exp.epoch_reaching(curve, 0.05) == "never"  # the paper's is better than any epoch of ours


def test_the_table_reads_the_committed_cells_and_the_shipped_cards(exp):
    lines = exp.rows(ROOT / "benchmarks" / "results" / "fidelity_measured")
    assert lines[0].startswith("| scenario | method | ours | paper |")
    l96 = [line for line in lines if line.startswith("| lorenz96 |")]
    assert len(l96) == 6  # every neural model of the scenario measured at the defaults
    for line in l96:
        ours, paper, ratio = (float(x) for x in line.split("|")[3:6])
        assert ratio == pytest.approx(ours / paper, rel=0.02)
