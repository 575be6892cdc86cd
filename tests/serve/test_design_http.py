"""`POST /api/synthesize` with constraints, timing and a front: the Python API's answer, and
`unmet` when no candidate can keep a constraint. The engine's own tests of constraints are
tests/engine/synthesis/test_design.py."""

from __future__ import annotations

import json
from typing import get_args

from links_ray.engine.synthesis.constraints import CONSTRAINT_NAMES
from links_ray.engine.synthesis.pipeline import synthesize
from links_ray.search.index import RetrievalIndex
from links_ray.serve.http.schemas import Unmet
from tests.engine.synthesis.test_design import misses
from tests.support.serving import Client, hand_drawn


def test_http_synthesize_keeps_constraints_and_says_unmet(
    client: Client, dataset_index: RetrievalIndex
) -> None:
    drawn = hand_drawn()[0]
    low, high = drawn.min(axis=0), drawn.max(axis=0)
    span = float((high - low).max())
    given = {"pivots": [*(low - 0.1 * span), *(high + 0.1 * span)], "max_link_ratio": 6.0}
    body = {"points": drawn.tolist(), "seed": 1, "iterations": 300, "constraints": given}
    status, data = client.post("/api/synthesize", {**body, "front": True, "timing": True})
    assert status == 200, data
    assert data["results"] and "unmet" not in data
    expected = synthesize(
        dataset_index, drawn, seed=1, iterations=300, constraints=given, front=True, timing=True
    )
    assert data["results"] == json.loads(json.dumps(list(expected)))
    for result in data["results"]:
        assert max(misses(result, given).values()) == 0.0
        assert result["timed_error"] > 0
    far = {"pivots": [1e4, 1e4, 1e4 + 1, 1e4 + 1]}
    status, data = client.post("/api/synthesize", {**body, "constraints": far})
    assert status == 200, data
    assert data["results"] == [] and data["unmet"]["constraint"] == "pivots"


def test_unmet_may_name_every_design_constraint_and_the_floor() -> None:
    """The answer's `unmet` names what the engine's violations can name: a design constraint,
    or the transmission floor a start below it has not yet reached."""
    named = get_args(Unmet.model_fields["constraint"].annotation)
    assert named == (*CONSTRAINT_NAMES, "min_transmission")
