"""POST /api/retrieve over real HTTP: a stored path found as stored, moved, turned or mirrored,
with a mechanism that traces it in the query's frame; k results, best first; the
min_transmission and max_joints filters (the `client` fixture's app, checked against
`dataset`'s curated paths and its index)."""

from typing import Any

import numpy as np
import pytest

import links_ray
from links_ray.engine import inputs
from tests.support.serving import Client, as_served, post_ok

RESULT_FIELDS = {
    "path_id",
    "n_joints",
    "mechanism_id",
    "joint",
    "chamfer",
    "points",
    "mechanism",
    "mechanism_joint",
}


def _check_result(result: dict[str, Any]) -> None:
    assert set(result) >= RESULT_FIELDS
    mechanism = result["mechanism"]
    assert set(mechanism) >= {"adjacency", "node_types", "positions"}
    n = len(mechanism["node_types"])
    assert np.array(mechanism["adjacency"]).shape == (n, n)
    assert np.array(mechanism["positions"]).shape == (n, 2)
    assert 0 <= result["mechanism_joint"] < n
    assert result["n_joints"] == n
    assert np.array(result["points"]).shape == (200, 2)
    assert isinstance(result["chamfer"], float) and result["chamfer"] >= 0


@pytest.mark.parametrize("where", ["as stored", "moved and scaled", "turned", "mirrored"])
def test_retrieve_finds_a_stored_path_and_a_mechanism_that_traces_it(
    client: Client, curated: Any, where: str
) -> None:
    row = 17 % len(curated)
    stored = curated.points.iloc[row].astype(np.float64)
    query = {
        "as stored": stored,
        "moved and scaled": stored * 3.0 + 7.0,
        "turned": (stored - 0.5) @ np.array([[0.0, -1.0], [1.0, 0.0]]) * 0.2 + 1.0,
        "mirrored": stored * np.array([1.0, -1.0]) + 2.0,
    }[where]
    _, data = post_ok(client, "/api/retrieve", {"points": query.tolist(), "k": 5})
    results = data["results"]
    assert isinstance(data["took_ms"], float) and data["took_ms"] >= 0
    assert len(results) == 5
    for result in results:
        _check_result(result)
    chamfers = [result["chamfer"] for result in results]
    assert chamfers == sorted(chamfers), "best first"
    assert chamfers[0] < 1e-6
    best = results[0]
    assert best["path_id"] == int(curated.path_id.iloc[row]) or chamfers[1] < 1e-6
    # A floor on the transmission angle: only paths keeping it, the best of them first.
    floor = 5.0
    _, kept = post_ok(
        client, "/api/retrieve", {"points": query.tolist(), "k": 5, "min_transmission": floor}
    )
    keeping = [r for r in results if r["min_transmission_deg"] >= floor]
    assert len(kept["results"]) == 5
    assert all(r["min_transmission_deg"] >= floor for r in kept["results"])
    assert [r["path_id"] for r in kept["results"]][: len(keeping)] == [
        r["path_id"] for r in keeping
    ]
    # The mechanism comes back in the query's frame: its joint traces the query itself.
    _, traced = post_ok(client, "/api/simulate", best["mechanism"])
    path = np.array(traced["trajectories"])[best["mechanism_joint"]]
    size = np.ptp(query, axis=0).max()
    assert links_ray.chamfer(path, query) < 1e-4 * size


def test_retrieve_keeps_to_mechanisms_of_at_most_max_joints(
    client: Client, dataset_index: Any, queries: list
) -> None:
    """`max_joints` reaches the index: one index's answer kept to paths whose reduced
    mechanism has at most that many joints (tests/search/test_retrieval.py holds that against brute
    force), each saying its count; null keeps none out; a limit below every path's, none."""
    counts = dataset_index.n_joints
    most = int(np.median(counts))
    for query in queries[:3]:
        body = {"points": np.asarray(query).tolist(), "k": 5}
        _, data = post_ok(client, "/api/retrieve", {**body, "max_joints": most})
        expected = as_served(dataset_index.retrieve(query, 5, max_joints=most))
        assert len(expected) == 5 and data["results"] == expected
        assert all(result["n_joints"] <= most for result in data["results"])
        _, unrestricted = post_ok(client, "/api/retrieve", {**body, "max_joints": None})
        assert unrestricted["results"] == as_served(dataset_index.retrieve(query, 5))
    smallest = int(counts.min())
    if smallest > inputs.MIN_JOINTS:
        _, data = post_ok(client, "/api/retrieve", {**body, "max_joints": smallest - 1})
        assert data["results"] == []
    _, data = post_ok(client, "/api/retrieve", {**body, "max_joints": smallest})
    assert data["results"] and {r["n_joints"] for r in data["results"]} == {smallest}


def test_retrieve_default_k_and_longest_query(client: Client, curated: Any) -> None:
    stored = curated.points.iloc[0].astype(np.float64)
    _, data = post_ok(client, "/api/retrieve", {"points": stored.tolist()})
    assert len(data["results"]) == 3
    many = np.tile(stored, (50, 1))  # exactly 10,000 pairs
    _, data = post_ok(client, "/api/retrieve", {"points": many.tolist(), "k": 1})
    assert data["results"][0]["chamfer"] < 1e-6


@pytest.mark.parametrize("length", [200, 3])
def test_retrieve_gives_k_results_when_the_index_has_them(
    client: Client, curated: Any, length: int
) -> None:
    stored = curated.points.iloc[0].astype(np.float64)[:length]
    _, data = post_ok(client, "/api/retrieve", {"points": stored.tolist(), "k": 100})
    assert len(curated) >= 100
    chamfers = [result["chamfer"] for result in data["results"]]
    assert len(chamfers) == 100
    assert chamfers == sorted(chamfers)
    assert len({result["path_id"] for result in data["results"]}) == 100
