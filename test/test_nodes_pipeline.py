"""The ROS 2 nodes live, in an isolated ROS domain per test (processes started as the launcher does): the
whole chain (simulator, estimators, evaluator) records, scores and equals replay; nodes started by hand in
any order lose nothing.
"""

from __future__ import annotations

import itertools
import json
import time

import numpy as np
import pytest

from neural_estimator.bags import BagReader, bag_to_arrays
from neural_estimator.data import simulate
from neural_estimator.nodes.launch import (
    ESTIMATOR,
    EVALUATOR,
    SIMULATOR,
    PipelineConfig,
    run_pipeline,
)
from neural_estimator.evaluation.replay import replay

pytestmark = pytest.mark.ros  # every test here runs ROS 2 nodes

pytest.importorskip("rclpy")


# ---- the whole chain -------------------------------------------------------------------------------------
def test_live_chain_records_scores_and_equals_replay(plugin, cart, domain, tmp_path):
    bag = tmp_path / "live.mcap"
    cfg = PipelineConfig(
        scenario="nodecart",
        methods=("ekf", "ukf"),
        trajectories=2,
        horizon=40,
        rate_hz=200.0,
        seed=3,
        plugins=(plugin,),
        output=str(bag),
        domain_id=domain,
        timeout=100.0,
    )
    res = run_pipeline(cfg)
    assert res.returncodes["evaluator"] == 0 and res.bag == bag
    N, T = 2, 40

    # the recorded file: every stream complete, identities right, estimates finite
    with BagReader(bag, strict=True) as reader:
        counts = {t: c.msgcount for t, c in reader.topics.items()}
        assert all(c.message_encoding == "cdr" for c in reader.connections)
    for topic in (
        "/observation",
        "/ground_truth",
        "/estimates/ekf",
        "/estimates/ukf",
        "/estimates/ekf/covariance",
        "/estimates/ukf/covariance",
    ):
        assert counts[topic] == N * T, (topic, counts)
    assert counts["/scenario"] == 1 and counts["/run_status"] == 2
    run = bag_to_arrays(bag)
    assert run.complete and run.trajectories.tolist() == [0, 1]
    assert all(v == 0 for v in run.missing.values()) and not run.rejected and not run.duplicates
    data = simulate(cart, N, T, seed=3)  # the simulator publishes exactly these data
    np.testing.assert_array_equal(run.x, data.x)
    np.testing.assert_array_equal(run.y, data.y)
    np.testing.assert_array_equal(run.u[:, :-1], data.u[:, :-1])
    for m in ("ekf", "ukf"):
        assert np.isfinite(run.x_hat[m]).all() and np.isfinite(run.P_hat[m]).all()
    assert np.all(np.diff(run.stamps.reshape(-1)) > 0)

    # the evaluator's metrics, from the file
    metrics = res.metrics()
    assert set(metrics["methods"]) == {"ekf", "ukf"} and metrics["trajectories"] == N
    for m in ("ekf", "ukf"):
        rmse = metrics["methods"][m]["rmse"]
        assert 0 < rmse < 1.0 and metrics["methods"][m]["n_diverged"] == 0
    assert {"markdown", "json", "png"} <= set(res.reports) and res.reports["png"].stat().st_size > 0

    # offline replay of the recorded observations == the live estimates
    out = replay(bag, ["ekf", "ukf"], tmp_path / "replayed.mcap")
    assert out.estimates == {"ekf": N * T, "ukf": N * T}
    rep = bag_to_arrays(out.path)
    for m in ("ekf", "ukf"):
        np.testing.assert_allclose(rep.x_hat[m], run.x_hat[m], rtol=0, atol=1e-12)
        np.testing.assert_allclose(rep.P_hat[m], run.P_hat[m], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(rep.x, run.x)  # the rest of the bag is carried over


# ---- started by hand, in any order -----------------------------------------------------------------------------
_UP = {"sim": ("trajectories x",), "est": ("waiting for the scenario", "ukf on"), "rec": ("recording to",)}


@pytest.mark.parametrize("order", list(itertools.permutations(("sim", "est", "rec"))), ids="-".join)
def test_hand_started_nodes_lose_nothing_in_any_order(order, plugin, nodes, tmp_path):
    """The README's hand-start commands (defaults, no wait_for_subscribers), one node after the
    other once the previous one is up; the evaluator on simulation time (/clock from the simulator)."""
    bag = tmp_path / "hand.mcap"
    N, T = 2, 40
    start = {
        "sim": lambda: nodes.start(
            SIMULATOR,
            "sim",
            scenario="nodecart",
            plugins=[plugin],
            trajectories=N,
            horizon=T,
            rate_hz=100.0,
            publish_clock=True,
        ),
        "est": lambda: nodes.start(ESTIMATOR, "est", method="ukf", plugins=[plugin]),
        "rec": lambda: nodes.start(EVALUATOR, "rec", output=str(bag), plugins=[plugin], use_sim_time=True),
    }
    for name in order:
        start[name]()
        t0 = time.monotonic()
        while not any(text in nodes.log(name) for text in _UP[name]):
            assert time.monotonic() - t0 < 60, nodes.log(name)
            assert nodes.procs[name].poll() is None, nodes.log(name)
            time.sleep(0.1)
    assert nodes.wait("rec", 120) == 0, nodes.log("rec") + nodes.log("est") + nodes.log("sim")
    with BagReader(bag, strict=True) as reader:
        counts = {t: c.msgcount for t, c in reader.topics.items()}
    for topic in ("/observation", "/ground_truth", "/estimates/ukf", "/estimates/ukf/covariance"):
        assert counts.get(topic) == N * T, (order, counts)
    metrics = json.loads(bag.with_name("hand.metrics.json").read_text())
    assert metrics["trajectories"] == N and set(metrics["methods"]) == {"ukf"}
