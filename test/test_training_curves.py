"""scripts/training_curves.py: the plateau figure and the plot of the zoo's full-recipe training curves."""

import json
import math

import pytest
from conftest import load_script


@pytest.fixture(scope="module")
def curves():
    return load_script("scripts/training_curves.py")


def _hist(vals, lrs):
    return [{"epoch": i + 1, "val_loss": v, "lr": lr, "seconds": 90.0} for i, (v, lr) in enumerate(zip(vals, lrs))]


def test_flatness_and_reductions(curves):
    assert curves.flatness([4.0, 2.0, 2.0, 1.0], 2) == pytest.approx(-0.5)  # the last two epochs halved the best
    assert curves.flatness([4.0, 2.0, 2.0, 2.2], 2) == pytest.approx(0.0)  # flat
    assert math.isnan(curves.flatness([1.0, 2.0], 2))
    assert curves.reductions(_hist([1, 1, 1, 1], [2e-3, 1e-3, 1e-3, 5e-4])) == [2, 4]


@pytest.mark.slow
def test_reads_finished_and_in_progress_pairs_and_plots(curves, tmp_path, capsys):
    done, running = tmp_path / "lorenz96-mamba", tmp_path / "nlink-mamba2"
    (done).mkdir()
    hist = _hist([3.0, 2.0, 1.5, 1.5, 1.49], [2e-3, 2e-3, 1e-3, 5e-4, 2.5e-4])
    card = {"training": {"stopped": "finished by hand (--finish) after 5 epochs, 0.12 h", "history": hist}}
    (done / "card.json").write_text(json.dumps(card))
    (running / "resume").mkdir(parents=True)
    state = {"run": {"history": _hist([0.05, 0.04], [2e-3, 2e-3])}}
    (running / "resume" / "state.json").write_text(json.dumps(state))
    (tmp_path / "quadrotor-gru").mkdir()  # not started: no line
    older = tmp_path / "normalised" / "bearings-mamba"  # a run of the earlier loss units, one level down
    older.mkdir(parents=True)
    (older / "card.json").write_text(json.dumps(card))
    out = tmp_path / "curves.png"
    assert curves.main(["--state", str(tmp_path), "--out", str(out), "--window", "2"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 3 and lines[2].startswith("normalised/bearings-mamba")
    assert lines[0].startswith("lorenz96-mamba") and "best val 1.49 at epoch   5" in lines[0]
    assert "lr reductions  3" in lines[0] and "flat over last 2: -0.7 %" in lines[0] and "finished by hand" in lines[0]
    assert lines[1].startswith("nlink-mamba2") and "flat over last 2: –" in lines[1] and "[in progress]" in lines[1]
    assert out.stat().st_size > 10_000 and out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_nothing_to_show_is_an_error(curves, tmp_path, capsys):
    assert curves.main(["--state", str(tmp_path)]) == 1
    assert "no training histories" in capsys.readouterr().err
