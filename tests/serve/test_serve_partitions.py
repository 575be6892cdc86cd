"""Partitioned serving (`links serve --shards N`; docs/reference/contract.md, HTTP API) on real Ray
(2 CPUs), real Parquet and real HTTP on loopback.

The index is split into N partitions, each served by its own deployment, and the gateway merges
their answers. The dataset is small enough that every part's search, and one index's, estimates
every path: over HTTP the answers must then be one index's exactly (same path ids, same chamfer
distances, same mechanisms), and the exact brute force's, for N = 1, 2 and 4. Each part builds
and saves only its own folder under `_links/index/`. Where the searches scan, partitioned answers
are compared with one index's in test_retrieval_scale.py; failures and load are in
test_serve_load.py.
"""

from __future__ import annotations

import json
import re
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import links_ray
from links_ray.data.commit import committed_shards
from links_ray.data.store import Store
from links_ray.engine.synthesis.options import DEFAULT_SYNTHESIS_TRANSMISSION_DEG
from links_ray.engine.synthesis.plan import pooled, retrievals
from links_ray.search.index import RetrievalIndex
from links_ray.serve.app import build_app
from tests.support.serving import as_served, retrieved, serving

#: Results per query in the comparisons.
K = 5
#: Partition replicas' CPUs: four partitions and the gateway (one CPU) fill the 2-CPU test cluster.
SHARD_CPUS = 0.25


@pytest.fixture(scope="module")
def partitioned_root(dataset: str, tmp_path_factory: pytest.TempPathFactory) -> str:
    """A copy of the dataset with no saved index (and no leases): what the partitions save in it
    is theirs alone."""
    root = tmp_path_factory.mktemp("partitioned") / "links"
    shutil.copytree(dataset, root, ignore=shutil.ignore_patterns("index", "leases"))
    assert not (root / "_links" / "index").exists()
    return str(root)


def part_rows(root: str, parts: int) -> list[int]:
    """Curated rows of each part when the curated shards are split in `parts` (by markers)."""
    rows = [0] * parts
    for shard, marker in committed_shards(Store.open(root), "curation").items():
        rows[shard % parts] += marker["rows"].get("curated", 0)
    return rows


@pytest.fixture(scope="module", params=[1, 2, 4], ids=lambda n: f"{n}-partitions")
def partitioned(
    request: pytest.FixtureRequest, partitioned_root: str, serve_port: int
) -> Iterator[Any]:
    """(N, client) of the app with its index in N partitions on `partitioned_root`."""
    partitions = request.param
    with serving(
        build_app(partitioned_root, shards=partitions, shard_cpus=SHARD_CPUS), serve_port
    ) as c:
        yield partitions, c


def test_health_reports_the_shards(
    partitioned: Any, dataset_index: RetrievalIndex, partitioned_root: str
) -> None:
    partitions, client = partitioned
    rows = part_rows(partitioned_root, partitions)
    assert len(rows) == partitions and all(rows), rows  # every part holds curated paths
    status, data = client.get("/api/health")
    assert status == 200
    assert data == {
        "status": "ok",
        "paths": len(dataset_index),
        "shards": [{"part": part, "paths": rows[part]} for part in range(partitions)],
    }


def test_answers_are_one_index_answers(
    partitioned: Any, dataset_index: RetrievalIndex, queries: list[np.ndarray]
) -> None:
    """Same results as one index over every path, to the bit, and as the exact brute force."""
    _, client = partitioned
    for number, query in enumerate(queries):
        got = retrieved(client, query, K)
        expected = as_served(dataset_index.retrieve(query, K))
        assert [r["path_id"] for r in got] == [r["path_id"] for r in expected], number
        assert [r["chamfer"] for r in got] == [r["chamfer"] for r in expected], number
        assert got == expected, number  # points and mechanisms too
        exact = dataset_index.brute_force(query, K)
        rows = np.array([row for row, _, _ in exact])
        assert [r["path_id"] for r in got] == dataset_index.path_ids(rows).tolist(), number
        assert [r["chamfer"] for r in got] == [distance for _, distance, _ in exact], number


