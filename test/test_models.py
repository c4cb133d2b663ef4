"""The six architectures: shapes, causality, step == forward, fast scans == references, mamba_ssm layout."""

from __future__ import annotations

import importlib.util
import math

import pytest
import torch
import torch.nn.functional as F

from neural_estimator.methods import table
from neural_estimator.models import ARCHITECTURES, SystemDims, build_model, count_parameters, model_dims
from neural_estimator.models.filterformer import FilterformerModel
from neural_estimator.models.cpu_scan import mamba_scan_fused, ssd_scan_fused
from neural_estimator.models.layers import alibi_slopes, window_attention
from neural_estimator.models.mamba import (
    MambaConfig,
    MambaMixer,
    selective_scan,
    selective_scan_chunked,
    selective_scan_ref,
    selective_scan_stepwise,
)
from neural_estimator.models.mamba2 import Mamba2Config, Mamba2Mixer, ssd_chunked, ssd_ref

NAMES = [n for n in ARCHITECTURES if table.has(n, family="neural")]  # the hybrid (f and h): test_kalmannet.py
ATOL = 1e-5  # step loop vs parallel form, float64 (observed differences are ~1e-14)
SCAN_ATOL = 1e-10  # fast scan vs sequential reference, float64
SCENARIO_DIMS = {"ballistic": (1, 3), "bearings": (1, 4), "lorenz96": (10, 10), "nlink": (6, 6), "quadrotor": (5, 6)}
# small attention windows make the test exercise the blocked parallel form and a full KV cache
SMALL_WINDOW = {"gpt2": {"decode_chunk": 32}, "filterformer": {"window": 32}}


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tiny tensors: one intra-op thread


def make(name: str, d_in: int = 5, d_out: int = 3, seed: int = 0, **overrides) -> torch.nn.Module:
    torch.manual_seed(seed)
    return build_model(name, SystemDims(dx=d_out, dy=d_in), **overrides)


def step_loop(model: torch.nn.Module, z: torch.Tensor) -> torch.Tensor:
    state = model.init_state(z.shape[0])
    ys = []
    for t in range(z.shape[1]):
        y, state = model.step(z[:, t], state)
        ys.append(y)
    return torch.stack(ys, dim=1)


# ---- interface ----------------------------------------------------------------------------------
@pytest.mark.parametrize("name", NAMES)
def test_shapes(name):
    model = make(name).eval()
    z = torch.randn(4, 17, 5)
    assert model(z).shape == (4, 17, 3)
    assert model(z).dtype == torch.float32
    y, state = model.step(z[:, 0], model.init_state(4))
    assert y.shape == (4, 3)
    y2, _ = model.step(z[:, 1], state)
    assert y2.shape == (4, 3)
    assert model.cfg.d_in == 5 and model.cfg.d_out == 3


@pytest.mark.parametrize("name", NAMES)
def test_causal(name):
    model = make(name, **SMALL_WINDOW.get(name, {})).eval()
    z = torch.randn(2, 80, 5, dtype=torch.float64)
    model.double()
    y = model(z)
    s = 37
    z2 = z.clone()
    z2[:, s + 1 :] = torch.randn_like(z2[:, s + 1 :]) * 10.0
    y2 = model(z2)
    torch.testing.assert_close(y2[:, : s + 1], y[:, : s + 1], rtol=0, atol=1e-12)
    assert (y2[:, s + 1 :] - y[:, s + 1 :]).abs().max() > 1e-6


@pytest.mark.slow
@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("small_window", [False, True], ids=["paper", "small-window"])
def test_step_equals_forward_beyond_training_length(name, small_window):
    """A loop of step equals the parallel form on T = 300 > training length 100 and > window W."""
    overrides = SMALL_WINDOW.get(name, {}) if small_window else {}
    if small_window and not overrides:
        pytest.skip("no attention window")
    model = make(name, **overrides).double().eval()
    z = torch.randn(2, 300, 5, dtype=torch.float64)
    if name == "gpt2":
        assert 300 > model.cfg.decode_chunk
    if name == "filterformer":
        assert 300 > model.cfg.window
    with torch.no_grad():
        y = model(z)
        ys = step_loop(model, z)
    assert (ys - y).abs().max().item() <= ATOL


