"""Layers for a mechanism built as bars (engine/fabrication/layers.py).

Every plan is checked against the brute force of tests/support/bars.py (exact segment
distances at 20,000 steps): no two links that come within the clearance, or share a joint, on
one layer, and no link within the span of a pin it comes near. Its layer count is checked
against an exhaustive search written here, over every assignment of 1, 2, ... layers, on
mechanisms of up to 8 links and on made-up conflicts of as many; where the planner finds no
plan, the search must find none either. (tests/project/test_layers.py is another matter: the
package's import layering.)
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
import pytest

import links_ray
from links_ray.engine.fabrication.collisions import find_collisions
from links_ray.engine.fabrication.layer_search import _feasible_order, _fewest_layers, _first_plan
from links_ray.engine.fabrication.layers import STATUSES, LayeringError, plan_layers
from links_ray.engine.kinematics.mechanism import LockingError
from links_ray.engine.kinematics.topology import random_topology
from links_ray.engine.node_kinds import FIXED
from tests.support.bars import brute_force, pairs_of
from tests.support.serving import FOUR_BAR, LOCKING_FOUR_BAR

FINE_STEPS = 20_000
#: (bar width, clearance, pin diameter) in the dataset's units, its crank 0.05 long.
SIZES = [(0.02, 0.005, 0.01), (0.06, 0.015, 0.03)]


def random_mechanism(seed: int, joints: int) -> dict[str, Any]:
    adjacency, node_types = random_topology(seed, joints)
    positions = links_ray.sample_positions(adjacency, node_types, count=1, seed=seed)[0]
    return {"adjacency": adjacency, "node_types": node_types, "positions": positions}


# -- the rules, and the exhaustive search -------------------------------------------------------


def spans_of(
    links: np.ndarray, layer: np.ndarray, n: int, posts: np.ndarray
) -> list[tuple[int, int] | None]:
    """Each joint's span: its links' lowest and highest layers, from 0 at a post."""
    spans: list[tuple[int, int] | None] = []
    for joint in range(n):
        own = [int(layer[k]) for k in range(len(links)) if joint in links[k]]
        spans.append((0 if posts[joint] else min(own), max(own)) if own else None)
    return spans


def obeys(
    links: np.ndarray,
    layer: np.ndarray,
    link_conflicts: np.ndarray,
    pin_conflicts: np.ndarray,
    posts: np.ndarray,
) -> bool:
    for first in range(len(links)):
        for second in range(first + 1, len(links)):
            if link_conflicts[first, second] and layer[first] == layer[second]:
                return False
    spans = spans_of(links, layer, pin_conflicts.shape[1], posts)
    for link, joint in np.argwhere(pin_conflicts):
        span = spans[joint]
        if span is not None and span[0] <= layer[link] <= span[1]:
            return False
    return True


def least_layers(
    links: np.ndarray, link_conflicts: np.ndarray, pin_conflicts: np.ndarray, posts: np.ndarray
) -> int | None:
    """The fewest layers of any plan, trying every assignment of 1, 2, ... up to as many
    layers as links (depth first, a link at a time), or None if there is none. A branch is
    cut once a placed link lies within the span of a pin it conflicts with, counting the
    pin's links placed so far: spans only grow as links are placed."""
    count, n = len(links), pin_conflicts.shape[1]
    members = [[k for k in range(count) if joint in links[k]] for joint in range(n)]
    # The pin conflicts placing each link can break: its own, and those of its pins.
    watched: list[list[tuple[int, int]]] = [[] for _ in range(count)]
    for link, joint in np.argwhere(pin_conflicts):
        for k in {int(link), *members[joint]}:
            watched[k].append((int(link), int(joint)))
    layer = [-1] * count

    def broken(i: int) -> bool:
        """Whether placing link i put a link within a span, or link i's pins over one."""
        for link, joint in watched[i]:
            if layer[link] < 0:
                continue
            own = [layer[k] for k in members[joint] if layer[k] >= 0]
            if own and (0 if posts[joint] else min(own)) <= layer[link] <= max(own):
                return True
        return False

    def place(i: int, layers: int) -> bool:
        if i == count:
            return True
        for value in range(layers):
            if any(link_conflicts[i, j] and layer[j] == value for j in range(i)):
                continue
            layer[i] = value
            if not broken(i) and place(i + 1, layers):
                return True
        layer[i] = -1
        return False

    for layers in range(1, count + 1):
        if place(0, layers):
            assert obeys(links, np.array(layer), link_conflicts, pin_conflicts, posts)
            return layers
    return None


