"""The limits the serving benchmark sets the ONNX steps against (benchmarks/bench_serving.py): the
state's arithmetic counted from each model's sizes as its card states them, and ONNX Runtime's
contrib operators computing what the standard-opset pieces they were tried against compute."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import load_script

from neural_estimator.scenarios import make_scenario
from neural_estimator.serving.load import load_neural_estimator


@pytest.fixture(scope="module")
def l96():
    return make_scenario("lorenz96")


def test_state_flops_counts_the_window_and_the_ssm_state_from_the_cards_sizes(l96):
    bench = load_script("benchmarks/bench_serving.py")

    def counted(method: str):
        model = load_neural_estimator(method, l96, context=0).model
        return bench.state_flops(model), model.trunk.cfg

    assert counted("gru")[0] == 0
    flops, cfg = counted("gpt2")
    assert flops == 4 * cfg.n_embd * cfg.decode_chunk * cfg.n_layer  # q k and p v over the window, every layer
    flops, cfg = counted("filterformer")
    assert flops == 4 * cfg.d_model * cfg.window  # its one attention layer
    flops, cfg = counted("mamba2")
    E, N, K = cfg.expand * cfg.d_model, cfg.d_state, cfg.d_conv
    assert flops == cfg.n_layer * (5 * N * E + 2 * K * (E + 2 * N))  # the conv runs over x, b and c
    flops, cfg = counted("mamba")
    E, N, K = cfg.expand * cfg.d_model, cfg.d_state, cfg.d_conv
    assert flops == cfg.n_layer * (6 * N * E + 2 * K * E)  # the decay exp(delta A) per element


def test_the_contrib_operators_compute_what_the_standard_pieces_compute():
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnx")
    bench = load_script("benchmarks/bench_ort_contrib.py")
    rng = np.random.default_rng(1)
    for layout in ("BNSH", "BSD"):
        (std, f_std), (mha, f_mha) = bench.attention_pair(4, 32, 15, rng, layout)
        q, k, v, bias = f_std["q"], f_std["k"], f_std["v"], f_std["bias"]
        scores = q @ k.transpose(0, 2, 1) / np.sqrt(15) + bias
        p = np.exp(scores - scores.max(-1, keepdims=True))
        want = ((p / p.sum(-1, keepdims=True)) @ v).reshape(1, -1)
        for sess, feeds in ((std, f_std), (mha, f_mha)):
            assert np.abs(sess.run(None, feeds)[0] - want).max() < 1e-5, layout
    (a, fa), (b, fb) = bench.residual_pair(60, 3, rng)
    got_a, got_b = a.run(None, fa)[0], b.run(None, fb)[0]
    assert got_a.shape == (1, 60) and np.abs(got_a - got_b).max() < 1e-5 and np.abs(got_a).max() > 0.1