@pytest.mark.parametrize("name", NAMES)
def test_step_equals_forward_float32(name):
    model = make(name, **SMALL_WINDOW.get(name, {})).eval()
    z = torch.randn(3, 120, 5)
    with torch.no_grad():
        assert (step_loop(model, z) - model(z)).abs().max().item() <= 1e-4


@pytest.mark.parametrize("name", NAMES)
def test_gradients_flow(name):
    model = make(name).train()
    z = torch.randn(3, 40, 5)
    if isinstance(model, FilterformerModel):
        mean, cov = model.forward_with_cov(z)
        loss = mean.square().mean() + cov.diagonal(dim1=-2, dim2=-1).mean()
    else:
        loss = model(z).square().mean()
    loss.backward()
    for pname, p in model.named_parameters():
        assert p.grad is not None, pname
        assert torch.isfinite(p.grad).all(), pname
        assert p.grad.abs().sum() > 0, pname


@pytest.mark.parametrize("name", list(SMALL_WINDOW))
def test_gradients_flow_blocked_attention(name):
    """T > W in train mode: the blocked parallel form with attention dropout back-propagates."""
    model = make(name, **SMALL_WINDOW[name]).train()
    model(torch.randn(2, 90, 5)).square().mean().backward()
    for pname, p in model.named_parameters():
        if pname != "head.log_std":  # only the covariance uses it
            assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0, pname


def test_build_model_rejects_unknown():
    with pytest.raises(KeyError, match="unknown architecture"):
        build_model("transformer", SystemDims(dx=1, dy=1))
    with pytest.raises(KeyError, match="unknown hyperparameter"):
        build_model("gru", SystemDims(dx=1, dy=1), hidden_size=3)
    with pytest.raises(KeyError, match="come from the scenario"):
        build_model("gru", SystemDims(dx=1, dy=1), d_in=4)
    assert build_model("gru", SystemDims(dx=3, dy=2), hidden=7).cfg.hidden == 7


@pytest.mark.parametrize("scenario", list(SCENARIO_DIMS))
def test_build_model_sizes_the_network_from_the_scenario(scenario):
    """d_in = dy + du (z_k = [y_k, u_{k-1}]) and d_out = dx, read from the scenario itself."""
    from neural_estimator.scenarios import make_scenario

    system = make_scenario(scenario)
    assert model_dims(system) == SCENARIO_DIMS[scenario]
    cfg = build_model("gru", system).cfg
    assert (cfg.d_in, cfg.d_out) == (system.dy + system.du, system.dx)
    assert model_dims(SystemDims(dx=6, dy=3, du=2)) == (5, 6)


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("scenario", list(SCENARIO_DIMS))
def test_parameter_budget(name, scenario):
    """The paper's hyperparameters give about 100k parameters (within 15%) on every scenario."""
    n = count_parameters(build_model(name, SystemDims(dx=SCENARIO_DIMS[scenario][1], dy=SCENARIO_DIMS[scenario][0])))
    assert abs(n - 100_000) <= 15_000, n


def test_known_parameter_counts_lorenz96():
    counts = {name: count_parameters(build_model(name, SystemDims(dx=40, dy=40))) for name in NAMES}
    assert counts == {
        "gru": 94_645,
        "lstm": 97_315,
        "gpt2": 92_980,
        "filterformer": 105_192,
        "mamba": 104_360,
        "mamba2": 102_992,
    }


