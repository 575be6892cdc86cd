"""The searches for a layer plan (`engine.fabrication.layers` says what a plan is, and how these
serve it): the rules checked, greedy placements, whether any order keeps the pin rule, and whether
the fewest layers a plan can have, as a constraint program (OR-Tools CP-SAT).

Arrays throughout: `links` (L, 2) joint pairs, `link_conflicts` (L, L) and `pin_conflicts`
(L, n) bool (`collisions.Collisions`), `posts` (n,) bool the joints whose pins stand on the
base plate, a plan (L,) the links' layers.

Numpy and OR-Tools: no numba of its own, no Ray.
"""

from __future__ import annotations

import time

import numpy as np
from ortools.sat.python import cp_model

#: Orders the greedy placement tries, the fewest layers kept; then rounds of it placing the
#: best plan's layers anew, in shuffled order (iterated greedy, as for graph colouring).
GREEDY_ORDERS, GREEDY_ROUNDS = 16, 48


def _pin_spans(links: np.ndarray, layer: np.ndarray, n: int, posts: np.ndarray) -> np.ndarray:
    """(n, 2) each joint's lowest and highest layer of its links; from 0 at `posts` (n,)
    bool; (-1, -1) for a joint without links."""
    spans = np.full((n, 2), -1, dtype=np.int64)
    for joint in range(n):
        at = layer[(links == joint).any(axis=1)]
        if len(at):
            spans[joint] = (0 if posts[joint] else at.min(), at.max())
    return spans


def _broken_rule(
    links: np.ndarray,
    layer: np.ndarray,
    link_conflicts: np.ndarray,
    pin_conflicts: np.ndarray,
    posts: np.ndarray,
) -> str | None:
    """The first rule (`engine.fabrication.layers`) the plan `layer` (L,) breaks, said, else
    None."""
    same = link_conflicts & (layer[:, None] == layer[None, :])
    if same.any():
        first, second = np.argwhere(same)[0]
        return f"links {links[first].tolist()} and {links[second].tolist()} share a layer"
    spans = _pin_spans(links, layer, pin_conflicts.shape[1], posts)
    inside = (spans[None, :, 0] <= layer[:, None]) & (layer[:, None] <= spans[None, :, 1])
    crossing = pin_conflicts & inside
    if crossing.any():
        link, joint = np.argwhere(crossing)[0]
        return f"link {links[link].tolist()} lies within the span of pin {joint}"
    return None


def _first_plan(
    links: np.ndarray,
    link_conflicts: np.ndarray,
    pin_conflicts: np.ndarray,
    posts: np.ndarray,
    least: int,
) -> np.ndarray | None:
    """The greedy plan of fewest layers over `GREEDY_ORDERS` orders (the busiest links
    first, then shuffles), then `GREEDY_ROUNDS` rounds placing the best plan's layers anew,
    a layer's links together, the layers shuffled (kept when no worse); None if no order
    gives a plan. Stops at `least` layers. Seeded alike at every call, so plans repeat."""
    busy = link_conflicts.sum(axis=1) + pin_conflicts.sum(axis=1)
    rng = np.random.default_rng(0)
    best = None
    for attempt in range(GREEDY_ORDERS):
        order = np.argsort(-busy, kind="stable") if attempt == 0 else rng.permutation(len(links))
        plan = _greedy_layers(links, link_conflicts, pin_conflicts, posts, order)
        if plan is not None and (best is None or plan.max() < best.max()):
            best = plan
        if best is not None and best.max() + 1 <= least:
            return best
    for _ in range(GREEDY_ROUNDS if best is not None else 0):
        layers = rng.permutation(int(best.max()) + 1)
        order = np.concatenate([np.flatnonzero(best == k) for k in layers])
        plan = _greedy_layers(links, link_conflicts, pin_conflicts, posts, order)
        if plan is not None and plan.max() <= best.max():
            best = plan
        if best.max() + 1 <= least:
            break
    return best


