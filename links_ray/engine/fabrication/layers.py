"""Layers for a mechanism built as bars: each link on a layer, each pin through a span of layers,
so that nothing collides over a crank turn, in as few layers as can be.

The rules. A link lies on one layer (an integer from 0 up). A joint's pin runs through the
span [lo, hi] of the layers of its links, lowest to highest. Over the whole turn
(`engine.fabrication.collisions`):

- links that conflict (their bodies come within the clearance, or they share a joint) lie on
  different layers;
- a link that comes within the clearance of a pin, and is not one of that pin's links, lies
  outside the pin's span: below all of the pin's links or above them all.

Pins clear each other too. Two pins whose spans share a layer share one that holds a link of one of
them: the higher of the spans' bottoms (a span's bottom is a layer of its links, but at a post,
below), or for two posts the lower of their tops. That link holds its own pin whole (a pin is
narrower than its bar, `fabrication.limits.as_bar_sizes`), so if the pins came closer than D + C the
link would come within W / 2 + D / 2 + C of the other pin, and the second rule keeps it out of that
pin's span. Pin heads, nuts and washers beyond a span are the builder's business.

With `ground_on_base`, every fixed joint's pin is a post standing on a base plate under layer
0: its span starts at layer 0, whatever the layers of its links, so a link that comes within
the clearance of a fixed pin lies above the post's top (its highest link). The base plate is
not one of the layers. The engine refuses links between two fixed joints, so the frame has
no bars of its own: the plate is the frame. Without it, a fixed pin spans its links' layers
as a moving one does, and how the frame holds it is left to the builder.

Finding a plan (`engine.fabrication.layer_search`). First a greedy one: the links placed one by one,
each on the lowest layer where the rules hold among the links placed so far, else on a new
layer inserted where they hold (the highest such place); inserting a layer keeps the
others' order, so the rules that held still hold. Several orders are tried (the busiest
links first, then seeded shuffles), then the best plan's layers placed anew, a layer's links
together, in shuffled orders (iterated greedy); the fewest layers kept, the search stopped at
the lower bound. It can fail where a plan exists.

Then whether any plan exists is decided on its own: one exists if one with no two links on a
layer does (a shared layer split in two keeps every span's ends on the same sides of every
other link), and conflicting links are apart then anyway; so each link and pin it conflicts
with choose, the link above all of the pin's links or below them all, and the choices must
leave "below" without a cycle: a depth-first search, each choice carried through the
transitive closure. None: `LayeringError`, naming the pins in the way. Else that order, one
layer per link, its neighbouring layers merged where the rules allow, is the first plan.
Random mechanisms of the dataset often have none: their links sweep over each other's joints.

Then the fewest layers, exactly, when the first plan is above the lower bound: a constraint
program (OR-Tools CP-SAT; `layer_search._fewest_layers` states it), started from the first
plan, minimizes the highest layer and proves the fewest. Skipped past `MAX_EXACT_LINKS` links
(the first plan taken). The searches of one plan do counted work, so a plan is the same on
any machine and under any load: the order search visits at most `ORDER_STATES` states, the
solver does at most `PLAN_WORK` of its deterministic time, in one thread. Past them, the best
plan so far is taken, and the bound proven so far reported with it. `PLAN_SECONDS` guards the
wall clock behind them, far above what the counted work takes.

The lower bound starts at the most links at one joint or a greedy clique of conflicting
links, whichever is larger (each needs a layer of its own); the solver may prove it higher.

Numpy and OR-Tools: no numba of its own, no Ray.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from links_ray.engine.fabrication.collisions import Collisions, find_collisions
from links_ray.engine.fabrication.layer_search import (
    _broken_rule,
    _feasible_order,
    _fewest_layers,
    _first_plan,
    _merged,
    _pin_spans,
)
from links_ray.engine.fabrication.limits import DEFAULT_COLLISION_STEPS
from links_ray.engine.inputs import as_flag
from links_ray.engine.kinematics.solver import topology_cache
from links_ray.engine.node_kinds import FIXED

__all__ = [
    "MAX_EXACT_LINKS",
    "ORDER_STATES",
    "PLAN_SECONDS",
    "PLAN_WORK",
    "STATUSES",
    "LayerPlan",
    "LayeringError",
    "plan_layers",
]

#: The most links whose fewest layers are sought exactly; past it, the first plan is taken.
MAX_EXACT_LINKS = 60
#: States the search for an order that keeps the pin rule may visit in one plan.
ORDER_STATES = 20_000
#: Work the constraint solver may do for one plan, in its units of deterministic time.
PLAN_WORK = 2.0
#: Seconds the searches of one plan may take together, a guard should the counted work ever
#: run far longer than it does; then the best plan so far is taken, as past the counted work.
PLAN_SECONDS = 60.0
#: How a plan was found: "optimal", its layers the lower bound (proven fewest); "work limit",
#: the searches spent ORDER_STATES or PLAN_WORK with their plan above the bound proven so
#: far; "time limit", the same at PLAN_SECONDS (the one outcome that depends on the
#: machine); "heuristic", past MAX_EXACT_LINKS, the first plan, above the starting bound.
STATUSES = ("optimal", "work limit", "time limit", "heuristic")


class LayeringError(ValueError):
    """No layer plan keeps every pin clear of the links that pass it (or none was found)."""


@dataclass(frozen=True, eq=False)
class LayerPlan:
    """Each link's layer and each pin's span of layers, for a mechanism built as bars.

    `links` (L, 2) holds each link's joints as `collisions.links` does; `link_layer` (L,)
    their layers, from 0; `pin_span` (n, 2) each joint's lowest and highest layer (from 0
    for a fixed joint with `ground_on_base`; (-1, -1) for a joint without links, which has
    no pin). `layers` is how many layers the plan uses, `lower_bound` the fewest any plan
    could, `optimal` whether the two meet, `status` one of STATUSES. `collisions` holds the
    conflicts the plan obeys and the least distances found.
    """

    links: np.ndarray
    link_layer: np.ndarray
    pin_span: np.ndarray
    layers: int
    lower_bound: int
    optimal: bool
    status: str
    ground_on_base: bool
    collisions: Collisions


def _lower_bound(links: np.ndarray, link_conflicts: np.ndarray) -> int:
    """The fewest layers any plan could use: the most links at one joint, or a clique of
    conflicting links grown greedily from each link, whichever is larger."""
    best = int(np.bincount(links.ravel()).max()) if len(links) else 0
    degree = link_conflicts.sum(axis=1)
    for start in range(len(links)):
        clique = [start]
        candidates = np.flatnonzero(link_conflicts[start])
        for other in candidates[np.argsort(-degree[candidates], kind="stable")]:
            if link_conflicts[other, clique].all():
                clique.append(int(other))
        best = max(best, len(clique))
    return best


def _no_plan(found: Collisions, pin_conflicts: np.ndarray, ground_on_base: bool) -> str:
    """Why no layer plan exists, for LayeringError: the pins in the way, closest first."""
    near = np.argwhere(pin_conflicts)
    closest = near[np.argsort(found.pin_distance[pin_conflicts], kind="stable")][:3]
    named = ", ".join(
        f"link {found.links[link].tolist()} passes {found.pin_distance[link, joint]:.3g} "
        f"from pin {joint}"
        for link, joint in closest
    )
    posts = " (with ground_on_base, fixed pins are posts from layer 0)" if ground_on_base else ""
    return (
        f"no layer plan keeps every pin clear of the links that pass it{posts}: "
        f"{len(near)} link-pin pairs come within {found.pin_threshold:g} of each other "
        f"(closest: {named})"
    )


def plan_layers(
    adjacency: ArrayLike,
    node_types: ArrayLike,
    positions: ArrayLike,
    *,
    bar_width: float,
    clearance: float,
    pin_diameter: float,
    ground_on_base: bool = False,
    steps: int = DEFAULT_COLLISION_STEPS,
) -> LayerPlan:
    """The layers of a mechanism built as bars `bar_width` wide with pins `pin_diameter`
    across, nothing within `clearance` of what it may collide with at any crank angle
    (`collisions.find_collisions`, at `steps` steps and between them), in as few layers as
    can be (the module's docstring); lengths in the unit of `positions`.

    Raises `ValueError` naming the problem: what `find_collisions` refuses (a malformed
    mechanism, sizes or step count, a mechanism that locks), a `ground_on_base` that is not
    true or false, or `LayeringError` when no plan keeps every pin clear (or none was found
    in time).
    """
    ground_on_base = as_flag(ground_on_base, "ground_on_base")
    found = find_collisions(
        adjacency,
        node_types,
        positions,
        bar_width=bar_width,
        clearance=clearance,
        pin_diameter=pin_diameter,
        steps=steps,
    )
    links, link_conflicts, pin_conflicts = found.links, found.link_conflicts, found.pin_conflicts
    topology = topology_cache.simulator(adjacency, node_types).topology  # kept by the check
    posts = (topology.node_types == FIXED) & ground_on_base
    lower = _lower_bound(links, link_conflicts)
    deadline = time.monotonic() + PLAN_SECONDS
    plan = _first_plan(links, link_conflicts, pin_conflicts, posts, lower)
    if plan is None:
        plan, found_one = _feasible_order(links, pin_conflicts, posts, ORDER_STATES, deadline)
        if found_one == "infeasible":
            raise LayeringError(_no_plan(found, pin_conflicts, ground_on_base))
        if plan is None:
            spent = (
                f"{PLAN_SECONDS:g} s" if found_one == "time limit" else f"{ORDER_STATES:,} states"
            )
            raise LayeringError(f"no layer plan found in {spent}, nor shown that none exists")
        plan = _merged(plan, links, link_conflicts, pin_conflicts, posts)
    # Fewer layers, if any, and the fewest proven.
    status = "heuristic"
    if lower < int(plan.max()) + 1 and len(links) <= MAX_EXACT_LINKS:
        plan, lower, status = _fewest_layers(
            links,
            link_conflicts,
            pin_conflicts,
            posts,
            lower,
            plan,
            PLAN_WORK,
            deadline - time.monotonic(),
        )
    # Layers the solver left empty are dropped: the order, and so the rules, stay.
    layer = np.unique(plan, return_inverse=True)[1].astype(np.int64)
    broken = _broken_rule(links, layer, link_conflicts, pin_conflicts, posts)
    if broken is not None:
        raise AssertionError(f"the layer plan breaks its own rules: {broken}")
    layers = int(layer.max()) + 1
    return LayerPlan(
        links=links,
        link_layer=layer,
        pin_span=_pin_spans(links, layer, topology.n_joints, posts),
        layers=layers,
        lower_bound=lower,
        optimal=layers == lower,
        status="optimal" if layers == lower else status,
        ground_on_base=ground_on_base,
        collisions=found,
    )
