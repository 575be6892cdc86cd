"""Synthesis's layers (engine.synthesis.kit_layers), against `plan_layers` called directly, in the
drawing's own units at the sizes the module states relative to each result's crank:

* every result of a synthesis given `max_layers` keeps it, and carries its count;
* `max_layers` no candidate can keep (1: a crank's joint holds two links) answers `unmet`;
* a front's results carry their layer counts; a plain synthesis's carry none;
* bad values of `max_layers` are a ValueError naming it (HTTP's: tests/serve).

Counted work (`seed`, `iterations`), over the engine tests' small dataset.
"""

from __future__ import annotations

import numpy as np
import pytest

from links_ray.engine.fabrication.layers import LayeringError, plan_layers
from links_ray.engine.synthesis.kit_layers import NO_PLAN_MISS
from links_ray.engine.synthesis.pipeline import synthesize
from links_ray.search.index import RetrievalIndex
from tests.support.serving import hand_drawn

ITERATIONS = 300


def layers_of(result: dict) -> int | None:
    """The result's layers as the module states them: bars 0.4, clearance 0.05 and pins 0.3
    of its own crank, in the drawing's units (None: no plan)."""
    mechanism = result["mechanism"]
    positions = np.array(mechanism["positions"])
    crank = float(np.hypot(*(positions[1] - positions[0])))
    try:
        plan = plan_layers(
            mechanism["adjacency"],
            mechanism["node_types"],
            positions,
            bar_width=0.4 * crank,
            clearance=0.05 * crank,
            pin_diameter=0.3 * crank,
        )
    except LayeringError:
        return None
    return plan.layers


def test_every_result_keeps_max_layers(dataset_index: RetrievalIndex) -> None:
    drawn = hand_drawn()[0]
    free = synthesize(dataset_index, drawn, k=3, seed=0, iterations=ITERATIONS, front=True)
    counts = [r["layers"] for r in free if r["layers"] is not None]
    most = min(counts)  # the fewest any answer of the front takes: keeping it is possible
    results = synthesize(
        dataset_index,
        drawn,
        k=2,
        seed=0,
        iterations=ITERATIONS,
        constraints={"max_layers": most},
    )
    assert results.unmet is None and len(results) >= 1
    for result in results:
        assert result["layers"] == layers_of(result)
        assert result["layers"] <= most


def test_max_layers_no_candidate_keeps_is_unmet(dataset_index: RetrievalIndex) -> None:
    drawn = hand_drawn()[0]
    results = synthesize(
        dataset_index, drawn, seed=0, iterations=100, constraints={"max_layers": 1}
    )
    assert list(results) == []
    assert results.unmet["constraint"] == "max_layers"
    assert 1 <= results.unmet["by"] <= NO_PLAN_MISS


def test_a_fronts_results_carry_their_layers(dataset_index: RetrievalIndex) -> None:
    drawn = hand_drawn()[1]
    front = synthesize(dataset_index, drawn, seed=0, iterations=ITERATIONS, front=True)
    assert len(front) >= 2
    for result in front:
        assert result["layers"] == layers_of(result)
    # Counted work: bit-equal again, layers included.
    assert synthesize(dataset_index, drawn, seed=0, iterations=ITERATIONS, front=True) == front
    plain = synthesize(dataset_index, drawn, k=2, seed=0, iterations=100)
    assert all("layers" not in result for result in plain)


@pytest.mark.parametrize(
    ("value", "words"),
    [
        (0, "max_layers must be from 1 to 40, got 0"),
        (-1, "max_layers must be from 1 to 40, got -1"),
        ("x", "max_layers must be an integer from 1 to 40, got 'x'"),
        (1e9, "max_layers must be an integer from 1 to 40"),
        (10**9, "max_layers must be from 1 to 40"),
        (True, "max_layers must be an integer"),
    ],
)
def test_bad_max_layers_is_refused(
    dataset_index: RetrievalIndex, value: object, words: str
) -> None:
    with pytest.raises(ValueError, match=words.replace("(", r"\(")):
        synthesize(dataset_index, hand_drawn()[0], constraints={"max_layers": value})
