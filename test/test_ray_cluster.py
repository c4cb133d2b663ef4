"""``reproduce`` on a real two-node Ray cluster (``ray.cluster_utils.Cluster``: a head and a worker
node, each its own raylet and object store, on this machine): jobs run on both nodes, the results
equal a local computation of the same jobs, and a second run computes nothing."""

from __future__ import annotations

import json

import pytest

from neural_estimator.cli import main
from neural_estimator.paper.reproduce.jobs import run_job
from neural_estimator.paper.reproduce.plan import plan_jobs
from neural_estimator.paper.reproduce.scales import get_scale

pytestmark = pytest.mark.slow  # a two-node Ray cluster and a small reproduce


@pytest.fixture(scope="module")
def cluster():
    import ray
    from ray.cluster_utils import Cluster

    if ray.is_initialized():  # another module's local instance: a driver joins one Ray at a time
        ray.shutdown()
    node = {"num_cpus": 1, "object_store_memory": 96 << 20}
    for attempt in (1, 2):  # Ray gives a raylet 30 s to register: on a loaded machine, one more try
        c = Cluster()
        try:
            c.add_node(**node)
            c.add_node(**node)
            c.wait_for_nodes(timeout=120)
            break
        except Exception:  # noqa: BLE001  the start-up timeout is a bare Exception in Ray
            c.shutdown()
            if attempt == 2:
                raise
    yield c
    ray.shutdown()
    c.shutdown()


def test_reproduce_on_a_two_node_cluster_equals_the_local_run_and_reruns_from_the_cache(cluster, tmp_path):
    out, cache = tmp_path / "out", tmp_path / "cache"
    args = ["reproduce", "--scale", "smoke", "--scenarios", "lorenz96", "--methods", "ekf"]
    args += ["--address", cluster.address, "--cache-dir", str(cache), "--quiet"]
    assert main([*args, "--out", str(out)]) == 0
    rows = json.loads((out / "reproduce.json").read_text())["jobs"]
    nodes = {node.node_id for node in cluster.list_all_nodes()}
    assert len(nodes) == 2
    ran_on = {r["node"] for r in rows}
    assert ran_on == nodes, "every node of the cluster ran jobs"
    assert all(r["status"] == "computed" for r in rows)
    # the same jobs computed here, without Ray, in a cache of their own: the same results
    jobs = plan_jobs(get_scale("smoke"), ["lorenz96"], ["ekf"])
    assert [json.loads(json.dumps(j.to_json())) for j in jobs] == [r["job"] for r in rows]
    for job, row in list(zip(jobs, rows))[:: max(1, len(rows) // 6)]:
        if job.kind == "runtime":
            continue  # a timing, not a result
        local = run_job(job, tmp_path / "local-cache")
        assert json.loads(json.dumps(local["result"], default=float)) == json.loads(
            json.dumps(row["result"], default=float)
        ), row["job"]
    # a second run on the cluster reads every job back from the cache
    assert main([*args, "--out", str(tmp_path / "again")]) == 0
    again = json.loads((tmp_path / "again" / "reproduce.json").read_text())["jobs"]
    assert [r["status"] for r in again] == ["cached"] * len(again)
