"""Sharded serving and serving under load (docs/CONTRACT.md, HTTP API), on real Ray (2 CPUs),
real Parquet and real HTTP on loopback.

`links serve --shards N` splits the index into N parts, each served by its own deployment, and
the front merges their answers: over HTTP they must be one index's answers exactly (same path
ids, same chamfer distances), and the exact brute force's where the small dataset makes the
search exact. Each part builds and saves only its own folder under `_links/index/`. A part
that goes away makes retrievals 503, not 500, until Serve has replaced it.

Under load (`LOAD_CLIENTS` clients retrieving for `LOAD_SECONDS`), retrievals beyond the
front's bound are refused at once with 503, `Retry-After` and a JSON error, and health checks
and simulations stay fast.
"""

from __future__ import annotations

import contextlib
import json
import re
import shutil
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from serving import FOUR_BAR, Client

import links_ray
from links_ray.cli.bench_services import (
    _held_out_queries,
    finish_load,
    probe_loop,
    retrieval_load,
    wait_for_port,
)
from links_ray.data.commit import committed_shards
from links_ray.data.store import Store
from links_ray.search.index import RetrievalIndex
from links_ray.serve.app import bindable_port, build_app

#: Results per query in the comparisons.
K = 5
#: The load test: clients retrieving at once, and for how long (seconds) in each setting.
LOAD_CLIENTS = 32
LOAD_SECONDS = 20.0
#: What health checks and simulations must stay under, at the 99th percentile, meanwhile.
PROBE_P99_S = 0.100
#: Shard replicas' CPUs: four shards and the front (one CPU) fill the 2-CPU test cluster.
SHARD_CPUS = 0.25


def _hand_drawn() -> list[np.ndarray]:
    """Curves as a user draws them: an ellipse, a figure eight, a zigzag of five clicks, an
    arc and a kidney, in screen-like coordinates."""
    t = np.linspace(0, 2 * np.pi, 120)
    return [
        np.column_stack([300 + 120 * np.cos(t), 200 + 50 * np.sin(t)]),
        np.column_stack([np.sin(t), np.sin(t) * np.cos(t)]),
        np.array([[0, 0], [1, 0.4], [2, 0.1], [1.5, -0.6], [0.3, -0.4]], dtype=float),
        np.column_stack([np.cos(t[:50]), np.sin(t[:50])]) * 40,
        np.column_stack([(1 + 0.4 * np.cos(t)) * np.cos(t), 0.7 * np.sin(t) + 0.2 * np.sin(2 * t)]),
    ]


@pytest.fixture(scope="module")
def queries() -> list[np.ndarray]:
    """Paths of mechanisms held out of the dataset, in random frames, and hand-drawn curves."""
    return _held_out_queries(6, seed=31) + _hand_drawn()


@pytest.fixture(scope="module")
def reference(dataset: str) -> RetrievalIndex:
    """One index over every curated path of the dataset."""
    return RetrievalIndex.open(dataset)


@pytest.fixture(scope="module")
def shard_root(dataset: str, tmp_path_factory: pytest.TempPathFactory) -> str:
    """A copy of the dataset with no saved index (and no leases): what the shards save in it
    is theirs alone."""
    root = tmp_path_factory.mktemp("shards") / "links"
    shutil.copytree(dataset, root, ignore=shutil.ignore_patterns("index", "leases"))
    assert not (root / "_links" / "index").exists()
    return str(root)


def part_rows(root: str, parts: int) -> list[int]:
    """Curated rows of each part when the curated shards are split in `parts` (by markers)."""
    rows = [0] * parts
    for shard, marker in committed_shards(Store.open(root), "curation").items():
        rows[shard % parts] += marker["rows"].get("curated", 0)
    return rows


@contextlib.contextmanager
def serving(app: Any, port: int) -> Iterator[Client]:
    """Run `app` on Serve, its front answering on `port` (direct ingress, as under `links
    serve`); shut Serve down after."""
    from ray import serve

    wait_for_port(port)  # the last app's front may still be letting go of it
    proxy_port = bindable_port("127.0.0.1", 0)
    no_access_log = {"enable_access_log": False}
    serve.start(
        http_options={"host": "127.0.0.1", "port": proxy_port}, logging_config=no_access_log
    )
    try:
        start = time.perf_counter()
        serve.run(app, name="links", route_prefix="/", logging_config=no_access_log)
        print(f"\nServe app ready in {time.perf_counter() - start:.1f} s")
        yield Client(port)
    finally:
        serve.shutdown()