def posts_of(node_types: Any, ground_on_base: bool) -> np.ndarray:
    return (np.asarray(node_types) == FIXED) & ground_on_base


# -- plans of mechanisms --------------------------------------------------------------------------


@pytest.fixture(scope="module")
def small_mechanisms() -> list[dict[str, Any]]:
    """Random valid mechanisms of 5 to 7 joints and at most 8 links."""
    found = []
    for seed in range(60):
        mechanism = random_mechanism(seed, 5 + seed % 3)
        if np.triu(mechanism["adjacency"], 1).sum() <= 8:
            found.append(mechanism)
    return found[:30]


def test_plans_use_the_fewest_layers(small_mechanisms: list[dict[str, Any]]) -> None:
    """On up to 8 links, the plan's layers are the fewest an exhaustive search finds over the
    plan's own conflicts; where the planner finds no plan, the search finds none."""
    plans = refused = 0
    for mechanism in small_mechanisms:
        for width, clearance, pin in SIZES:
            for ground_on_base in (False, True):
                sizes = {"bar_width": width, "clearance": clearance, "pin_diameter": pin}
                posts = posts_of(mechanism["node_types"], ground_on_base)
                try:
                    plan = plan_layers(**mechanism, **sizes, ground_on_base=ground_on_base)
                except LayeringError:
                    found = find_collisions(**mechanism, **sizes)
                    conflicts = (found.links, found.link_conflicts, found.pin_conflicts)
                    assert least_layers(*conflicts, posts) is None
                    refused += 1
                    continue
                collisions = plan.collisions
                conflicts = (plan.links, collisions.link_conflicts, collisions.pin_conflicts)
                assert plan.layers == least_layers(*conflicts, posts)
                assert plan.optimal and plan.status == "optimal"
                assert plan.lower_bound == plan.layers
                plans += 1
    print(f"{plans} plans of the fewest layers, {refused} mechanisms with none, confirmed")
    assert plans >= 60 and refused >= 1


@pytest.mark.parametrize("ground_on_base", [False, True])
def test_plans_obey_the_brute_force(ground_on_base: bool) -> None:
    """Random mechanisms of 8 to 11 joints: no two links within the clearance (at 20,000
    steps) or sharing a joint on one layer; no link within the span of a pin it comes near;
    each span its links' lowest and highest layers (from 0 at a post)."""
    checked = 0
    for seed in range(24):
        mechanism = random_mechanism(2000 + seed, 8 + seed % 4)
        width, clearance, pin = SIZES[seed % 2]
        try:
            plan = plan_layers(
                **mechanism,
                bar_width=width,
                clearance=clearance,
                pin_diameter=pin,
                ground_on_base=ground_on_base,
            )
        except LayeringError:
            continue
        n = len(mechanism["positions"])
        posts = posts_of(mechanism["node_types"], ground_on_base)
        links, pairs, which, is_pin = pairs_of(np.asarray(mechanism["adjacency"]))
        assert np.array_equal(plan.links, links)
        least, _ = brute_force(links_ray.simulate(**mechanism, steps=FINE_STEPS), pairs)
        near = least < np.where(is_pin, (width + pin) / 2 + clearance, width + clearance)
        link_conflicts = np.zeros((len(links), len(links)), dtype=bool)
        pin_conflicts = np.zeros((len(links), n), dtype=bool)
        for (first, second), close in zip(which[~is_pin], near[~is_pin], strict=True):
            link_conflicts[first, second] = link_conflicts[second, first] = close
        for (link, joint), close in zip(which[is_pin], near[is_pin], strict=True):
            pin_conflicts[link, joint] = close
        shared = (links[:, None, :, None] == links[None, :, None, :]).any(axis=(2, 3))
        link_conflicts |= shared & ~np.eye(len(links), dtype=bool)
        layer = plan.link_layer
        assert obeys(links, layer, link_conflicts, pin_conflicts, posts)
        spans = spans_of(links, layer, n, posts)
        assert [tuple(span) for span in plan.pin_span] == [
            span if span is not None else (-1, -1) for span in spans
        ]
        assert sorted(set(layer.tolist())) == list(range(plan.layers))
        assert plan.status in STATUSES and plan.lower_bound <= plan.layers
        checked += 1
    print(f"{checked} plans obey the brute force")
    assert checked >= 5