def _greedy_layers(
    links: np.ndarray,
    link_conflicts: np.ndarray,
    pin_conflicts: np.ndarray,
    posts: np.ndarray,
    order: np.ndarray,
) -> np.ndarray | None:
    """A plan (L,) by the greedy placement (`engine.fabrication.layers`), the links placed in
    `order`, or None if it fails."""
    count = len(links)
    # Positions in the order of layers so far: placed links hold whole numbers, and a new
    # layer inserted below layer g is tried at g - 0.5 (the numbers are made whole after).
    position = np.full(count, np.nan)
    for link in order:
        placed = ~np.isnan(position)
        used = np.unique(position[placed])
        top = len(used)
        candidates = [float(k) for k in range(top)] + [g - 0.5 for g in range(top, -1, -1)]
        for spot in candidates:
            if _fits(link, spot, links, position, placed, link_conflicts, pin_conflicts, posts):
                break
        else:
            return None
        position[link] = spot
        if spot != int(spot):  # a new layer: renumber so the layers are 0, 1, ... again
            position[~np.isnan(position)] = np.unique(
                position[~np.isnan(position)], return_inverse=True
            )[1]
    return position.astype(np.int64)


def _fits(
    link: int,
    spot: float,
    links: np.ndarray,
    position: np.ndarray,
    placed: np.ndarray,
    link_conflicts: np.ndarray,
    pin_conflicts: np.ndarray,
    posts: np.ndarray,
) -> bool:
    """Whether `link` at `spot` keeps the rules among the links `placed` at `position`."""
    if (placed & link_conflicts[link] & (position == spot)).any():
        return False
    # Outside the span, so far, of every pin it comes near: a post's span is from the bottom.
    for joint in np.flatnonzero(pin_conflicts[link]):
        at = position[placed & (links == joint).any(axis=1)]
        if len(at) and (posts[joint] or at.min() <= spot) and spot <= at.max():
            return False
    # Its own pins' spans, grown to take it, must not take in a link that comes near them.
    for joint in links[link]:
        at = position[placed & (links == joint).any(axis=1)]
        low = -np.inf if posts[joint] else min(at.min(initial=spot), spot)
        high = max(at.max(initial=spot), spot)
        near = placed & pin_conflicts[:, joint]
        if (near & (low <= position) & (position <= high)).any():
            return False
    return True


def _merged(
    plan: np.ndarray,
    links: np.ndarray,
    link_conflicts: np.ndarray,
    pin_conflicts: np.ndarray,
    posts: np.ndarray,
) -> np.ndarray:
    """`plan` with neighbouring layers merged, lowest first, wherever the rules still hold."""
    plan = np.unique(plan, return_inverse=True)[1]
    k = 0
    while k < plan.max():
        merged = np.where(plan > k, plan - 1, plan)
        if _broken_rule(links, merged, link_conflicts, pin_conflicts, posts) is None:
            plan = merged
        else:
            k += 1
    return plan


def _feasible_order(
    links: np.ndarray,
    pin_conflicts: np.ndarray,
    posts: np.ndarray,
    states: int,
    deadline: float,
) -> tuple[np.ndarray | None, str]:
    """(a plan (L,) of one layer per link, or None; "feasible", "infeasible", or "work
    limit" after `states` states visited, "time limit" if `deadline` (time.monotonic) passed
    first): whether any plan keeps the pin rule.

    A plan exists if one with no two links on a layer does (a shared layer split in two
    keeps every span's ends on the same sides of every other link), and conflicting links
    differ then anyway. So each link and pin it conflicts with choose: the link above every
    link of the pin, or below every one (above, at a post); the choices must leave "below"
    without a cycle. Searched depth first, each choice's consequences carried through the
    transitive closure (bitsets), a choice left with one way taken at once."""
    count = len(links)
    groups = []
    for m, p in np.argwhere(pin_conflicts):
        own = np.flatnonzero((links == p).any(axis=1))
        groups.append((int(m), sum(1 << int(o) for o in own), bool(posts[p])))
    # below[i] and above[i]: bitsets of the links certainly below and above link i.
    start = ([0] * count, [0] * count, [-1] * len(groups))

    def put_below(first: int, second: int, below: list[int], above: list[int]) -> bool:
        """Put `first` below `second`, closing the relation; False on a cycle."""
        if first == second or (below[first] >> second) & 1:
            return False
        lower = below[first] | (1 << first)
        upper = above[second] | (1 << second)
        for i in _members(upper):
            below[i] |= lower
        for i in _members(lower):
            above[i] |= upper
        return True

    def choose(state: tuple[list[int], list[int], list[int]], g: int, up: bool) -> bool:
        below, above, chosen = state
        m, own, _ = groups[g]
        chosen[g] = up
        return all(
            put_below(o, m, below, above) if up else put_below(m, o, below, above)
            for o in _members(own)
        )

    def settle(state: tuple[list[int], list[int], list[int]]) -> int | None:
        """Take every forced choice; the group to branch on next, -1 if none is left, None
        if a group has no way left."""
        below, above, chosen = state
        while True:
            forced, branch = False, -1
            for g, (m, own, post) in enumerate(groups):
                if chosen[g] != -1:
                    continue
                can_up = not above[m] & own
                can_down = not post and not below[m] & own
                if not (can_up or can_down):
                    return None
                if can_up != can_down:
                    if not choose(state, g, can_up):
                        return None
                    forced = True
                elif branch == -1:
                    branch = g
            if not forced:
                return branch

    stack = [start]
    while stack:
        if states <= 0:
            return None, "work limit"
        if time.monotonic() > deadline:
            return None, "time limit"
        states -= 1
        state = stack.pop()
        branch = settle(state)
        if branch is None:
            continue
        if branch == -1:
            below = state[0]
            # Each link's rank among the others: below[j] grows strictly along the order.
            sizes = np.array([bin(bits).count("1") for bits in below])
            return np.argsort(np.argsort(sizes, kind="stable")), "feasible"
        for up in (False, True):
            child = ([*state[0]], [*state[1]], [*state[2]])
            if choose(child, branch, up):
                stack.append(child)
    return None, "infeasible"


