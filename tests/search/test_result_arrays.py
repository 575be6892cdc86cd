"""Retrieval results hold numpy arrays, equal to what the index's own arrays give when worked out
apart from `RetrievalIndex.retrieve`; and the JSON written from them, the HTTP answers and
`links retrieve --json`, is byte for byte what it was when results held lists. Made without Ray
(tests/support/local_dataset.py). Synthesis reading the arrays: tests/engine/synthesis/
test_retrieved_arrays.py.
"""

from __future__ import annotations

import asyncio
import json
import math
from pathlib import Path

import numpy as np
import pytest

from links_ray.data.generation import GenerationPlan
from links_ray.engine.inputs import validate_query
from links_ray.engine.kinematics.mechanism import reduce_mechanism
from links_ray.engine.kinematics.paths import normalization
from links_ray.search.index import RetrievalIndex
from links_ray.search.placement import into_query_frame
from links_ray.serve.http.responses import (
    JSON_PIECE_NUMBERS,
    JsonResponse,
    render_json,
    rendered_json,
)
from tests.support.local_dataset import generate_and_curate
from tests.support.serving import hand_drawn


@pytest.fixture(scope="module")
def index(tmp_path_factory: pytest.TempPathFactory) -> RetrievalIndex:
    """An index over a few hundred curated paths (more than the largest k)."""
    folder = str(tmp_path_factory.mktemp("result-arrays") / "links")
    plan = GenerationPlan(seed=5, mechanisms=90, topologies_per_shard=3)
    found = RetrievalIndex.open(generate_and_curate(folder, plan))
    assert len(found) > 100
    return found


def queries(index: RetrievalIndex) -> list[np.ndarray]:
    """Stored paths in other frames, and hand-drawn curves."""
    rows = np.random.default_rng(2).choice(len(index), size=2, replace=False)
    moved = [path * 3.0 + [1.0, -2.0] for path in index.paths(rows).astype(np.float64)]
    return [*moved, *hand_drawn()[:3]]


def lists_answer(index: RetrievalIndex, points: np.ndarray, k: int) -> list[dict]:
    """The k best results as retrieval answered when results held lists, worked out from the
    index's ranking, packed mechanisms and traced paths, every array made a list."""
    query, k = validate_query(points, k)
    normalized, matrix, offset = normalization(query)
    answer = []
    for row, distance, variant in index.ranked(normalized, k):
        joint, mechanism_row = int(index.joint[row]), int(index.mechanism_row[row])
        adjacency, node_types, positions, at = reduce_mechanism(
            *index.bank.mechanism(mechanism_row), joint
        )
        placed = into_query_frame(adjacency, node_types, positions, at, variant, matrix, offset)
        transmission = float(index.transmission[row])
        answer.append(
            {
                "path_id": int(index.path_ids(np.array([row]))[0]),
                "mechanism_id": int(index.bank.ids[mechanism_row]),
                "joint": joint,
                "chamfer": distance,
                "min_transmission_deg": None if math.isnan(transmission) else transmission,
                "n_joints": len(node_types),
                "points": index.paths(np.array([row]))[0].astype(float).tolist(),
                "mechanism": {
                    "adjacency": adjacency.tolist(),
                    "node_types": node_types.tolist(),
                    "positions": placed.tolist(),
                },
                "mechanism_joint": at,
            }
        )
    return answer


def test_results_hold_the_indexs_values_as_arrays_of_their_own(index: RetrievalIndex) -> None:
    arrays = {"points": np.float64}
    placed = {"adjacency": np.uint8, "node_types": np.int8, "positions": np.float64}
    for query in queries(index):
        results, expected = index.retrieve(query, 10), lists_answer(index, query, 10)
        assert len(results) == len(expected) == 10
        for result, wanted in zip(results, expected, strict=True):
            assert list(result) == list(wanted)
            for key in result.keys() - {"points", "mechanism"}:
                assert type(result[key]) is type(wanted[key]) and result[key] == wanted[key]
            pairs = [(result[key], wanted[key], dtype) for key, dtype in arrays.items()]
            pairs += [
                (result["mechanism"][key], wanted["mechanism"][key], dtype)
                for key, dtype in placed.items()
            ]
            for got, listed, dtype in pairs:
                assert type(got) is np.ndarray and got.dtype == dtype
                np.testing.assert_array_equal(got, np.array(listed, dtype=dtype), strict=True)
            # Made for the answer: a caller that changes them changes nothing of the index's.
            assert not np.shares_memory(result["mechanism"]["positions"], index.bank.positions)


def test_http_answers_are_byte_for_byte_those_of_lists(index: RetrievalIndex) -> None:
    """`/api/retrieve`'s body (`json_answer`: `rendered_json`, piece by piece when large) and
    `JsonResponse`'s, against compact JSON of the lists answer."""
    for k in (3, 100):  # a small answer, rendered whole; a large one, in pieces
        for query in queries(index):
            body = {"results": index.retrieve(query, k), "took_ms": 1.234}
            lists = {"results": lists_answer(index, query, k), "took_ms": 1.234}
            expected = json.dumps(lists, allow_nan=False, separators=(",", ":")).encode()
            assert asyncio.run(rendered_json(body)) == expected
            assert render_json(body) == expected
            assert JsonResponse(body).body == expected
        if k == 100:
            numbers = sum(len(r["points"]) * 2 for r in lists["results"])
            assert numbers > JSON_PIECE_NUMBERS, "the large answer is rendered whole"


def test_links_retrieve_json_is_byte_for_byte_that_of_lists(
    index: RetrievalIndex, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from links_ray.cli.main import main

    drawing = tmp_path / "drawing.json"
    for query in queries(index)[:3]:
        drawing.write_text(json.dumps(query.tolist()))
        assert main(["retrieve", index.store.uri, "--points", str(drawing), "--json"]) == 0
        printed = capsys.readouterr().out
        took_ms = json.loads(printed)["took_ms"]  # a float: JSON gives it back exactly
        lists = {"results": lists_answer(index, query, 3), "took_ms": took_ms}
        assert printed == json.dumps(lists) + "\n"
