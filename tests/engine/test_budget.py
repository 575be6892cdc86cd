"""The share of a synthesis's budget left (engine.budget), which starts its polish."""

from __future__ import annotations

import time

import pytest

from links_ray.engine.budget import IterationBudget, TimeBudget
from links_ray.engine.refine import Refinement


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
