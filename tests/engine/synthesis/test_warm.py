"""Synthesis's kernels load before its clock starts (engine.synthesis.warm): the warming comes
before the budget is made and before the first retrieval, its time is not the budget's, it runs
once a process and kind of synthesis (and of retrieval, an index), it leaves counted work
bit-equal, and after it a synthesis compiles nothing more (in a fresh process: `warm_probe`)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from links_ray.engine.synthesis import pipeline, warm
from links_ray.engine.synthesis.budget import TimeBudget
from links_ray.engine.synthesis.options import SynthesisOptions
from links_ray.engine.synthesis.pipeline import refine_retrieved, synthesize
from links_ray.engine.synthesis.target import as_target
from links_ray.search.index import RetrievalIndex
from tests.support.serving import hand_drawn


class Made(Exception):
    """Raised by a recorded budget: the synthesis need go no further."""


def recorded_budget(order: list[Any]) -> type[TimeBudget]:
    """A TimeBudget that notes (started, seconds) in `order` when made, and raises Made."""

    class Recorded(TimeBudget):
        def __init__(self, started: float, seconds: float, stop: Any = None) -> None:
            order.append(("budget", started, seconds))
            raise Made

    return Recorded


def test_the_kernels_warm_before_the_budget_is_made_and_its_time_is_not_the_budgets(
    dataset_index: RetrievalIndex, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A warming that takes 7 s (as told): the budget, made after it, counts from `started`
    plus those 7 s."""
    order: list[Any] = []

    def warming(target: Any, options: SynthesisOptions, index: Any = None) -> float:
        order.append(("warm", options.partial, index))
        return 7.0

    monkeypatch.setattr(pipeline, "warm_synthesis", warming)
    monkeypatch.setattr(pipeline, "TimeBudget", recorded_budget(order))
    query = hand_drawn()[0]
    retrieved = dataset_index.retrieve(query, 4)
    with pytest.raises(Made):
        refine_retrieved(query, retrieved, SynthesisOptions(seconds=2.0), started=100.0)
    assert order == [("warm", False, None), ("budget", 107.0, 2.0)]


def test_a_synthesis_warms_the_index_and_refinement_before_its_clock(
    dataset_index: RetrievalIndex, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`synthesize` warms, with its index, before it retrieves, and the clock starts after."""
    order: list[Any] = []

    class Watched:
        def retrieve(self, *args: Any) -> list:
            order.append("retrieve")
            return dataset_index.retrieve(*args)

    watched = Watched()

    def warming(target: Any, options: SynthesisOptions, index: Any = None) -> float:
        order.append(("warm", index is watched))
        return 0.0

    monkeypatch.setattr(pipeline, "warm_synthesis", warming)
    monkeypatch.setattr(pipeline, "TimeBudget", recorded_budget(order))
    with pytest.raises(Made):
        synthesize(watched, hand_drawn()[1], k=3, seconds=1.5)
    assert order[0] == ("warm", True) and order[1] == "retrieve"
    assert order[-2] == ("warm", False)  # refine_retrieved's own, which finds it done
    assert order[-1][0] == "budget"


def test_warming_runs_once_a_process_and_kind(monkeypatch: pytest.MonkeyPatch) -> None:
    """Each kind of synthesis (`warm.variant`) warms once; an index is asked one result of
    each kind of retrieval its syntheses make (with and without a floor, with a joint limit),
    once."""
    runs: list[tuple[bool, ...]] = []
    monkeypatch.setattr(warm, "_warmed", set())
    monkeypatch.setattr(warm, "_warm_retrievals_done", {})
    monkeypatch.setattr(warm, "_warm_run", lambda _, options: runs.append(warm.variant(options)))

    class Index:
        def __init__(self) -> None:
            self.asked: list[tuple[int, float, int | None]] = []

        def retrieve(self, points: Any, k: int, floor: float, most: int | None) -> list:
            self.asked.append((k, floor, most))
            return []

    index, other = Index(), Index()
    t = np.linspace(0.0, 2.0 * np.pi, 40, endpoint=False)
    closed = as_target(np.column_stack([np.cos(t), np.sin(t)]), False)
    stroke = as_target(closed.points[:20], True)
    for _ in range(2):
        warm.warm_synthesis(closed, SynthesisOptions(), index)
        warm.warm_synthesis(closed, SynthesisOptions(k=7, seconds=2.0), index)
        warm.warm_synthesis(stroke, SynthesisOptions(partial=True), other)
        warm.warm_synthesis(closed, SynthesisOptions(front=True, iterations=50), index)
        warm.warm_synthesis(closed, SynthesisOptions(front=True))
    assert runs == [
        warm.variant(SynthesisOptions()),
        warm.variant(SynthesisOptions(partial=True)),
        warm.variant(SynthesisOptions(front=True)),
    ]
    assert len(set(runs)) == 3
    floor = SynthesisOptions().min_transmission_deg
    assert index.asked == [(1, floor, None), (1, 0.0, None), (1, floor, 5)]
    assert other.asked == [(1, floor, None), (1, 0.0, None)]


def test_warming_leaves_counted_work_bit_equal(
    dataset_index: RetrievalIndex, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The same counted synthesis, warmed just before (a fresh warming) or long warm."""
    query = hand_drawn()[2]
    once = synthesize(dataset_index, query, k=2, seed=3, iterations=300)
    monkeypatch.setattr(warm, "_warmed", set())
    monkeypatch.setattr(warm, "_warm_retrievals_done", {})
    again = synthesize(dataset_index, query, k=2, seed=3, iterations=300)
    assert again == once and again.iterations == once.iterations


def test_the_warming_synthesis_is_placed_on_the_drawing() -> None:
    """The warming mechanism's path box is centred on the drawing's and as long as its chord,
    in a retrieval result's types."""
    from links_ray.engine.kinematics.solver import simulate

    drawn = hand_drawn()[0]
    target = as_target(drawn, False)
    result = warm.warm_retrieved(target)
    mechanism = result["mechanism"]
    assert mechanism["adjacency"].dtype == np.uint8 and mechanism["node_types"].dtype == np.int8
    assert mechanism["positions"].dtype == np.float64
    path = simulate(mechanism["adjacency"], mechanism["node_types"], mechanism["positions"], 200)[
        result["mechanism_joint"]
    ]
    np.testing.assert_allclose(path, result["points"], atol=1e-9 * target.chord)
    low, high = path.min(axis=0), path.max(axis=0)
    np.testing.assert_allclose((low + high) / 2, (drawn.min(axis=0) + drawn.max(axis=0)) / 2)
    assert np.hypot(*(high - low)) == pytest.approx(target.chord)


def test_after_warming_a_synthesis_compiles_nothing(dataset: str) -> None:
    """In a fresh process, each kind of synthesis warmed, then run for real (counted, over the
    index, and over a few candidates through every pass): no kernel gains a signature. The
    warming itself compiles or loads the kernels (it adds signatures)."""
    root = str(Path(__file__).resolve().parents[3])  # the repository: `tests` importable
    done = subprocess.run(
        [sys.executable, "-m", "tests.engine.synthesis.warm_probe", dataset],
        capture_output=True,
        text=True,
        cwd=root,
        env={**os.environ, "PYTHONPATH": root},
        check=False,
    )
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    assert report["designed"]["warming"], "the first warming loaded no kernel"
    assert {name: kind["after"] for name, kind in report.items()} == {name: {} for name in report}