# ---- attention ----------------------------------------------------------------------------------
@pytest.mark.parametrize("fused", [True, False])
@pytest.mark.parametrize("T,W", [(1, 4), (9, 16), (16, 16), (17, 16), (50, 7), (64, 16)])
def test_window_attention_matches_naive(T, W, fused):
    torch.manual_seed(1)
    B, nh, hs = 2, 4, 5
    q, k, v = (torch.randn(B, nh, T, hs, dtype=torch.float64) for _ in range(3))
    slopes = alibi_slopes(nh).double()
    y = window_attention(q, k, v, slopes, W, fused=fused)
    ref = torch.empty_like(y)
    for t in range(T):
        s0 = max(0, t - W + 1)
        scores = q[:, :, t : t + 1] @ k[:, :, s0 : t + 1].transpose(-1, -2) / math.sqrt(hs)  # (B, nh, 1, n)
        dist = torch.arange(t - s0, -1, -1, dtype=torch.float64)
        w = torch.softmax(scores - slopes[:, None, None] * dist, dim=-1)
        ref[:, :, t] = (w @ v[:, :, s0 : t + 1])[:, :, 0]
    torch.testing.assert_close(y, ref, rtol=0, atol=1e-12)


@pytest.mark.parametrize("T,W", [(9, 16), (50, 7)])  # one block, and the blocked form
def test_the_window_bias_is_made_once_and_equals_a_fresh_one(T, W):
    """The ALiBi/window bias is cached per (slopes, T, W): the same tensor for every layer and call,
    equal to the one computed afresh, and never taken from the cache while a graph is traced."""
    from neural_estimator.models import layers

    slopes = alibi_slopes(4)
    first = layers.window_bias(slopes, T, W)
    assert layers.window_bias(slopes.clone(), T, W) is first
    assert torch.equal(first, layers._make_window_bias(slopes, T, W))
    assert layers.window_bias(slopes * 2, T, W) is not first
    traced = []
    torch.jit.trace(lambda s: traced.append(layers.window_bias(s, T, W)) or s * 1, (slopes,))
    assert traced[0] is not first and torch.equal(traced[0], first)


@pytest.mark.parametrize("T,W", [(12, 16), (40, 16)])  # one block, and the blocked form
def test_window_attention_fused_gradients_equal_the_math_path(T, W):
    """The fused kernel (forced: the test fails if torch cannot take it) equals the unfused path,
    value and gradients, float64."""
    from torch.nn.attention import SDPBackend, sdpa_kernel

    torch.manual_seed(2)
    B, nh, hs = 3, 4, 6
    base = [torch.randn(B, nh, T, hs, dtype=torch.float64) for _ in range(3)]
    slopes = alibi_slopes(nh).double()
    out = {}
    for fused in (True, False):
        q, k, v = (t.clone().requires_grad_() for t in base)
        backends = [SDPBackend.FLASH_ATTENTION] if fused else [SDPBackend.MATH]
        with sdpa_kernel(backends):
            y = window_attention(q, k, v, slopes, W, fused=fused)
            (y * torch.linspace(-1, 1, hs, dtype=torch.float64)).sum().backward()
        out[fused] = (y.detach(), q.grad, k.grad, v.grad)
    for a, b in zip(out[True], out[False]):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", ["gpt2", "filterformer"])
def test_attention_models_fused_equals_math_path(name):
    torch.manual_seed(3)
    model = build_model(name, SystemDims(dx=2, dy=3)).double().eval()
    z = torch.randn(2, 300, 3, dtype=torch.float64)  # longer than GPT-2's window: the blocked form too
    with torch.no_grad():
        fused = model(z)
        for m in model.modules():
            if hasattr(m, "attention_path"):
                m.attention_path = "math"
        math_path = model(z)
    torch.testing.assert_close(fused, math_path, rtol=0, atol=1e-10)


def test_alibi_slopes():
    torch.testing.assert_close(alibi_slopes(4), torch.tensor([2**-2, 2**-4, 2**-6, 2**-8]))
    assert alibi_slopes(6).shape == (6,)


