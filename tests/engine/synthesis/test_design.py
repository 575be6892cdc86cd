"""Synthesis a designer can build: constraints, prescribed timing, the simplest first.

Against independent truth:
* how far a mechanism misses its constraints, measured by brute force over its joints, its
  links and a 2,000-step turn (`violation`);
* every result of a constrained synthesis keeps every constraint, checked the same way, and
  a request no candidate can meet answers `unmet`, not an error;
* refinement moves a start that misses a pivot region into it, and never out again;
* a four-bar's coupler curve sampled at known crank angles (in closed form, not by the
  solver) is recovered with a timed error under 1e-4, from a perturbed start in another
  phase, with equal steps or explicit angles of a stroke;
* a front's joint counts rise as its chamfers fall, and `max_joints` bounds every result.

Tests of quality run a counted amount of work (`seed` and `iterations`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

import links_ray
from links_ray.engine.inputs import link_pairs
from links_ray.engine.kinematics.mechanism import analyze_topology
from links_ray.engine.synthesis.constraints import Constraints, as_constraints, violation
from links_ray.engine.synthesis.limits import REFINE_CHECK_STEPS
from links_ray.engine.synthesis.options import SynthesisOptions, as_timing
from links_ray.engine.synthesis.pipeline import refine_retrieved, synthesize
from links_ray.engine.synthesis.refinement.checks import check_mechanism
from links_ray.engine.synthesis.refinement.loop import refine_validated
from links_ray.engine.synthesis.target import as_target
from links_ray.search.index import RetrievalIndex
from tests.support.serving import hand_drawn

ITERATIONS = 600


# -- independent truth ------------------------------------------------------------------------


def misses(result: dict, constraints: dict) -> dict[str, float]:
    """How far a result's mechanism misses each constraint, by brute force over its joints,
    its links and a 2,000-step turn (0 where kept)."""
    mechanism = result["mechanism"]
    adjacency = np.array(mechanism["adjacency"])
    node_types = np.array(mechanism["node_types"])
    positions = np.array(mechanism["positions"])
    turn = links_ray.simulate(adjacency, node_types, positions, REFINE_CHECK_STEPS)
    lengths = [
        float(np.hypot(*(positions[i] - positions[j])))
        for i in range(len(positions))
        for j in range(i + 1, len(positions))
        if adjacency[i, j]
    ]
    out = {}
    for name, value in constraints.items():
        if name in ("pivots", "footprint"):
            xmin, ymin, xmax, ymax = value
            points = positions[node_types == 0] if name == "pivots" else turn.reshape(-1, 2)
            worst = 0.0
            for x, y in points:
                worst = max(worst, xmin - x, x - xmax, ymin - y, y - ymax)
            out[name] = worst
        elif name == "min_link":
            out[name] = max(0.0, value - min(lengths))
        elif name == "max_link":
            out[name] = max(0.0, max(lengths) - value)
        else:
            out[name] = max(0.0, max(lengths) / min(lengths) - value)
    return out


def coupler_four_bar(
    crank: float, rocker: float, coupler: float, ground: float, offset: tuple[float, float]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A four-bar in the dataset's form with a coupler point: joint 0 the crank's centre at
    the origin, 1 its tip (at angle 0.3), 2 the rocker's pivot (ground, 0), 3 the rocker's
    tip, 4 the coupler point at `offset` in the frame of the link 1 -> 3."""
    adjacency = np.zeros((5, 5), dtype=int)
    for i, j in ((0, 1), (1, 3), (2, 3), (1, 4), (3, 4)):
        adjacency[i, j] = adjacency[j, i] = 1
    node_types = np.array([0, 2, 0, 1, 1])
    tip = crank * np.array([np.cos(0.3), np.sin(0.3)])
    pivot = np.array([ground, 0.0])
    rocker_tip = circles_meet(tip, coupler, pivot, rocker, 1.0)
    along = (rocker_tip - tip) / coupler
    point = tip + offset[0] * along + offset[1] * np.array([-along[1], along[0]])
    return adjacency, node_types, np.array([[0.0, 0.0], tip, pivot, rocker_tip, point])


def circles_meet(a: np.ndarray, ra: float, b: np.ndarray, rb: float, side: float) -> np.ndarray:
    """Where the circles about a (radius ra) and b (radius rb) meet, on `side` (+1 left of
    a -> b, -1 right)."""
    gap = b - a
    d = float(np.hypot(*gap))
    along = (d * d + ra * ra - rb * rb) / (2 * d)
    height = np.sqrt(ra * ra - along * along)
    return a + along * gap / d + side * height * np.array([-gap[1], gap[0]]) / d


