"""The Serve app under load and when a shard fails (docs/reference/contract.md, HTTP API: 503 and
`Retry-After`), on real Ray (2 CPUs) over real HTTP on loopback.

`LOAD_CLIENTS` clients retrieve for `LOAD_SECONDS` (in a process of their own, each waiting
the `Retry-After` it is given) while another checks health and simulates: retrievals beyond
the gateway's bound are refused at once with 503, `Retry-After` and a JSON error, nothing else
fails, health checks and simulations are answered ahead of the queued retrievals, and
afterwards the server answers as before; with one index in the gateway and with the index in
two partitions. A partition whose replica dies makes retrievals 503 until Serve has replaced
it. Clients posting bodies and asking for simulations as large as the limits allow do not hold
up the event loop, which answers health checks.
"""

from __future__ import annotations

import os
import time

import numpy as np
import pytest

import links_ray
from links_ray.bench.load_clients import (
    finish_load,
    health_probes,
    largest_simulation,
    post_load,
    probe_loop,
    retrieval_load,
)
from links_ray.search.index import RetrievalIndex
from links_ray.serve.app import build_app
from links_ray.serve.http.limits import MAX_REQUEST_JOINT_STEPS
from tests.support.serving import FOUR_BAR, as_served, retrieved, serving

#: Results per query in the comparisons.
K = 5
#: The load: clients retrieving at once, and for how long (seconds) in each setting.
LOAD_CLIENTS = 32
LOAD_SECONDS = 10.0
#: Partition replicas' CPUs, so that the partitions and the gateway (one CPU) fit the 2-CPU cluster.
SHARD_CPUS = 0.25


def _kill_replicas(deployment: str) -> int:
    """Kill the Serve replica actors of `deployment` (by their own handles); how many."""
    import ray

    killed = 0
    for actor in ray.util.list_named_actors(all_namespaces=True):
        if f"#{deployment}#" in actor["name"]:
            ray.kill(ray.get_actor(actor["name"], namespace=actor["namespace"]), no_restart=True)
            killed += 1
    return killed


def test_a_lost_partition_is_503_until_serve_replaces_it(
    dataset: str, serve_port: int, dataset_index: RetrievalIndex, queries: list[np.ndarray]
) -> None:
    """Retrievals while a part is gone are 503 with Retry-After and a JSON error, never a
    500 or a dropped connection; health keeps answering; then answers come back as before."""
    app = build_app(dataset, shards=2, shard_cpus=SHARD_CPUS, partition_timeout_s=2.0)
    query = queries[0]
    expected = as_served(dataset_index.retrieve(query, K))
    with serving(app, serve_port) as client:
        assert client.get("/api/health")[0] == 200
        assert retrieved(client, query, K) == expected
        assert _kill_replicas("IndexPartition-1-of-2") == 1
        seen: list[int] = []
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            status, headers, data = client.request(
                "POST", "/api/retrieve", {"points": query.tolist(), "k": K}
            )
            seen.append(status)
            assert status in (200, 503), (status, data)
            if status == 503:
                assert headers.get("retry-after") == "1"
                assert set(data) == {"error"}, data
                assert "index partition 1 of 2 is unavailable" in data["error"] or (
                    "did not answer" in data["error"]
                ), data
                assert client.get("/api/health")[0] == 200
            elif 503 in seen:
                assert data["results"] == expected
                break
            time.sleep(0.2)
        assert 503 in seen and seen[-1] == 200, seen