def _members(bits: int) -> list[int]:
    """The members of the bitset `bits`."""
    members = []
    while bits:
        low = bits & -bits
        members.append(low.bit_length() - 1)
        bits ^= low
    return members


def _fewest_layers(
    links: np.ndarray,
    link_conflicts: np.ndarray,
    pin_conflicts: np.ndarray,
    posts: np.ndarray,
    lower: int,
    plan: np.ndarray,
    work: float,
    seconds: float,
) -> tuple[np.ndarray, int, str]:
    """(the plan (L,) of fewest layers found, at most those of `plan`; the fewest any plan
    can have, proven, at least `lower`; "optimal" when the two meet, else "work limit" or
    "time limit"), by a constraint program (OR-Tools CP-SAT) that starts from `plan`: each
    link's layer a variable; the links of a joint, and two conflicting links, on different
    layers; per link m and pin p it conflicts with, a choice: m above every link of p, or
    below every one (at a post, above); the highest layer minimized.

    The solver runs in one thread from a fixed seed, stopped after `work` units of its
    deterministic time (its own count of work done, the same on any machine), so its answer
    is too; `seconds` of wall clock guard it, should that count ever run far slower."""
    count, layers = len(links), int(plan.max()) + 1
    model = cp_model.CpModel()
    layer = [model.new_int_var(0, layers - 1, f"link {link}") for link in range(count)]
    top = model.new_int_var(lower - 1, layers - 1, "top")
    model.add_max_equality(top, layer)
    shared = (links[:, None, :, None] == links[None, :, None, :]).any(axis=(2, 3))
    apart = np.triu((link_conflicts | shared) & ~np.eye(count, dtype=bool), 1)
    for first, second in np.argwhere(apart):
        model.add(layer[first] != layer[second])
    for m, p in np.argwhere(pin_conflicts):
        own = np.flatnonzero((links == p).any(axis=1))
        above = model.new_constant(1) if posts[p] else model.new_bool_var(f"{m} above pin {p}")
        for o in own:
            model.add(layer[m] > layer[o]).only_enforce_if(above)
            if not posts[p]:
                model.add(layer[m] < layer[o]).only_enforce_if(~above)
    if not posts.any():  # a plan upside down is a plan: keep link 0 in the lower half
        model.add(2 * layer[0] <= top)
    for link in range(count):
        model.add_hint(layer[link], int(plan[link]))
    model.minimize(top)
    solver = cp_model.CpSolver()
    solver.parameters.num_workers = 1
    solver.parameters.random_seed = 0
    solver.parameters.max_deterministic_time = work
    solver.parameters.max_time_in_seconds = max(seconds, 0.01)
    answer = solver.solve(model)
    proven = solver.best_objective_bound
    bound = max(lower, round(proven) + 1) if np.isfinite(proven) else lower
    if answer in (cp_model.OPTIMAL, cp_model.FEASIBLE):
        found = np.array([solver.value(v) for v in layer], dtype=np.int64)
        if found.max() < plan.max():
            plan = found
    if answer == cp_model.OPTIMAL or int(plan.max()) + 1 <= bound:
        return plan, int(plan.max()) + 1, "optimal"
    out_of_time = solver.wall_time >= max(seconds, 0.01)
    return plan, bound, "time limit" if out_of_time else "work limit"
