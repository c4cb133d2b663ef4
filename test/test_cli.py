"""The neural-estimator command line: verbs, files, and clear errors with exit status 2."""

import json

import numpy as np
import pytest

from neural_estimator.cli import main
from neural_estimator.data import load_trajectories, save_estimates

PLUGIN = ["--plugin", "examples/custom_scenario.py"]


@pytest.fixture(autouse=True)
def _repo_cwd(monkeypatch):
    from pathlib import Path

    monkeypatch.chdir(Path(__file__).resolve().parents[1])


def test_simulate_writes_the_documented_format(tmp_path, capsys):
    out = tmp_path / "osc.npz"
    assert (
        main(
            [
                "simulate",
                *PLUGIN,
                "--scenario",
                "oscillator",
                "--trajectories",
                "4",
                "--horizon",
                "9",
                "--seed",
                "2",
                "--set",
                "omega=2.0",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    data, extras = load_trajectories(out)
    assert data.x.shape == (4, 9, 2) and data.y.shape == (4, 9, 1) and data.u.shape == (4, 9, 0)
    assert data.meta["config"]["omega"] == 2.0 and data.meta["seed"] == 2 and not extras
    assert "wrote" in capsys.readouterr().out


def test_metrics_on_truth_and_estimate_files(tmp_path, capsys):
    truth = tmp_path / "truth.npz"
    main(
        [
            "simulate",
            *PLUGIN,
            "--scenario",
            "oscillator",
            "--trajectories",
            "20",
            "--horizon",
            "16",
            "--out",
            str(truth),
        ]
    )
    data, _ = load_trajectories(truth)
    err = np.zeros_like(data.x)
    err[..., 0] = 0.5  # constant error 0.5 on one of two components: RMSE = sqrt(0.25 / 2)
    save_estimates(tmp_path / "a.npz", data, data.x + err, "biased")
    capsys.readouterr()
    assert main(["metrics", *PLUGIN, str(truth), str(tmp_path / "a.npz"), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)["methods"]["biased"]
    assert report["rmse"] == pytest.approx(np.sqrt(0.125))
    assert report["drift_ratio"] == pytest.approx(1.0) and report["outlier_ratio"] == 0
    assert len(report["rmse_t"]) == 16 - 10 and report["warmup"] == 10  # the paper's warm-up is not scored
    assert main(["metrics", *PLUGIN, str(truth), str(tmp_path / "a.npz"), "--json", "--warmup", "0"]) == 0
    every = json.loads(capsys.readouterr().out)["methods"]["biased"]
    assert len(every["rmse_t"]) == 16 and every["warmup"] == 0 and every["rmse"] == pytest.approx(np.sqrt(0.125))
    assert main(["metrics", *PLUGIN, str(truth), str(tmp_path / "a.npz"), "--warmup", "16"]) == 2
    assert "--warmup 16 leaves no step of 16-step trajectories" in capsys.readouterr().err
    # one file holding both, and a CSV table
    assert main(["metrics", str(tmp_path / "a.npz"), "--out", str(tmp_path / "t.csv")]) == 0
    text = capsys.readouterr().out
    assert "RMSE" in text and "biased" in text
    assert (tmp_path / "t.csv").read_text().startswith("method,rmse,rmse_iqr")


@pytest.mark.parametrize(
    "argv, message",
    [
        (["simulate", "--scenario", "nope", "--out", "x.npz"], "unknown scenario 'nope'; choose one of: ballistic"),
        (
            ["simulate", *PLUGIN, "--scenario", "oscillator", "--set", "omegaa=1", "--out", "x.npz"],
            "no constant 'omegaa' (did you mean 'omega'?); valid:",
        ),
        (
            ["simulate", *PLUGIN, "--scenario", "oscillator", "--set", "omega", "--out", "x.npz"],
            "--set expects name=value",
        ),
        (["simulate", *PLUGIN, "--scenario", "oscillator", "--trajectories", "0", "--out", "x.npz"], "must be >= 1"),
        (["metrics", "missing.npz"], "missing.npz: no such file"),
        (
            ["evaluate", *PLUGIN, "--scenario", "oscillator", "--methods", "ekf,particleflow"],
            "unknown method 'particleflow'; choose one of: ekf",
        ),
        (["simulate", "--plugin", "nope.py", "--scenario", "x", "--out", "x.npz"], "plugin nope.py: no such file"),
    ],
)
def test_bad_input_is_one_clear_line_and_status_2(argv, message, capsys, tmp_path, monkeypatch):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


def test_metrics_refuses_estimates_of_another_dataset(tmp_path, capsys):
    for seed in (0, 1):
        main(
            [
                "simulate",
                *PLUGIN,
                "--scenario",
                "oscillator",
                "--trajectories",
                "3",
                "--horizon",
                "5",
                "--seed",
                str(seed),
                "--out",
                str(tmp_path / f"d{seed}.npz"),
            ]
        )
    other, _ = load_trajectories(tmp_path / "d1.npz")
    save_estimates(tmp_path / "e.npz", other, other.x, "ukf")
    assert main(["metrics", str(tmp_path / "d0.npz"), str(tmp_path / "e.npz")]) == 2
    assert "estimates of another dataset" in capsys.readouterr().err


def test_metrics_scores_an_estimate_file_holding_only_x_hat(tmp_path, capsys):
    """A user's own estimator writes just its estimates: x_hat (N, T, dx), no copy of the data."""
    import numpy as np

    from neural_estimator.data.io import save_npz

    main(
        [
            "simulate",
            *PLUGIN,
            "--scenario",
            "oscillator",
            "--trajectories",
            "3",
            "--horizon",
            "15",
            "--out",
            str(tmp_path / "d.npz"),
        ]
    )
    truth, _ = load_trajectories(tmp_path / "d.npz")
    save_npz(tmp_path / "mine.npz", {"x_hat": truth.x + 0.5}, {"method": "mine"})
    capsys.readouterr()
    assert main(["metrics", str(tmp_path / "d.npz"), str(tmp_path / "mine.npz")]) == 0
    out = capsys.readouterr().out
    assert "mine" in out and "0.500" in out
    save_npz(tmp_path / "bad.npz", {"x_hat": np.zeros((3, 4, 2))}, {})
    assert main(["metrics", str(tmp_path / "d.npz"), str(tmp_path / "bad.npz")]) == 2
    assert "x_hat has shape (3, 4, 2), the truth's x has (3, 15, 2)" in capsys.readouterr().err


def test_preset_flag_selects_named_constants_recorded_in_the_file(tmp_path, capsys):
    out = tmp_path / "b.npz"
    args = ["simulate", "--scenario", "ballistic", "--trajectories", "2", "--horizon", "5", "--out", str(out)]
    assert main([*args, "--preset", "v3"]) == 0
    data, _ = load_trajectories(out)
    assert data.meta["preset"] == "v3" and data.meta["config"]["dt"] == 0.1
    assert main([*args, "--preset", "v3", "--set", "dt=0.2"]) == 0  # --set applies on top
    data, _ = load_trajectories(out)
    assert data.meta["preset"] == "custom" and data.meta["config"]["dt"] == 0.2
    assert main(args) == 0
    data, _ = load_trajectories(out)
    assert data.meta["preset"] == "v4" and data.meta["config"]["dt"] == 0.01
    capsys.readouterr()
    assert main([*args, "--preset", "v9"]) == 2
    err = capsys.readouterr().err.strip()
    assert "no preset 'v9'" in err and "\n" not in err


def test_evaluate_on_preset_v3_loads_the_model_trained_on_it(tmp_path, capsys):
    """A shipped model trained on the earlier constants evaluates on their preset; on the new
    defaults it is refused with one line naming the preset."""
    import json as _json
    from pathlib import Path

    from neural_estimator.scenarios import scenario_class

    zoo = Path(__file__).resolve().parents[1] / "neural_estimator" / "serving" / "zoo"
    card = _json.loads((zoo / "ballistic-gru" / "card.json").read_text())
    preset = scenario_class("ballistic").preset_of(card["scenario"]["config"])
    common = ["evaluate", "--scenario", "ballistic", "--methods", "gru", "--trajectories", "3", "--sets", "1"]
    common += ["--horizon", "30", "--no-cache", "--out", str(tmp_path / "r")]
    assert main([*common, "--preset", preset]) == 0
    if preset != "v4":
        capsys.readouterr()
        assert main(common) == 2
        err = capsys.readouterr().err.strip()
        assert f"--preset {preset}" in err and "\n" not in err