@pytest.fixture(scope="module", params=[1, 2, 4], ids=lambda n: f"{n}-shards")
def sharded(request: pytest.FixtureRequest, shard_root: str, serve_port: int) -> Iterator[Any]:
    """(N, client) of the app with its index in N shards on `shard_root`."""
    shards = request.param
    with serving(build_app(shard_root, shards=shards, shard_cpus=SHARD_CPUS), serve_port) as c:
        yield shards, c


def _retrieve(client: Client, query: np.ndarray, k: int = K) -> list[dict]:
    status, data = client.post("/api/retrieve", {"points": query.tolist(), "k": k})
    assert status == 200, data
    return data["results"]


def test_health_reports_the_shards(sharded: Any, reference: RetrievalIndex, shard_root: str):
    shards, client = sharded
    rows = part_rows(shard_root, shards)
    assert all(rows), rows  # every part holds curated paths
    status, data = client.get("/api/health")
    assert status == 200
    assert data == {
        "status": "ok",
        "paths": len(reference),
        "shards": [{"part": part, "paths": rows[part]} for part in range(shards)],
    }


def test_answers_are_one_index_answers(
    sharded: Any, reference: RetrievalIndex, queries: list[np.ndarray]
) -> None:
    """Same results as one index over every path, to the bit, and as the exact brute force."""
    _, client = sharded
    for number, query in enumerate(queries):
        got = _retrieve(client, query)
        # As one index answers it, through the same JSON (floats round-trip exactly).
        expected = json.loads(json.dumps(reference.retrieve(query, K)))
        assert [r["path_id"] for r in got] == [r["path_id"] for r in expected], number
        assert [r["chamfer"] for r in got] == [r["chamfer"] for r in expected], number
        assert got == expected, number  # points and mechanisms too
        exact = reference.brute_force(query, K)
        rows = np.array([row for row, _, _ in exact])
        assert [r["path_id"] for r in got] == reference.path_ids(rows).tolist(), number
        assert [r["chamfer"] for r in got] == [distance for _, distance, _ in exact], number


def test_k_beyond_a_part_and_stored_paths(
    sharded: Any, reference: RetrievalIndex, dataset: str
) -> None:
    """k = 100, more than the finalists a part measures exactly beyond the first few: 100
    distinct results, best first, led by the dataset's own path (at distance 0) and one
    index's best. (Deeper down the parts' answers are better than one index's, whose
    finalists are then about as many as k, so they are not compared there.)"""
    _, client = sharded
    curated = links_ray.load(dataset, "curated", columns=["path_id", "points"], reshape=True)
    for row in (0, 17, len(curated) - 1):
        query = curated.points.iloc[row].astype(np.float64) * 5 + 3
        got = _retrieve(client, query, k=100)
        chamfers = [result["chamfer"] for result in got]
        assert len({result["path_id"] for result in got}) == 100
        assert chamfers == sorted(chamfers) and chamfers[0] < 1e-6
        expected = json.loads(json.dumps(reference.retrieve(query, K)))
        assert got[:K] == expected


def test_each_shard_wrote_only_its_own_part(sharded: Any, shard_root: str) -> None:
    shards, _ = sharded
    folder = Path(shard_root) / "_links" / "index"
    saved = {entry.name for entry in folder.iterdir() if entry.is_dir()}
    # Parts of the splits served so far in this module, and never the whole index's.
    assert all(re.fullmatch(r"part-\d+-of-[124]", name) for name in saved), saved
    assert {name for name in saved if name.endswith(f"-of-{shards}")} == {
        f"part-{part}-of-{shards}" for part in range(shards)
    }
    rows = part_rows(shard_root, shards)
    for part in range(shards):
        current = json.loads((folder / f"part-{part}-of-{shards}" / "current.json").read_text())
        assert current["rows"] == rows[part]


