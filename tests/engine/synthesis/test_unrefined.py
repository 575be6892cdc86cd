"""A synthesis result says whether refinement moved it (`refined`) and, if not, `why`: counted
work refines its answers; a time budget spent before the first iteration, or work called off
first, answers them as retrieved and says so; the HTTP schema documents the fields and takes
the answers; the CLI's table shows them. No Ray, no timing."""

from __future__ import annotations

import threading
import time
import typing
from typing import Any

import numpy as np
import pytest

from links_ray.cli.report import format_synthesize
from links_ray.engine.kinematics.mechanism import analyze_topology
from links_ray.engine.synthesis.candidates import UNREFINED, Candidate
from links_ray.engine.synthesis.options import DEFAULT_SYNTHESIS_TRANSMISSION_DEG, SynthesisOptions
from links_ray.engine.synthesis.pipeline import refine_retrieved, synthesize
from links_ray.engine.synthesis.target import as_target
from links_ray.engine.synthesis.warm import warm_synthesis
from links_ray.search.index import RetrievalIndex
from links_ray.serve.http.schemas import SynthesisResult
from tests.support.serving import hand_drawn


def retrieved_for(index: RetrievalIndex, query: np.ndarray) -> list:
    """What synthesis retrieves first: paths that keep its floor."""
    return index.retrieve(query, 96, DEFAULT_SYNTHESIS_TRANSMISSION_DEG)


def assert_consistent(results: list[dict]) -> None:
    """`refined` and `why` agree, and an unrefined result is its retrieved mechanism."""
    for result in results:
        assert isinstance(result["refined"], bool)
        assert (result["why"] is None) == result["refined"]
        if not result["refined"]:
            assert result["why"] in UNREFINED
            assert result["chamfer"] == pytest.approx(result["retrieved_chamfer"], abs=5e-7)
        SynthesisResult.model_validate(result)  # as the HTTP answer documents it


def test_counted_work_says_its_answers_are_refined(dataset_index: RetrievalIndex) -> None:
    """Counted work refines (the best beats its start); a result it kept no step of says
    no_step, never no_time."""
    results = synthesize(dataset_index, hand_drawn()[0], k=3, seed=0, iterations=400)
    assert results.iterations > 0 and len(results) == 3
    assert_consistent(results)
    assert results[0]["refined"] and results[0]["chamfer"] < results[0]["retrieved_chamfer"]
    assert {r["why"] for r in results if not r["refined"]} <= {"no_step"}


def test_a_budget_spent_before_the_first_iteration_says_no_time(
    dataset_index: RetrievalIndex,
) -> None:
    """Kernels warm, a budget of a millisecond that ended a second ago: every result is as
    retrieved, and says the time was spent before its first iteration."""
    query = hand_drawn()[1]
    options = SynthesisOptions(k=3, seconds=0.001)
    warm_synthesis(as_target(query, False), options)
    retrieved = retrieved_for(dataset_index, query)
    results = refine_retrieved(query, retrieved, options, started=time.perf_counter() - 1.0)
    assert results.iterations == 0 and len(results) >= 2
    assert_consistent(results)
    assert [r["why"] for r in results] == ["no_time"] * len(results)


def test_work_called_off_first_says_stopped(dataset_index: RetrievalIndex) -> None:
    """Counted work whose stop is set before it begins: nothing refined, each says stopped."""
    query = hand_drawn()[1]
    stop = threading.Event()
    stop.set()
    options = SynthesisOptions(k=2, iterations=500)
    results = refine_retrieved(query, retrieved_for(dataset_index, query), options, stop=stop)
    assert results.stopped and results.iterations == 0 and len(results) == 2
    assert_consistent(results)
    assert [r["why"] for r in results] == ["stopped", "stopped"]


def candidate_of(**done: Any) -> Candidate:
    """A four-bar candidate with what refinement did to it (`Candidate` fields)."""
    adjacency = np.array([[0, 1, 0, 0], [1, 0, 0, 1], [0, 0, 0, 1], [0, 1, 1, 0]])
    topology = analyze_topology(adjacency, np.array([0, 2, 0, 1]))
    positions = np.array([[0.5, 0.5], [0.55, 0.5], [0.8, 0.5], [0.6, 0.7]])
    c = Candidate({}, topology, 3, positions, positions, 0.1, 0.1, None)  # type: ignore[arg-type]
    for name, value in done.items():
        setattr(c, name, value)
    return c


@pytest.mark.parametrize(
    ("done", "stopped", "why"),
    [
        ({"moved": True, "iterations": 4}, False, None),
        ({"moved": True}, True, None),  # a coupler-point child of a refined parent
        ({"iterations": 3}, False, "no_step"),
        ({"iterations": 3, "refused": True}, True, "no_step"),
        ({"refused": True}, False, "cannot_refine"),
        ({}, True, "stopped"),
        ({}, False, "no_time"),
    ],
)
def test_why_a_candidate_is_unrefined(done: dict, stopped: bool, why: str | None) -> None:
    assert candidate_of(**done).why_unrefined(stopped) == why


def test_the_http_schema_documents_the_fields() -> None:
    """`refined` is required, `why` is one of UNREFINED or null, both described."""
    schema = SynthesisResult.model_json_schema()
    assert "refined" in schema["required"]
    why = SynthesisResult.model_fields["why"].annotation
    assert set(typing.get_args(typing.get_args(why)[0])) == set(UNREFINED)
    for field in ("refined", "why"):
        assert schema["properties"][field]["description"]


def test_the_cli_table_says_which_are_unrefined_and_why() -> None:
    """A column `refined`, and a footnote for each reason given."""
    base = {
        "chamfer": 0.1274,
        "retrieved_chamfer": 0.1274,
        "mechanism": {"node_types": [0, 2, 0, 1]},
        "mechanism_joint": 3,
        "path_id": 7,
        "interval": None,
    }
    answer = {
        "results": [
            {**base, "chamfer": 0.05, "refined": True, "why": None},
            {**base, "refined": False, "why": "no_time"},
        ],
        "took_ms": 3000.0,
    }
    lines = format_synthesize(answer).splitlines()
    assert len(lines) == 5 and "refined" in lines[1].split()
    assert " yes " in lines[2] and "no (no time)" in lines[3]
    assert lines[4] == (
        "(no time: the budget was spent before its first iteration; --json for the mechanisms)"
    )
    answer["results"] = answer["results"][:1]
    assert format_synthesize(answer).splitlines()[-1] == "(--json for the mechanisms)"