@pytest.mark.parametrize("shards", [None, 2], ids=["one-index", "2-shards"])
def test_under_load(
    shards: int | None,
    dataset: str,
    serve_port: int,
    dataset_index: RetrievalIndex,
    queries: list[np.ndarray],
) -> None:
    """LOAD_CLIENTS clients retrieve for LOAD_SECONDS while another checks health and
    simulates: only 200s and 503s (with Retry-After and a JSON error); health and simulate
    faster than the retrievals at the median and the 99th percentile (a probe queued behind
    retrievals would wait as long as they do; the load keeps more waiting than the server
    holds), and afterwards the server answers as before. Their speed in milliseconds is
    `links bench serve`'s to measure: here it would measure how busy the machine is."""
    app = build_app(dataset, shards=shards, shard_cpus=SHARD_CPUS)
    with serving(app, serve_port) as client:
        load = retrieval_load(client.port, queries, LOAD_SECONDS, LOAD_CLIENTS)
        try:
            probes = probe_loop(client.port, LOAD_SECONDS)
        finally:
            record = finish_load(load)
        statuses = record["statuses"]
        answered = statuses.get("200", 0)
        latencies = record["latencies"]

        def ms(values: list[float], q: float) -> str:
            return f"{np.percentile(values, q) * 1e3:.1f}" if values else "-"

        print(
            f"\n{shards or 'no'} shards: {statuses} in {record['seconds']:.1f} s "
            f"({answered / record['seconds']:.1f} retrievals/s); health p50/p99 "
            f"{ms(probes['health'], 50)}/{ms(probes['health'], 99)} ms, simulate p50/p99 "
            f"{ms(probes['simulate'], 50)}/{ms(probes['simulate'], 99)} ms; retrieve p50/p99 "
            f"{ms(record['latencies'], 50)}/{ms(record['latencies'], 99)} ms"
        )
        assert set(statuses) <= {"200", "503"}, statuses
        assert answered > 0 and statuses.get("503", 0) > 0, statuses
        assert record["no_retry_after"] == 0 and record["not_json"] == 0, record
        assert set(probes["statuses"]) == {"health 200", "simulate 200"}, probes["statuses"]
        assert len(probes["health"]) > 20 and len(probes["simulate"]) > 20
        for probe in ("health", "simulate"):
            for q in (50, 99):
                took, retrieving = np.percentile(probes[probe], q), np.percentile(latencies, q)
                assert took < retrieving, (
                    f"{probe} p{q} {took * 1e3:.1f} ms, retrieve {retrieving * 1e3:.1f} ms"
                )
        # Afterwards: answers as before.
        status, data = client.get("/api/health")
        assert status == 200 and data["paths"] == len(dataset_index)
        status, data = client.post("/api/simulate", FOUR_BAR)
        assert status == 200 and data["trajectories"] == links_ray.simulate(**FOUR_BAR).tolist()
        assert retrieved(client, queries[1], K) == as_served(dataset_index.retrieve(queries[1], K))


#: Clients posting the largest bodies and simulations at once, and for how long (seconds).
BIG_CLIENTS, BIG_SECONDS = 8, 10.0


def test_health_is_answered_while_the_largest_bodies_and_answers_are_handled(
    dataset: str, serve_port: int
) -> None:
    """BIG_CLIENTS clients post bodies of MAX_BODY_BYTES asking for simulations of
    MAX_REQUEST_JOINTS joints x their most steps (100 x 1,000, about 4 MB of JSON back), one
    of them a byte more (413), for BIG_SECONDS: every answer is 200, 413 or 503, every health
    check meanwhile is answered, and waits less than a large request takes (the 99th percentile
    of health against the median large simulation: health never queues behind them); the large
    answer is right. How fast health stays in absolute terms is measured by `links bench serve`,
    not here: a bound in milliseconds would measure how busy the machine is."""
    largest = largest_simulation()
    body = largest["body"]
    assert len(body["node_types"]) * body["steps"] == MAX_REQUEST_JOINT_STEPS
    over = largest["text"] + " "
    expected = links_ray.simulate(**body).tolist()
    with serving(build_app(dataset), serve_port) as client:
        status, data = client.post("/api/simulate", largest["text"].encode())
        assert status == 200 and data["trajectories"] == expected
        # Client i posts bodies i, i + BIG_CLIENTS, ... in turn: the last client alternates
        # the body over the limit, refused at once, with the largest simulation, so that it
        # does not only upload bodies to be refused; the others post the largest simulation.
        # They run below the server's priority: clients on other machines take none of its CPU.
        bodies = [largest["text"]] * (2 * BIG_CLIENTS - 1) + [over]
        load = post_load(client.port, "/api/simulate", bodies, BIG_SECONDS, BIG_CLIENTS, 10)
        try:
            probes = health_probes(client.port, BIG_SECONDS)
        finally:
            record = finish_load(load)
        statuses = record["statuses"]
        latencies = np.array(probes["latencies"])
        p50, p99 = np.percentile(latencies, [50, 99])
        large = float(np.median(record["latencies"]))
        print(
            f"\nlargest bodies: {statuses} in {record['seconds']:.1f} s; health p50/p99/max "
            f"{p50 * 1e3:.1f}/{p99 * 1e3:.1f}/{latencies.max() * 1e3:.1f} ms over "
            f"{len(latencies)} checks; large simulations p50 {large * 1e3:.1f} ms; "
            f"load average {os.getloadavg()[0]:.1f}"
        )
        assert set(statuses) <= {"200", "413", "503"}, statuses
        assert statuses.get("200", 0) >= BIG_CLIENTS and statuses.get("413", 0) > 0, statuses
        assert record["not_json"] == 0, record
        assert set(probes["statuses"]) == {200} and len(latencies) > 50, probes["statuses"]
        assert p99 < large, (
            f"health p99 {p99 * 1e3:.1f} ms, a large simulation's median {large * 1e3:.1f} ms"
        )
        status, data = client.post("/api/simulate", largest["text"].encode())
        assert status == 200 and data["trajectories"] == expected