# ---- filterformer covariance --------------------------------------------------------------------
def test_filterformer_covariance_symmetric_psd_and_step():
    model = make("filterformer", d_in=4, d_out=6, window=16).double().eval()
    z = torch.randn(2, 40, 4, dtype=torch.float64)
    mean, cov = model.forward_with_cov(z)
    assert mean.shape == (2, 40, 6) and cov.shape == (2, 40, 6, 6)
    torch.testing.assert_close(mean, model(z))
    torch.testing.assert_close(cov, cov.transpose(-1, -2), rtol=0, atol=0)
    assert torch.linalg.eigvalsh(cov).min() > 0
    # the mixture moments: within-component variances plus the spread of the means
    w = torch.softmax(model.head.readout(model.encode(z)), dim=-1)  # (B, T, K)
    m, s2 = model.head.means, torch.exp(2 * model.head.log_std)
    second = torch.einsum("btk,ki,kj->btij", w, m, m) + torch.diag_embed(w @ s2)
    torch.testing.assert_close(cov, second - mean[..., :, None] * mean[..., None, :])
    state = model.init_state(2)
    for t in range(40):
        mt, ct, state = model.step_with_cov(z[:, t], state)
        torch.testing.assert_close(mt, mean[:, t], rtol=0, atol=1e-12)
        torch.testing.assert_close(ct, cov[:, t], rtol=0, atol=1e-12)


# ---- Mamba: scans and mamba_ssm layout ---------------------------------------------------------
def _scan_inputs(B, T, E, N, seed=0):
    g = torch.Generator().manual_seed(seed)
    u = torch.randn(B, T, E, generator=g, dtype=torch.float64)
    delta = F.softplus(torch.randn(B, T, E, generator=g, dtype=torch.float64) - 1.0)
    A = -torch.exp(torch.randn(E, N, generator=g, dtype=torch.float64))
    b = torch.randn(B, T, N, generator=g, dtype=torch.float64)
    c = torch.randn(B, T, N, generator=g, dtype=torch.float64)
    return u, delta, A, b, c


@pytest.mark.parametrize(
    "B,T,E,N,chunk",
    [(1, 1, 3, 2, 0), (2, 7, 4, 3, 0), (3, 100, 8, 16, 0), (2, 37, 5, 4, 6), (2, 50, 6, 5, 64), (1, 301, 4, 4, 0)],
)
def test_selective_scan_fast_equals_reference(B, T, E, N, chunk):
    u, delta, A, b, c = _scan_inputs(B, T, E, N)
    y_ref, s_ref = selective_scan_ref(u, delta, A, b, c)
    for y, s in (
        selective_scan_stepwise(u, delta, A, b, c),
        selective_scan_chunked(u, delta, A, b, c, chunk),
        selective_scan(u, delta, A, b, c, chunk),
    ):
        torch.testing.assert_close(y, y_ref, rtol=0, atol=SCAN_ATOL)
        torch.testing.assert_close(s, s_ref, rtol=0, atol=SCAN_ATOL)


def test_selective_scan_gradients_equal_reference():
    inputs = [x.requires_grad_() for x in _scan_inputs(2, 23, 4, 3, seed=3)]
    w = torch.randn(2, 23, 4, dtype=torch.float64)
    grads = []
    for fn in (selective_scan_ref, selective_scan_stepwise, lambda *a: selective_scan_chunked(*a, chunk=5)):
        (fn(*inputs)[0] * w).sum().backward()
        grads.append([x.grad.clone() for x in inputs])
        for x in inputs:
            x.grad = None
    for g in grads[1:]:
        for a, r in zip(g, grads[0]):
            torch.testing.assert_close(a, r, rtol=1e-9, atol=1e-10)


