"""Synthesis reads retrieval's arrays as they are: each result holds numpy arrays of fixed dtypes
and shapes, a candidate's positions are the result's own array (no copy, no list between) and its
topology is analyzed from the result's adjacency and node types themselves; refinement leaves the
retrieved arrays as they were; and a retriever answering lists still gets the same synthesis.
The arrays against the index's, and the JSON written from them: tests/search/test_result_arrays.py.
"""

from __future__ import annotations

import copy
from typing import Any

import numpy as np
import pytest

from links_ray.engine.synthesis import candidates as synthesis_candidates
from links_ray.engine.synthesis.candidates import candidate
from links_ray.engine.synthesis.options import DEFAULT_SYNTHESIS_TRANSMISSION_DEG, SynthesisOptions
from links_ray.engine.synthesis.pipeline import refine_retrieved, synthesize
from links_ray.engine.synthesis.plan import RetrievalResult, pooled, retrievals
from links_ray.engine.synthesis.target import as_target
from links_ray.search.index import RetrievalIndex
from tests.support.results import assert_same_results
from tests.support.serving import hand_drawn

FLOOR = DEFAULT_SYNTHESIS_TRANSMISSION_DEG


def retrieved_for(index: RetrievalIndex, drawn: np.ndarray) -> list[RetrievalResult]:
    """What synthesis retrieves for `drawn` at its default floor (CANDIDATES and more), pooled."""
    return pooled(
        [
            index.retrieve(drawn, count, floor, most)
            for count, most, floor in retrievals(3, None, False, FLOOR)
        ]
    )


def test_results_hold_arrays_of_fixed_dtypes_and_shapes(
    dataset_index: RetrievalIndex, queries: list
) -> None:
    retrieved = retrieved_for(dataset_index, queries[0])
    assert len(retrieved) > 3
    for result in retrieved:
        mechanism = result["mechanism"]
        n = result["n_joints"]
        for value, dtype, shape in (
            (result["points"], np.float64, (dataset_index.steps, 2)),
            (mechanism["adjacency"], np.uint8, (n, n)),
            (mechanism["node_types"], np.int8, (n,)),
            (mechanism["positions"], np.float64, (n, 2)),
        ):
            assert type(value) is np.ndarray
            assert (value.dtype, value.shape) == (np.dtype(dtype), shape)
        assert mechanism["positions"].flags.c_contiguous
        for key in ("path_id", "mechanism_id", "joint", "n_joints", "mechanism_joint"):
            assert type(result[key]) is int, key
        assert type(result["chamfer"]) is float


def test_candidates_are_built_from_the_retrieved_arrays(
    dataset_index: RetrievalIndex, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Each candidate's topology is analyzed from the result's own arrays, and its positions
    (where refinement starts and what it keeps the branches of) are the result's array."""
    given: list[tuple[Any, Any]] = []
    analyze = synthesis_candidates.analyze_topology

    def recording(adjacency: Any, node_types: Any) -> Any:
        given.append((adjacency, node_types))
        return analyze(adjacency, node_types)

    monkeypatch.setattr(synthesis_candidates, "analyze_topology", recording)
    drawn = hand_drawn()[0]
    target = as_target(drawn, False)
    built = 0
    for result in retrieved_for(dataset_index, drawn):
        mechanism = result["mechanism"]
        given.clear()
        made = candidate(result, target, None, FLOOR)
        assert len(given) == 1
        assert given[0][0] is mechanism["adjacency"] and given[0][1] is mechanism["node_types"]
        if made is None:  # locks between the simulation's steps: no candidate
            continue
        built += 1
        assert made.result is result
        assert made.origin is mechanism["positions"] and made.positions is made.origin
        np.testing.assert_array_equal(made.topology.adjacency, mechanism["adjacency"])
        np.testing.assert_array_equal(made.topology.node_types, mechanism["node_types"])
        assert made.joint == result["mechanism_joint"]
    assert built > 3


def test_refinement_leaves_the_retrieved_arrays_as_they_were(
    dataset_index: RetrievalIndex,
) -> None:
    """Candidates hold the results' arrays uncopied: refinement must copy what it changes."""
    drawn = hand_drawn()[4]
    retrieved = retrieved_for(dataset_index, drawn)
    before = copy.deepcopy(retrieved)
    options = SynthesisOptions(k=3, seed=0, iterations=300)
    results = refine_retrieved(drawn, retrieved, options)
    assert len(results) == 3
    assert any(r["chamfer"] < r["retrieved_chamfer"] for r in results), "nothing was refined"
    assert_same_results(retrieved, before)


class ListRetriever:
    """An index whose answers hold lists, as a retriever of one's own may answer."""

    def __init__(self, index: RetrievalIndex) -> None:
        self.index = index

    def retrieve(
        self, points: object, k: int = 3, min_transmission: float = 0.0, max_joints: Any = None
    ) -> list[dict]:
        results = self.index.retrieve(points, k, min_transmission, max_joints)
        return [
            {
                **result,
                "points": result["points"].tolist(),
                "mechanism": {key: a.tolist() for key, a in result["mechanism"].items()},
            }
            for result in results
        ]


def test_a_retriever_answering_lists_gets_the_same_synthesis(
    dataset_index: RetrievalIndex,
) -> None:
    drawn = hand_drawn()[1]
    asked = {"k": 2, "seed": 0, "iterations": 200}
    from_arrays = synthesize(dataset_index, drawn, **asked)
    from_lists = synthesize(ListRetriever(dataset_index), drawn, **asked)
    assert len(from_arrays) == 2
    assert_same_results(list(from_lists), list(from_arrays))
