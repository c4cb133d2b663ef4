"""benchmarks/bounded_context.py: an SSM run with its context bounded by staggered restarts."""

import pytest
import torch
from conftest import load_script

from neural_estimator.models import build_model


@pytest.fixture(scope="module")
def bc():
    return load_script("benchmarks/bounded_context.py")


@pytest.mark.parametrize("length,copies", [(10, 1), (10, 3), (10, 10), (7, 2)])
def test_every_step_sees_at_most_length_steps_and_nearly_that_many(bc, length, copies):
    for t in range(60):
        s = bc.restart_of(t, length, copies)
        assert 0 <= s <= t and t - s + 1 <= length
        if t < length:
            assert s == 0
        else:
            assert t - s + 1 >= length - -(-length // copies)  # at least L - ceil(L / K) steps of context


def test_bounded_forward_is_the_model_on_each_steps_window(bc):
    torch.manual_seed(0)
    model = build_model("mamba2", 3, 2).double().eval()
    z = torch.randn(2, 37, 3, dtype=torch.float64)
    with torch.no_grad():
        y = bc.bounded_forward(model, z, 10, 3)
        for t in (0, 5, 9, 10, 17, 29, 36):
            s = bc.restart_of(t, 10, 3)
            torch.testing.assert_close(y[:, t], model(z[:, s : t + 1])[:, -1], rtol=0, atol=1e-12)
        torch.testing.assert_close(bc.bounded_forward(model, z, 37, 4), model(z), rtol=0, atol=1e-12)


def test_runs_on_a_shipped_model(bc, capsys):
    from conftest import ROOT

    bc.main(["--model", str(ROOT / "neural_estimator/zoo/nlink-mamba2"), "--trajectories", "2", "--copies", "2"])
    out = capsys.readouterr().out.splitlines()
    assert out[2].split()[0] == "inference" and [r.split()[0] for r in out[3:]] == ["continuous", "bounded"]
    assert all(0 < float(v) < 5 for v in out[4].split()[2:])
    with pytest.raises(SystemExit):
        bc.main(
            ["--model", str(ROOT / "neural_estimator/zoo/nlink-mamba2"), "--trajectories", "2", "--segments", "0,900"]
        )