@pytest.mark.parametrize(
    "B,T,H,P,N,chunk",
    [
        (1, 1, 2, 3, 4, 32),
        (2, 7, 2, 3, 4, 3),
        (3, 100, 8, 16, 48, 32),
        (2, 33, 4, 2, 5, 8),
        (2, 65, 2, 4, 3, 64),
        (1, 300, 2, 2, 6, 32),
    ],
)
def test_ssd_chunked_equals_reference(B, T, H, P, N, chunk):
    g = torch.Generator().manual_seed(T)
    x = torch.randn(B, T, H, P, generator=g, dtype=torch.float64)
    delta = F.softplus(torch.randn(B, T, H, generator=g, dtype=torch.float64))
    A = -torch.empty(H, dtype=torch.float64).uniform_(1.0, 16.0, generator=g)
    b = torch.randn(B, T, N, generator=g, dtype=torch.float64)
    c = torch.randn(B, T, N, generator=g, dtype=torch.float64)
    y_ref, s_ref = ssd_ref(x, delta, A, b, c)
    y, s = ssd_chunked(x, delta, A, b, c, chunk)
    torch.testing.assert_close(y, y_ref, rtol=0, atol=SCAN_ATOL)
    torch.testing.assert_close(s, s_ref, rtol=0, atol=SCAN_ATOL)


