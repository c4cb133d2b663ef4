"""scripts/fit_covariance_heads.py on the zoo's trained instances (``--instance K``): each instance gets
its own head, fitted on the same validation sets as the shipped model's, and serves it."""

from __future__ import annotations

import importlib.util
import json
import shutil
from pathlib import Path

import numpy as np

from neural_estimator.serving import instances as I

ROOT = Path(__file__).resolve().parents[1]


def _script():
    spec = importlib.util.spec_from_file_location("fit_heads", ROOT / "scripts" / "fit_covariance_heads.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_an_instance_gets_its_own_head_in_its_own_folder(tmp_path, monkeypatch, capsys):
    zoo = tmp_path / "zoo"
    shipped = I.instance_checkpoint("nlink", "gru", 0)
    dest = I.instance_checkpoint("nlink", "gru", 1, zoo)
    assert dest == zoo / "instances" / "i1" / "nlink-gru"
    dest.mkdir(parents=True)
    shutil.copy2(shipped / "model.safetensors", dest / "model.safetensors")
    card = json.loads((shipped / "card.json").read_text())
    del card["covariance_head"]  # an instance as train_zoo.py installs it: no head yet
    (dest / "card.json").write_text(json.dumps(card))
    monkeypatch.setattr(I, "ZOO_DIR", zoo)
    fit = _script().main
    small = ["--head-trajectories", "8", "--calibration-trajectories", "8", "--steps", "20"]
    assert fit(["--scenarios", "nlink", "--methods", "gru", "lstm", "--instance", "1", *small]) == 0
    out = capsys.readouterr().out
    assert "nlink-lstm: no instance 1 in the zoo, skipped" in out
    assert "head set: val index 101" in out  # the shipped heads' validation sets, not recorded data
    entry = json.loads((dest / "card.json").read_text())["covariance_head"]
    assert entry["fitted_on"]["head"]["index"] == 101 and (dest / entry["file"]).is_file()
    assert not (zoo / "nlink-gru").exists()  # the shipped model's folder was not touched
    # the instance serves its head through the exported step (ONNX Runtime) as through torch
    from neural_estimator.scenarios import make_scenario
    from neural_estimator.data import simulate
    from neural_estimator.serving.load import load_neural_estimator

    scenario = make_scenario("nlink")
    data = simulate(scenario, 1, 30, seed=4)
    served = load_neural_estimator("gru", scenario, dest, backend="auto")
    assert type(served).__name__ == "OnnxEstimator" and served.has_covariance
    run = load_neural_estimator("gru", scenario, dest).run(data.y, data.u)
    assert np.linalg.eigvalsh(run.cov).min() > 0
    # done once: a second run skips it; a negative instance is one line and exit 2
    assert fit(["--scenarios", "nlink", "--methods", "gru", "--instance", "1", *small]) == 0
    assert "nlink-gru: has a covariance head, skipped" in capsys.readouterr().out
    assert fit(["--instance", "-1"]) == 2
    assert capsys.readouterr().err.strip() == "--instance must be >= 0 (0: the shipped model), got -1"
