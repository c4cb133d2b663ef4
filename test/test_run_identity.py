"""Two publishers of one run are detected in-band: two simulators on one topic
gave a scored table from mixed runs (EKF RMSE 104 against 57.7 clean), with "run started" logged
twice in 80 ms and no warning. Each observation's stamp names its run's start
(stamp - (n T + k) dt), so the evaluator's RunIdentity counts what belongs to another run."""

from __future__ import annotations

import numpy as np

from neural_estimator.stream import messages as MSG
from neural_estimator.data import simulate
from neural_estimator.nodes.run_identity import MAX_STARTS, RunIdentity
from neural_estimator.scenarios import make_scenario

N, T = 2, 10


def _run(scen, data, start_ns):
    period = MSG.dt_ns(scen.dt)
    codec = MSG.VectorCodec(scen.name, MSG.observation_labels(scen))
    announce = MSG.encode_scenario(
        scen.describe(), trajectories=N, horizon=T, start_ns=start_ns, dt_ns=period, messages=N * T
    )
    obs = [
        codec.encode(
            MSG.step_stamp_ns(start_ns, n * T + k, period),
            n,
            k,
            np.concatenate([data.y[n, k], data.u[n, k - 1] if k else np.zeros(scen.du)]),
        )
        for n in range(N)
        for k in range(T)
    ]
    return announce, obs


def test_one_publisher_is_one_run():
    scen = make_scenario("bearings")
    data = simulate(scen, N, T, seed=3)
    announce, obs = _run(scen, data, 10**18)
    ident = RunIdentity()
    assert ident.on_started() is None and ident.on_scenario(announce) is None
    assert [ident.on_observation(raw) for raw in obs] == [None] * (N * T)
    assert not ident.mixed and ident.report() == [] and ident.checked == N * T


def test_two_simulators_on_one_topic_are_reported():
    scen = make_scenario("bearings")
    data = simulate(scen, N, T, seed=3)
    a_announce, a_obs = _run(scen, data, 10**18)
    b_announce, b_obs = _run(scen, data, 10**18 + 80_000_000)  # the second one started 80 ms later
    ident = RunIdentity()
    warnings = [ident.on_started(), ident.on_scenario(a_announce), ident.on_started(), ident.on_scenario(b_announce)]
    assert warnings[:2] == [None, None]
    assert "started' received twice" in warnings[2] and "second run was announced" in warnings[3]
    texts = [ident.on_observation(raw) for pair in zip(a_obs, b_obs) for raw in pair]
    first = [t for t in texts if t]
    assert len(first) == 1 and "belongs to another run (start_ns 1000000000080000000" in first[0]
    assert ident.mixed and ident.foreign == {10**18 + 80_000_000: N * T}
    report = ident.report()
    assert report[0].startswith(f"MIXED RUNS: {N * T} of {2 * N * T} observations") and "\n" not in report[0]


def test_same_identities_same_values_other_start_still_differ():
    """A forged copy of the stream with the same (n, k) and values but its own clock is another run."""
    scen = make_scenario("bearings")
    data = simulate(scen, N, T, seed=3)
    announce, obs = _run(scen, data, 10**18)
    _, later = _run(scen, data, 10**18 + 1)
    ident = RunIdentity()
    ident.on_scenario(announce)
    for raw in obs[:5] + later[5:]:
        ident.on_observation(raw)
    assert sum(ident.foreign.values()) == N * T - 5


def test_foreign_starts_are_counted_in_bounded_memory():
    scen = make_scenario("bearings")
    data = simulate(scen, N, T, seed=3)
    announce, _ = _run(scen, data, 10**18)
    ident = RunIdentity()
    ident.on_scenario(announce)
    for i in range(1, 3 * MAX_STARTS):
        ident.on_observation(_run(scen, data, 10**18 + i)[1][0])
    assert len(ident.foreign) == MAX_STARTS + 1 and sum(ident.foreign.values()) == 3 * MAX_STARTS - 1


def test_the_evaluators_recorder_reports_a_second_run(monkeypatch):
    """The evaluator node's recorder (EvaluatorNode._recorder) feeds /scenario and /observation to
    its RunIdentity and logs the first message of another run; run here on a stand-in node."""
    import types

    import pytest

    E = pytest.importorskip("neural_estimator.nodes.evaluator_node")
    scen = make_scenario("bearings")
    data = simulate(scen, N, T, seed=3)
    a_announce, a_obs = _run(scen, data, 10**18)
    _, b_obs = _run(scen, data, 10**18 + 80_000_000)
    warnings, written = [], []
    ev = types.SimpleNamespace(
        closed=False,
        write_error=None,
        unrecorded=0,
        _max_bytes=0,
        sim_time=False,
        counts={"/scenario": 0, "/observation": 0},
        _last_stream=None,
        identity=RunIdentity(),
        bag=types.SimpleNamespace(write=lambda *a, **k: written.append(a[0])),
        get_logger=lambda: types.SimpleNamespace(warning=warnings.append, info=lambda text: None),
    )
    info = {"received_timestamp": 1, "source_timestamp": 1}
    record_scenario = E.EvaluatorNode._recorder(ev, "/scenario", MSG.topic_role("/scenario"))
    record_obs = E.EvaluatorNode._recorder(ev, "/observation", MSG.topic_role("/observation"))
    record_scenario(a_announce, info)
    for a, b in zip(a_obs, b_obs):
        record_obs(a, info)
        record_obs(b, info)
    assert len(written) == 1 + 2 * N * T  # everything recorded as it arrived
    assert len(warnings) == 1 and "belongs to another run" in warnings[0]
    assert ev.identity.report()[0].startswith(f"MIXED RUNS: {N * T} of {2 * N * T}")