def test_ssd_chunked_stable_for_strong_decay():
    """Long chunks with large delta*A: the masked segment sums keep every exponent finite."""
    B, T, H, P, N = 1, 128, 2, 2, 3
    x = torch.randn(B, T, H, P)
    delta = torch.full((B, T, H), 5.0)
    A = torch.tensor([-16.0, -1.0])
    b, c = torch.randn(B, T, N), torch.randn(B, T, N)
    y, _ = ssd_chunked(x, delta, A, b, c, chunk_size=128)
    y_ref, _ = ssd_ref(x, delta, A, b, c)
    assert torch.isfinite(y).all()
    torch.testing.assert_close(y, y_ref, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("name", ["mamba", "mamba2"])
def test_mamba_fast_forward_equals_reference_forward(name):
    model = make(name, d_in=3, d_out=2).double().eval()
    z = torch.randn(2, 130, 3, dtype=torch.float64)
    torch.testing.assert_close(model(z), model(z, reference=True), rtol=0, atol=1e-10)


# ---- the fused CPU kernels (numba, hand-written backward) against the sequential references ------
@pytest.mark.parametrize("B,T,E,N", [(1, 1, 3, 2), (2, 23, 4, 3), (3, 100, 8, 16)])
def test_fused_mamba_scan_value_and_gradients_equal_reference(B, T, E, N):
    inputs = [x.requires_grad_() for x in _scan_inputs(B, T, E, N, seed=T)]
    w = torch.randn(B, T, E, dtype=torch.float64)
    results = []
    for fn in (selective_scan_ref, mamba_scan_fused):
        y, s = fn(*inputs)
        results.append((y.detach(), s.detach(), torch.autograd.grad((y * w).sum(), inputs)))
    (y_ref, s_ref, g_ref), (y, s, g) = results
    torch.testing.assert_close(y, y_ref, rtol=0, atol=SCAN_ATOL)
    torch.testing.assert_close(s, s_ref, rtol=0, atol=SCAN_ATOL)
    for name, a, r in zip(("u", "delta", "A", "B", "C"), g, g_ref):
        torch.testing.assert_close(a, r, rtol=1e-9, atol=1e-10, msg=lambda m: f"d/d{name}: {m}")
    with torch.no_grad():  # the inference kernel (decays computed on the fly)
        y_ng, s_ng = mamba_scan_fused(*inputs)
    torch.testing.assert_close(y_ng, y_ref, rtol=0, atol=SCAN_ATOL)
    torch.testing.assert_close(s_ng, s_ref, rtol=0, atol=SCAN_ATOL)


@pytest.mark.parametrize("B,T,H,P,N", [(1, 1, 2, 3, 4), (2, 23, 2, 3, 5), (3, 100, 8, 16, 48)])
def test_fused_ssd_scan_value_and_gradients_equal_reference(B, T, H, P, N):
    g = torch.Generator().manual_seed(T)
    x = torch.randn(B, T, H, P, generator=g, dtype=torch.float64)
    delta = F.softplus(torch.randn(B, T, H, generator=g, dtype=torch.float64))
    A = -torch.empty(H, dtype=torch.float64).uniform_(1.0, 16.0, generator=g)
    b = torch.randn(B, T, N, generator=g, dtype=torch.float64)
    c = torch.randn(B, T, N, generator=g, dtype=torch.float64)
    inputs = [v.requires_grad_() for v in (x, delta, A, b, c)]
    w = torch.randn(B, T, H, P, dtype=torch.float64)
    results = []
    for fn in (ssd_ref, ssd_scan_fused):
        y, s = fn(*inputs)
        results.append((y.detach(), s.detach(), torch.autograd.grad((y * w).sum(), inputs)))
    (y_ref, s_ref, g_ref), (y, s, grads) = results
    torch.testing.assert_close(y, y_ref, rtol=0, atol=SCAN_ATOL)
    torch.testing.assert_close(s, s_ref, rtol=0, atol=SCAN_ATOL)
    for name, a, r in zip(("x", "delta", "A", "B", "C"), grads, g_ref):
        torch.testing.assert_close(a, r, rtol=1e-9, atol=1e-10, msg=lambda m: f"d/d{name}: {m}")


@pytest.mark.slow
@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("name", ["mamba", "mamba2"])
def test_fused_training_gradients_equal_reference_model(name, threads):
    """Every parameter's gradient through the fused path equals the one through the reference scan."""
    model = make(name, d_in=3, d_out=2).double()
    z = torch.randn(5, 31, 3, dtype=torch.float64)
    target = torch.randn(5, 31, 2, dtype=torch.float64)
    grads = []
    old = torch.get_num_threads()
    torch.set_num_threads(threads)  # 2: the batch rows are split over two kernel threads
    try:
        for reference in (True, False):
            model.zero_grad()
            (model(z, reference=reference) - target).square().mean().backward()
            grads.append({k: p.grad.clone() for k, p in model.named_parameters()})
    finally:
        torch.set_num_threads(old)
    for k, r in grads[0].items():
        torch.testing.assert_close(grads[1][k], r, rtol=1e-9, atol=1e-11, msg=lambda m: f"{k}: {m}")


# Expected per-mixer state_dicts, derived from mamba_ssm/modules/mamba_simple.py (Mamba) and
# mamba_ssm/modules/mamba2.py (Mamba2) with the paper's hyperparameters.
MAMBA_MIXER_80 = {  # d_model=80, d_state=16, d_conv=4, expand=2: d_inner=160, dt_rank=ceil(80/16)=5
    "in_proj.weight": (320, 80),
    "conv1d.weight": (160, 1, 4),
    "conv1d.bias": (160,),
    "x_proj.weight": (5 + 2 * 16, 160),
    "dt_proj.weight": (160, 5),
    "dt_proj.bias": (160,),
    "A_log": (160, 16),
    "D": (160,),
    "out_proj.weight": (80, 160),
}
MAMBA2_MIXER_64 = {  # d_model=64, d_state=48, d_conv=4, expand=2, headdim=16, ngroups=1: d_inner=128, 8 heads
    "in_proj.weight": (2 * 128 + 2 * 48 + 8, 64),  # [z, x, B, C, dt]
    "conv1d.weight": (128 + 2 * 48, 1, 4),
    "conv1d.bias": (128 + 2 * 48,),
    "dt_bias": (8,),
    "A_log": (8,),
    "D": (8,),
    "norm.weight": (128,),
    "out_proj.weight": (64, 128),
}


@pytest.mark.parametrize(
    "name,mixer,n_layer,d_model", [("mamba", MAMBA_MIXER_80, 2, 80), ("mamba2", MAMBA2_MIXER_64, 3, 64)]
)
def test_mamba_state_dict_layout(name, mixer, n_layer, d_model):
    model = build_model(name, SystemDims(dx=40, dy=40))
    shapes = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    expected = {
        "input_proj.weight": (d_model, 40),
        "input_proj.bias": (d_model,),
        "backbone.norm_f.weight": (d_model,),
        "head.weight": (40, d_model),
        "head.bias": (40,),
    }
    for i in range(n_layer):
        expected[f"backbone.layers.{i}.norm.weight"] = (d_model,)
        expected.update({f"backbone.layers.{i}.mixer.{k}": v for k, v in mixer.items()})
    assert shapes == expected


def test_mamba_init_follows_mamba_ssm():
    torch.manual_seed(0)
    m = MambaMixer(MambaConfig(1, 1))
    torch.testing.assert_close(m.A_log, torch.log(torch.arange(1, 17.0)).expand(160, 16))
    torch.testing.assert_close(m.D, torch.ones(160))
    dt = F.softplus(m.dt_proj.bias)
    assert dt.min() >= 1e-3 * (1 - 1e-5) and dt.max() <= 0.1 * (1 + 1e-5)
    assert m.dt_proj.weight.abs().max() <= 5**-0.5
    assert m.in_proj.bias is None and m.out_proj.bias is None and m.x_proj.bias is None
    m2 = Mamba2Mixer(Mamba2Config(1, 1))
    A = torch.exp(m2.A_log)
    assert A.min() >= 1.0 and A.max() <= 16.0
    dt = F.softplus(m2.dt_bias)
    assert dt.min() >= 1e-3 * (1 - 1e-5) and dt.max() <= 0.1 * (1 + 1e-5)
    torch.testing.assert_close(m2.norm.weight, torch.ones(128))


HAVE_CUDA_MAMBA = torch.cuda.is_available() and importlib.util.find_spec("mamba_ssm") is not None


@pytest.mark.skipif(not HAVE_CUDA_MAMBA, reason="needs CUDA and mamba_ssm")
@pytest.mark.parametrize("name", ["mamba", "mamba2"])
def test_parity_with_mamba_ssm_cuda(name):
    """State dicts move both ways, and forward/step agree with mamba_ssm's fused kernels."""
    torch.manual_seed(0)
    if name == "mamba":
        from mamba_ssm.modules.mamba_simple import Mamba

        theirs = Mamba(d_model=80, d_state=16, d_conv=4, expand=2).cuda()
        ours = MambaMixer(MambaConfig(1, 1)).cuda()
    else:
        from mamba_ssm.modules.mamba2 import Mamba2

        theirs = Mamba2(d_model=64, d_state=48, d_conv=4, expand=2, headdim=16, ngroups=1).cuda()
        ours = Mamba2Mixer(Mamba2Config(1, 1)).cuda()
    ours.load_state_dict(theirs.state_dict())
    theirs.load_state_dict(ours.state_dict())
    x = torch.randn(2, 96, theirs.d_model, device="cuda")
    with torch.no_grad():
        ref = theirs(x)
        torch.testing.assert_close(ours(x), ref, rtol=1e-3, atol=1e-3)  # our code around their kernel
        torch.testing.assert_close(ours(x, reference=True), ref, rtol=1e-3, atol=1e-3)  # pure PyTorch
        conv, ssm = theirs.allocate_inference_cache(2, 1)
        c2, s2 = ours.init_state(2, device="cuda", dtype=torch.float32)
        for t in range(8):
            y_theirs, conv, ssm = theirs.step(x[:, t : t + 1], conv, ssm)
            y_ours, c2, s2 = ours.step(x[:, t], c2, s2)
            torch.testing.assert_close(y_ours, y_theirs[:, 0], rtol=1e-3, atol=1e-3)