def test_a_plan_cut_at_its_counted_work_is_the_same_every_time(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """With no work left for the solver, a plan above its bound stops at "work limit": the
    first plan, obeying the rules the full plan obeys, the same at every call; with the
    default work, the same mechanisms are planned the same at every call too."""
    import links_ray.engine.fabrication.layers as layers

    cut = 0
    for seed in range(30):
        mechanism = random_mechanism(3000 + seed, 10 + seed % 6)
        width, clearance, pin = SIZES[1]
        sizes = {"bar_width": width, "clearance": clearance, "pin_diameter": pin}
        try:
            whole = [plan_layers(**mechanism, **sizes) for _ in range(2)]
        except LayeringError:
            continue
        assert np.array_equal(whole[0].link_layer, whole[1].link_layer)
        with monkeypatch.context() as patched:
            patched.setattr(layers, "PLAN_WORK", 1e-9)
            short = [plan_layers(**mechanism, **sizes) for _ in range(2)]
        assert np.array_equal(short[0].link_layer, short[1].link_layer)
        assert short[0].layers >= whole[0].layers >= short[0].lower_bound
        if short[0].status == "work limit":
            assert short[0].layers > short[0].lower_bound and not short[0].optimal
            cut += 1
    print(f"{cut} plans cut at no work")
    assert cut >= 1


def test_a_four_bar_takes_two_layers() -> None:
    """The crank and the rocker share no joint and, this thin, never meet: they share a layer
    under (or over) the coupler."""
    plan = plan_layers(**FOUR_BAR, bar_width=0.01, clearance=0.002, pin_diameter=0.005)
    assert plan.layers == 2 and plan.optimal and plan.status == "optimal"
    crank, coupler, rocker = (
        int(np.flatnonzero((plan.links == pair).all(axis=1))[0])
        for pair in ([0, 1], [1, 3], [2, 3])
    )
    assert plan.link_layer[crank] == plan.link_layer[rocker] != plan.link_layer[coupler]


def test_posts_and_a_joint_without_links() -> None:
    """With a base plate, fixed pins span from layer 0; a joint with no links has no pin."""
    adjacency = np.zeros((5, 5), dtype=int)
    for i, j in [(0, 1), (1, 3), (2, 3)]:
        adjacency[i, j] = adjacency[j, i] = 1
    positions = np.vstack([np.asarray(FOUR_BAR["positions"]), [0.9, 0.9]])
    mechanism = {"adjacency": adjacency, "node_types": [0, 2, 0, 1, 0], "positions": positions}
    sizes = {"bar_width": 0.01, "clearance": 0.002, "pin_diameter": 0.005}
    on_base = plan_layers(**mechanism, **sizes, ground_on_base=True)
    assert on_base.pin_span[0, 0] == on_base.pin_span[2, 0] == 0
    assert tuple(on_base.pin_span[4]) == (-1, -1)
    free = plan_layers(**mechanism, **sizes)
    assert tuple(free.pin_span[4]) == (-1, -1) and not free.ground_on_base


def test_no_plan_is_refused_by_name() -> None:
    """Links that sweep over other joints' pins can leave no order of layers."""
    mechanism = random_mechanism(8, 8)
    with pytest.raises(LayeringError, match=r"no layer plan keeps every pin clear.*from pin \d"):
        plan_layers(**mechanism, bar_width=0.01, clearance=0.0025, pin_diameter=0.005)


# -- made-up conflicts ----------------------------------------------------------------------------


def made_up(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(links, link_conflicts, pin_conflicts, posts) of a random graph of up to 8 links,
    random conflicts between links and pins not their own."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(4, 8))
    pairs = np.array([(i, j) for i in range(n) for j in range(i + 1, n)])
    links = pairs[np.sort(rng.choice(len(pairs), size=min(8, len(pairs)), replace=False))]
    shared = (links[:, None, :, None] == links[None, :, None, :]).any(axis=(2, 3))
    link_conflicts = np.triu(rng.random((len(links), len(links))) < 0.3, 1)
    link_conflicts = (link_conflicts | link_conflicts.T | shared) & ~np.eye(len(links), dtype=bool)
    own = (links[:, :, None] == np.arange(n)[None, None, :]).any(axis=1)
    pin_conflicts = (rng.random((len(links), n)) < rng.choice([0.1, 0.25])) & ~own
    posts = rng.random(n) < 0.3 if seed % 2 else np.zeros(n, dtype=bool)
    return links, link_conflicts, pin_conflicts, posts


def test_the_solvers_on_made_up_conflicts() -> None:
    """The greedy plan, when it finds one, obeys the rules; the search for an order agrees
    with the exhaustive one; the program finds a plan on the fewest layers, none on fewer."""
    solved = none = 0
    for seed in range(80):
        links, link_conflicts, pin_conflicts, posts = made_up(seed)
        least = least_layers(links, link_conflicts, pin_conflicts, posts)
        greedy = _first_plan(links, link_conflicts, pin_conflicts, posts, 1)
        if greedy is not None:
            assert obeys(links, greedy, link_conflicts, pin_conflicts, posts)
        order, status = _feasible_order(links, pin_conflicts, posts, 10**6, time.monotonic() + 60)
        assert (order is None) == (least is None) and status in ("feasible", "infeasible")
        if least is None:
            none += 1
            continue
        assert obeys(links, order, link_conflicts, pin_conflicts, posts)
        one_each = np.argsort(np.argsort(order, kind="stable"))  # a link a layer: a start
        plan, bound, status = _fewest_layers(
            links, link_conflicts, pin_conflicts, posts, 1, one_each, 100.0, 60.0
        )
        assert status == "optimal" and bound == least
        assert obeys(links, plan, link_conflicts, pin_conflicts, posts)
        assert len(np.unique(plan)) == plan.max() + 1 == least
        solved += 1
    print(f"{solved} made-up plans of the fewest layers, {none} with none")
    assert solved >= 40 and none >= 5


def test_the_searches_stop_at_their_counted_work() -> None:
    """Given fewer states than it needs, the order search stops with "work limit", and with
    enough, its answer does not depend on the budget; the program, given no work, keeps a
    plan that obeys the rules and says "work limit" where it proved nothing, the same at
    every call. Counted work, so the same on any machine."""
    cut_orders = cut_programs = 0
    for seed in range(80):
        links, link_conflicts, pin_conflicts, posts = made_up(seed)
        whole = _feasible_order(links, pin_conflicts, posts, 10**6, time.monotonic() + 60)
        for states in (1, 2, 4):
            order, status = _feasible_order(links, pin_conflicts, posts, states, math.inf)
            assert status in ("work limit", whole[1])
            if status == "work limit":
                assert order is None
                cut_orders += 1
            else:
                assert np.array_equal(order, whole[0])
        if whole[0] is None:
            continue
        start = np.argsort(np.argsort(whole[0], kind="stable"))
        runs = [
            _fewest_layers(links, link_conflicts, pin_conflicts, posts, 1, start, 1e-9, 60.0)
            for _ in range(2)
        ]
        plan, bound, status = runs[0]
        assert np.array_equal(plan, runs[1][0]) and runs[0][1:] == runs[1][1:]
        assert obeys(links, plan, link_conflicts, pin_conflicts, posts)
        assert status in ("optimal", "work limit") and bound <= plan.max() + 1
        cut_programs += status == "work limit"
    print(f"order searches cut: {cut_orders}; programs cut at no work: {cut_programs}")
    assert cut_orders > 0 and cut_programs > 0


# -- refused input --------------------------------------------------------------------------------

SIZE = {"bar_width": 0.01, "clearance": 0.001, "pin_diameter": 0.004}


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"ground_on_base": "yes"}, "ground_on_base must be true or false"),
        ({"bar_width": -0.01}, "bar_width must be more than 0"),
        ({"clearance": float("nan")}, "clearance must be from 0"),
        ({"pin_diameter": 0.02}, "pin_diameter must be less than bar_width"),
        ({"positions": [[0.0, 0.0]]}, "positions must have shape"),
        ({"steps": 1.5}, "steps must be an integer"),
    ],
)
def test_bad_input_is_refused_by_name(change: dict[str, Any], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        plan_layers(**{**FOUR_BAR, **SIZE, **change})


def test_a_locking_mechanism_is_refused() -> None:
    with pytest.raises(LockingError, match="mechanism locks at step"):
        plan_layers(**LOCKING_FOUR_BAR, **SIZE)
