"""A synthesis's budget (engine.synthesis.budget): the share left, which starts its polish; work
called off (its `stop`), in the budget, a refinement and a synthesis; and the bound on counted work
(`SynthesisOptions.check_work`)."""

from __future__ import annotations

import math
import threading
import time
from typing import Any

import numpy as np
import pytest

from links_ray.engine.inputs import MAX_POINTS
from links_ray.engine.kinematics.mechanism import analyze_topology
from links_ray.engine.synthesis.budget import IterationBudget, TimeBudget
from links_ray.engine.synthesis.options import MAX_SYNTHESIS_WORK, SynthesisOptions
from links_ray.engine.synthesis.pipeline import refine_retrieved
from links_ray.engine.synthesis.plan import pooled, retrievals
from links_ray.engine.synthesis.refinement.loop import Refinement, refine_validated
from links_ray.engine.synthesis.target import as_target
from tests.engine.kinematics.test_solver import fourbar_truth
from tests.engine.synthesis.test_refine import GOOD_FOURBAR, LOW_FOURBAR, fourbar


def test_counted_work_left_is_the_share_of_iterations_not_spent() -> None:
    budget = IterationBudget(200)
    assert budget.left() == 1.0
    budget.charge(None)  # an attempt that did nothing counts one
    assert budget.left() == pytest.approx(199 / 200)
    done = Refinement(None, 0.0, 0.0, None, 149, 0, 90.0)  # type: ignore[arg-type]
    budget.charge(done)
    assert budget.left() == pytest.approx(50 / 200)
    budget.charge(done)
    assert budget.left() == 0.0  # never below


def test_a_time_budget_left_is_the_share_of_its_seconds_to_come() -> None:
    now = time.perf_counter()
    assert TimeBudget(now + 100.0, 10.0).left() == 1.0  # not started: all of it
    assert TimeBudget(now - 7.5, 10.0).left() == pytest.approx(0.25, abs=0.01)
    assert TimeBudget(now - 20.0, 10.0).left() == 0.0


# -- work called off, and the bound on counted work ------------------------------------------


class StopAfter(threading.Event):
    """A stop that reads as set from its `looks`-th look on: called off at a counted point of
    the work, whatever the time."""

    def __init__(self, looks: int) -> None:
        super().__init__()
        self.looks, self.looked = looks, 0
        self._counting = threading.Lock()

    def is_set(self) -> bool:
        """Set once looked at `looks` times (or set)."""
        with self._counting:
            self.looked += 1
            return self.looked > self.looks or super().is_set()


@pytest.mark.parametrize(
    "made",
    [
        lambda stop: IterationBudget(100, stop),
        lambda stop: TimeBudget(time.perf_counter(), 100.0, stop),
    ],
)
def test_a_budget_called_off_is_done_and_expired(made: Any) -> None:
    stop = threading.Event()
    budget = made(stop)
    assert not budget.done(1.0, math.inf) and not budget.expired() and not budget.stopped()
    stop.set()
    assert budget.done(0.0, math.inf) and budget.expired() and budget.stopped()
    assert budget.left() == pytest.approx(1.0, abs=0.01)  # nothing was spent


def test_a_refinement_called_off_ends_at_its_next_iteration() -> None:
    """Refinement looks at its stop before each iteration and each damping trial: set from
    its twelfth look, it does fewer than twelve of the iterations it was given, and keeps
    what it gained, as one cut by its deadline does."""
    adjacency, node_types, start = fourbar(LOW_FOURBAR)
    _, _, goal = fourbar(GOOD_FOURBAR)
    topology = analyze_topology(adjacency, node_types)
    target = as_target(fourbar_truth(goal, 200)[4], False)
    args = (topology, start, 4, target, 200, 40, 3.0)
    whole = refine_validated(*args)
    assert whole.iterations > 5
    stopped = refine_validated(*args, stop=StopAfter(12))
    assert 1 <= stopped.iterations < min(12, whole.iterations)
    assert whole.chamfer_after < stopped.chamfer_after < stopped.chamfer_before


def test_a_synthesis_called_off_answers_with_what_it_has(dataset_index: Any) -> None:
    """Counted work whose stop is set after a few looks: the answer comes with its k results,
    having done a few dozen of the 5,000 iterations asked, and says it was stopped; the same
    work not called off does all of them."""
    drawn = hand_drawn_ellipse()
    options = SynthesisOptions(k=2, seed=0, iterations=5000)
    retrieved = pooled(
        [
            dataset_index.retrieve(drawn, count, floor, most)
            for count, most, floor in retrievals(2, None, False, options.min_transmission_deg)
        ]
    )
    stopped = refine_retrieved(drawn, retrieved, options, stop=StopAfter(40))
    assert stopped.stopped and len(stopped) == 2
    assert stopped.iterations <= 40
    small = SynthesisOptions(k=2, seed=0, iterations=300)
    whole = refine_retrieved(drawn, retrieved, small, stop=threading.Event())
    assert not whole.stopped and whole.iterations >= 300


def hand_drawn_ellipse() -> np.ndarray:
    """An ellipse of 120 points in screen-like coordinates, as a user draws one."""
    t = np.linspace(0, 2 * np.pi, 120)
    return np.column_stack([300 + 120 * np.cos(t), 200 + 50 * np.sin(t)])


#: Points of the drawing at the bound, and the candidates a synthesis of the default k and
#: transmission floor retrieves (synthesis_plan: 96 keeping the floor, 48 whatever it).
BOUND_POINTS, BOUND_CANDIDATES = 1500, 96 + 48


def bound_iterations() -> int:
    """The iterations that bring counted work on BOUND_POINTS to MAX_SYNTHESIS_WORK exactly:
    each candidate counts CANDIDATE_ITERATIONS (10) besides."""
    most, rest = divmod(MAX_SYNTHESIS_WORK, BOUND_POINTS)
    assert rest == 0
    return most - 10 * BOUND_CANDIDATES


def test_counted_work_at_its_bound_is_taken_and_past_it_refused() -> None:
    """points x (iterations + 10 a candidate) at MAX_SYNTHESIS_WORK is taken, one iteration
    more is refused naming the bound and the request's units; timed work has no such units."""
    t = np.linspace(0, 1.5 * np.pi, BOUND_POINTS)
    stroke = np.column_stack([np.cos(t), np.sin(t)])
    at = bound_iterations()
    options = SynthesisOptions(partial=True, iterations=at)
    assert options.counted_work_units(BOUND_POINTS) == MAX_SYNTHESIS_WORK
    assert options.drawing(stroke).shape == (BOUND_POINTS, 2)
    over = SynthesisOptions(partial=True, iterations=at + 1)
    units = BOUND_POINTS * (at + 1 + 10 * BOUND_CANDIDATES)
    with pytest.raises(ValueError) as refused:
        over.drawing(stroke)
    message = str(refused.value)
    assert f"at most {MAX_SYNTHESIS_WORK:,} point-iterations (MAX_SYNTHESIS_WORK)" in message
    assert f"{BOUND_POINTS} points x ({at + 1} iterations + 1440 for the candidates)" in message
    assert f"= {units:,}: give at most {at} iterations for {BOUND_POINTS} points" in message
    assert SynthesisOptions(partial=True, seconds=30).counted_work_units(MAX_POINTS) is None