def coupler_at(positions: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """The coupler point of `coupler_four_bar`'s form at crank angles `angles` (radians from
    the crank's initial angle), in closed form: (len(angles), 2)."""
    centre, tip0, pivot, rocker0, point0 = positions
    crank = np.hypot(*(tip0 - centre))
    start = np.arctan2(*(tip0 - centre)[::-1])
    coupler, rocker = np.hypot(*(rocker0 - tip0)), np.hypot(*(rocker0 - pivot))
    gap, bar = pivot - tip0, rocker0 - tip0
    side = np.sign(gap[0] * bar[1] - gap[1] * bar[0])
    # The coupler point in the frame of the bar tip -> rocker tip.
    unit = bar / coupler
    normal = np.array([-unit[1], unit[0]])
    local = np.array([(point0 - tip0) @ unit, (point0 - tip0) @ normal])
    out = []
    for angle in angles:
        tip = centre + crank * np.array([np.cos(start + angle), np.sin(start + angle)])
        rocker_tip = circles_meet(tip, coupler, pivot, rocker, side)
        u = (rocker_tip - tip) / coupler
        out.append(tip + local[0] * u + local[1] * np.array([-u[1], u[0]]))
    return np.array(out)


def retrieved(adjacency: np.ndarray, node_types: np.ndarray, positions: np.ndarray) -> dict:
    """A mechanism as a retrieval result placed in the drawing's frame."""
    return {
        "path_id": 4,
        "mechanism_id": 0,
        "chamfer": 0.0,
        "mechanism": {
            "adjacency": adjacency.tolist(),
            "node_types": node_types.tolist(),
            "positions": positions.tolist(),
        },
        "mechanism_joint": 4,
    }


FOUR_BAR = coupler_four_bar(1.0, 2.5, 3.0, 3.2, (1.2, 0.8))


# -- measuring constraints --------------------------------------------------------------------


def test_violation_is_the_brute_force_miss() -> None:
    adjacency, node_types, positions = FOUR_BAR
    topology = analyze_topology(adjacency, node_types)
    check = check_mechanism(topology, positions)
    result = retrieved(adjacency, node_types, positions)
    for given in (
        {"pivots": [0.5, -1.0, 4.0, 1.0]},  # joint 0 is 0.5 left of it
        {"footprint": [-1.0, -1.0, 3.5, 3.0]},
        {"max_link_ratio": 2.0},
        {"min_link": 1.5},
        {"max_link": 2.0},
        {"pivots": [-1.0, -1.0, 4.0, 1.0], "max_link": 10.0},  # both kept
    ):
        truth = misses(result, given)
        measured = violation(
            as_constraints(given),
            positions,
            topology.fixed_joints,
            link_pairs(topology.adjacency),
            check.bounds,
            chord=2.0,
        )
        worst = max(truth.values())
        assert measured.kept == (worst == 0.0), given
        if worst > 0:
            assert measured.by == pytest.approx(worst, rel=1e-12), given
            assert measured.name == max(truth, key=truth.get), given


def test_constraints_are_checked_by_name() -> None:
    for bad, words in (
        ({"pivot": [0, 0, 1, 1]}, "unknown constraint 'pivot'"),
        ({"pivots": [0, 0, 1]}, "pivots must be four numbers"),
        ({"footprint": [0, 0, 1, float("nan")]}, "footprint must be finite"),
        ({"max_link_ratio": 0.5}, "max_link_ratio must be at least 1"),
        ({"min_link": -1}, "min_link must be more than 0"),
        ({"min_link": 3, "max_link": 2}, "min_link (3) must not exceed max_link (2)"),
        ([0, 0, 1, 1], "constraints must be an object"),
    ):
        with pytest.raises(ValueError, match=words.replace("(", r"\(").replace(")", r"\)")):
            as_constraints(bad)
    assert as_constraints({}) is None and as_constraints(None) is None
    assert as_constraints({"max_link": 2}) == Constraints(max_link=2.0)
    with pytest.raises(ValueError, match="one angle per point: 3, got 2"):
        as_timing([0, 1], 3, False)
    with pytest.raises(ValueError, match="timing=true spreads the points over a whole turn"):
        as_timing(True, 3, True)


# -- refinement keeps them ----------------------------------------------------------------------


def test_refinement_moves_a_start_into_a_pivot_region_and_keeps_it_there() -> None:
    adjacency, node_types, positions = FOUR_BAR
    topology = analyze_topology(adjacency, node_types)
    drawn = coupler_at(positions, np.linspace(0, 2 * np.pi, 80, endpoint=False))
    target = as_target(drawn, False)
    # The crank's centre is at x = 0: the region wants it at least 0.4 to the right.
    given = {"pivots": [0.4, -1.0, 4.0, 1.0], "max_link_ratio": 3.0}
    constraints = as_constraints(given)
    before = misses(retrieved(adjacency, node_types, positions), given)
    assert before["pivots"] == pytest.approx(0.4)
    refinement = refine_validated(
        topology, positions, 4, target, 200, 200, 3.0, constraints=constraints
    )
    assert refinement.violation.kept
    after = retrieved(adjacency, node_types, refinement.positions)
    assert max(misses(after, given).values()) == 0.0
    # It still traces the curve it was given: moving a pivot 0.4 costs some of the fit.
    assert refinement.chamfer_after < 0.05
    # Refined on from there, every kept step keeps them.
    again = refine_validated(
        topology, refinement.positions, 4, target, 200, 100, 3.0, constraints=constraints
    )
    assert again.chamfer_after <= refinement.chamfer_after
    assert max(misses(retrieved(adjacency, node_types, again.positions), given).values()) == 0.0


# -- synthesis keeps them -----------------------------------------------------------------------


def test_constrained_synthesis_keeps_every_constraint(dataset_index: RetrievalIndex) -> None:
    drawn = hand_drawn()[0]
    free = synthesize(dataset_index, drawn, k=3, seed=0, iterations=ITERATIONS)
    low, high = drawn.min(axis=0), drawn.max(axis=0)
    span = float((high - low).max())
    given = {
        "pivots": [*(low - 0.1 * span), *(high + 0.1 * span)],
        "footprint": [*(low - 0.8 * span), *(high + 0.8 * span)],
        "max_link_ratio": 6.0,
    }
    # The answer without them misses them: keeping them is work.
    assert max(misses(free[0], given).values()) > 0
    results = synthesize(
        dataset_index, drawn, k=3, seed=0, iterations=ITERATIONS, constraints=given
    )
    assert results.unmet is None and len(results) >= 1
    for result in results:
        assert max(misses(result, given).values()) == 0.0, misses(result, given)
    # Still a trace of the drawing, if a poorer one: these pivots cost the fit.
    assert results[0]["chamfer"] < 0.1
    chamfers = [r["chamfer"] for r in results]
    assert chamfers == sorted(chamfers)


def test_constraints_no_candidate_can_keep_are_unmet(dataset_index: RetrievalIndex) -> None:
    drawn = hand_drawn()[0]
    far = [1e4, 1e4, 1e4 + 1, 1e4 + 1]
    results = synthesize(dataset_index, drawn, seed=0, iterations=100, constraints={"pivots": far})
    assert list(results) == []
    assert results.unmet["constraint"] == "pivots" and results.unmet["by"] > 1e3


# -- timing -------------------------------------------------------------------------------------


@pytest.mark.parametrize("stroke", [False, True], ids=["equal steps", "angles of a stroke"])
def test_timing_recovers_a_closed_form_four_bar(stroke: bool) -> None:
    adjacency, node_types, positions = FOUR_BAR
    if stroke:  # 40 points over 200 degrees, unevenly, from 110 degrees into the turn
        degrees = 200.0 * np.linspace(0.0, 1.0, 40) ** 1.3
        angles = np.radians(110.0 + degrees)
        timing: Any = degrees.tolist()
    else:
        angles = 2.0 + 2 * np.pi * np.arange(60) / 60
        timing = True
    drawn = coupler_at(positions, angles)
    scale = float(np.ptp(drawn, axis=0).max())
    rng = np.random.default_rng(3)
    start = positions + rng.normal(0.0, 0.01 * scale, positions.shape)
    answer = refine_retrieved(
        drawn,
        [retrieved(adjacency, node_types, start)],
        SynthesisOptions(k=1, partial=stroke, timing=timing, seed=0, iterations=800),
    )
    (result,) = answer
    assert result["timed_error"] < 1e-4
    # The same, measured in closed form from the answer's own start.
    found = np.array(result["mechanism"]["positions"])
    relative = angles - angles[0]
    error = np.hypot(*(coupler_at(found, relative) - drawn).T).mean()
    chord = max(np.hypot(*(p - q)) for p in drawn for q in drawn)
    assert error / chord == pytest.approx(result["timed_error"], rel=1e-6, abs=1e-12)
    # The untimed start is far off in timing: the timing was the work.
    untimed = np.hypot(*(coupler_at(start, relative) - drawn).T).mean() / chord
    assert untimed > 100 * result["timed_error"]


# -- the simplest first -------------------------------------------------------------------------


def test_a_front_rises_in_joints_as_it_falls_in_chamfer(dataset_index: RetrievalIndex) -> None:
    drawn = hand_drawn()[1]
    front = synthesize(dataset_index, drawn, seed=0, iterations=ITERATIONS, front=True)
    assert len(front) >= 2
    joints = [r["n_joints"] for r in front]
    chamfers = [r["chamfer"] for r in front]
    assert joints == sorted(set(joints))
    assert chamfers == sorted(chamfers, reverse=True) and len(set(chamfers)) == len(chamfers)
    for result in front:
        assert result["n_joints"] == len(result["mechanism"]["node_types"])
        assert result["n_links"] == int(np.triu(np.array(result["mechanism"]["adjacency"])).sum())
    # The k best are no better than the front's best.
    best = synthesize(dataset_index, drawn, k=1, seed=0, iterations=ITERATIONS)
    assert front[-1]["chamfer"] <= best[0]["chamfer"] * 1.5
    simple = synthesize(dataset_index, drawn, k=3, seed=0, iterations=300, max_joints=joints[0])
    assert simple and all(r["n_joints"] <= joints[0] for r in simple)