def _kill_replicas(deployment: str) -> int:
    """Kill the Serve replica actors of `deployment` (by their own handles); how many."""
    import ray

    killed = 0
    for actor in ray.util.list_named_actors(all_namespaces=True):
        if f"#{deployment}#" in actor["name"]:
            ray.kill(ray.get_actor(actor["name"], namespace=actor["namespace"]), no_restart=True)
            killed += 1
    return killed


def test_a_lost_shard_is_503_until_serve_replaces_it(
    shard_root: str, serve_port: int, reference: RetrievalIndex, queries: list[np.ndarray]
) -> None:
    """Retrievals while a part is gone are 503 with Retry-After and a JSON error, never a
    500 or a dropped connection; health keeps answering; then answers come back as before."""
    app = build_app(shard_root, shards=2, shard_cpus=SHARD_CPUS, shard_timeout_s=2.0)
    query = queries[0]
    expected = json.loads(json.dumps(reference.retrieve(query, K)))
    with serving(app, serve_port) as client:
        assert client.get("/api/health")[0] == 200
        assert _retrieve(client, query) == expected
        assert _kill_replicas("IndexShard-1-of-2") == 1
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
                assert "index shard 1 of 2 is unavailable" in data["error"] or (
                    "did not answer" in data["error"]
                ), data
                assert client.get("/api/health")[0] == 200
            elif 503 in seen:
                assert data["results"] == expected
                break
            time.sleep(0.2)
        assert 503 in seen and seen[-1] == 200, seen


def _simulated() -> list:
    return links_ray.simulate(**FOUR_BAR).tolist()


@pytest.mark.parametrize("shards", [None, 2], ids=["one-index", "2-shards"])
def test_under_load(
    shards: int | None,
    dataset: str,
    shard_root: str,
    serve_port: int,
    reference: RetrievalIndex,
    queries: list[np.ndarray],
) -> None:
    """LOAD_CLIENTS clients retrieve for LOAD_SECONDS while another checks health and
    simulates: only 200s and 503s (with Retry-After and a JSON error), health and simulate
    p99 under PROBE_P99_S, and afterwards the server answers as before."""
    root = dataset if shards is None else shard_root
    app = build_app(root, shards=shards, shard_cpus=SHARD_CPUS)
    with serving(app, serve_port) as client:
        load = retrieval_load(client.port, queries, LOAD_SECONDS, LOAD_CLIENTS)
        try:
            probes = probe_loop(client.port, LOAD_SECONDS)
        finally:
            record = finish_load(load)
        statuses = record["statuses"]
        answered = statuses.get("200", 0)
        print(
            f"\n{shards or 'no'} shards: {statuses} in {record['seconds']:.1f} s "
            f"({answered / record['seconds']:.0f} retrievals/s); "
            f"health p50/p99 {np.percentile(probes['health'], 50) * 1e3:.1f}/"
            f"{np.percentile(probes['health'], 99) * 1e3:.1f} ms, "
            f"simulate p50/p99 {np.percentile(probes['simulate'], 50) * 1e3:.1f}/"
            f"{np.percentile(probes['simulate'], 99) * 1e3:.1f} ms; "
            f"retrieve p50/p99 {np.percentile(record['latencies'], 50) * 1e3:.0f}/"
            f"{np.percentile(record['latencies'], 99) * 1e3:.0f} ms"
        )
        assert set(statuses) <= {"200", "503"}, statuses
        assert answered > 0 and statuses.get("503", 0) > 0, statuses
        assert record["no_retry_after"] == 0 and record["not_json"] == 0, record
        assert set(probes["statuses"]) == {"health 200", "simulate 200"}, probes["statuses"]
        assert len(probes["health"]) > 20 and len(probes["simulate"]) > 20
        assert np.percentile(probes["health"], 99) < PROBE_P99_S
        assert np.percentile(probes["simulate"], 99) < PROBE_P99_S
        # Afterwards: answers as before.
        status, data = client.get("/api/health")
        assert status == 200 and data["paths"] == len(reference)
        status, data = client.post("/api/simulate", FOUR_BAR)
        assert status == 200 and data["trajectories"] == _simulated()
        expected = json.loads(json.dumps(reference.retrieve(queries[1], K)))
        assert _retrieve(client, queries[1]) == expected