def test_k_beyond_a_part_and_stored_paths(
    partitioned: Any, dataset_index: RetrievalIndex, dataset: str
) -> None:
    """k = 100, more than the finalists a part measures exactly beyond the first few: 100
    distinct results, best first, led by the dataset's own path (at distance 0) and one
    index's best. (Deeper down the parts' answers are better than one index's, whose
    finalists are then about as many as k, so they are not compared there.)"""
    _, client = partitioned
    curated = links_ray.load(dataset, "curated", columns=["path_id", "points"], reshape=True)
    for row in (0, 17, len(curated) - 1):
        query = curated.points.iloc[row].astype(np.float64) * 5 + 3
        got = retrieved(client, query, 100)
        chamfers = [result["chamfer"] for result in got]
        assert len({result["path_id"] for result in got}) == 100
        assert chamfers == sorted(chamfers) and chamfers[0] < 1e-6
        assert got[:K] == as_served(dataset_index.retrieve(query, K))


def test_each_partition_wrote_only_its_own_part(partitioned: Any, partitioned_root: str) -> None:
    partitions, _ = partitioned
    folder = Path(partitioned_root) / "_links" / "index"
    saved = {entry.name for entry in folder.iterdir() if entry.is_dir()}
    # Parts of the splits served so far in this module, and never the whole index's.
    assert all(re.fullmatch(r"part-\d+-of-[124]", name) for name in saved), saved
    assert {name for name in saved if name.endswith(f"-of-{partitions}")} == {
        f"part-{part}-of-{partitions}" for part in range(partitions)
    }
    rows = part_rows(partitioned_root, partitions)
    for part in range(partitions):
        current = json.loads((folder / f"part-{part}-of-{partitions}" / "current.json").read_text())
        assert current["rows"] == rows[part]


@pytest.mark.parametrize("option", ["min_transmission", "max_joints"])
def test_a_filter_is_one_index_answer(
    partitioned: Any, dataset_index: RetrievalIndex, queries: list[np.ndarray], option: str
) -> None:
    """`min_transmission` and `max_joints` go to every part: the merged answer is one
    index's, every result within the filter."""
    _, client = partitioned
    floor = float(np.quantile(dataset_index.transmission, 0.5))
    most = int(np.median(dataset_index.n_joints))
    value = floor if option == "min_transmission" else most
    for query in queries[:3]:
        body = {"points": np.asarray(query).tolist(), "k": K, option: value}
        status, data = client.post("/api/retrieve", body)
        assert status == 200, data
        expected = as_served(dataset_index.retrieve(query, K, **{option: value}))
        assert len(expected) == K and data["results"] == expected
        for result in expected:
            assert result["min_transmission_deg"] >= floor or option != "min_transmission"
            assert result["n_joints"] <= most or option != "max_joints"


def test_synthesis_refines_what_the_partitions_retrieve(
    partitioned: Any, dataset_index: RetrievalIndex, queries: list[np.ndarray]
) -> None:
    """/api/synthesize on a partitioned app starts from the merged retrieval's candidates and
    refines them: each result no worse than its retrieved path, which is among the paths one
    index returns for the retrievals synthesis asks for (`synthesis_plan.retrievals`)."""
    _, client = partitioned
    query = queries[0]
    body = {"points": np.asarray(query).tolist(), "k": 2, "seconds": 0.5}
    status, data = client.post("/api/synthesize", body)
    assert status == 200, data
    results = data["results"]
    assert len(results) == 2
    # What one index returns for the retrievals synthesis asks for: CANDIDATES keeping the
    # default floor, and more with none.
    asked = retrievals(2, None, False, DEFAULT_SYNTHESIS_TRANSMISSION_DEG)
    candidates = {
        r["path_id"]: r
        for r in pooled(
            [dataset_index.retrieve(query, count, floor, joints) for count, joints, floor in asked]
        )
    }
    for result in results:
        start = candidates[result["path_id"]]
        assert result["retrieved_chamfer"] == pytest.approx(start["chamfer"], abs=5e-7)
        assert result["chamfer"] <= result["retrieved_chamfer"] + 1e-12
