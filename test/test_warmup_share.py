"""experiments/warmup_share.py: RMSE split at the warm-up and over segments of the horizon."""

import numpy as np
import pytest
from conftest import load_script


@pytest.fixture(scope="module")
def share():
    return load_script("experiments/warmup_share.py")


def test_splits_pool_trajectories_and_components_and_wrap_angles(share):
    x = np.zeros((2, 6, 2))
    x_hat = np.zeros((2, 6, 2))
    x_hat[:, :2, 0] = 2.0  # error 2 on one of two components in steps 0-1: per-step MSE 2
    x_hat[:, 4:, 1] = 2 * np.pi + 1.0  # an angle off by 2 pi + 1: wrapped, error 1, per-step MSE 0.5
    all_, head, rest = share.split_rmse(x, x_hat, 2, angle_states=(1,))
    assert head == pytest.approx(np.sqrt(2.0)) and rest == pytest.approx(np.sqrt(1.0 / 4))
    assert all_ == pytest.approx(np.sqrt((2 * 2 + 2 * 0.5) / 6))
    assert share.segment_rmse(x, x_hat, [0, 2, 4, 6], angle_states=(1,)) == pytest.approx([np.sqrt(2), 0, np.sqrt(0.5)])
    assert share.segment_rmse(x, x_hat, [4, 6])[0] > 4  # not wrapped when the component is no angle


@pytest.mark.slow
def test_segments_run_on_a_shipped_model(share, capsys):
    share.main(["--scenario", "nlink", "--methods", "gru", "--trajectories", "2", "--segments", "0,10,100,500"])
    out = capsys.readouterr().out.splitlines()
    assert out[1].split() == ["method", "0-10", "10-100", "100-500"]
    values = [float(v) for v in out[2].split()[1:]]
    assert len(values) == 3 and all(0 < v < 5 for v in values)
    with pytest.raises(SystemExit):
        share.main(["--scenario", "nlink", "--methods", "gru", "--trajectories", "2", "--segments", "0,600"])
