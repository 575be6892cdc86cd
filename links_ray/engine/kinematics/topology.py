"""Random topologies from the J-operator (paper: "1-DOF Operator", "Generating Valid Topologies").

The start is the simplest one-degree-of-freedom mechanism: joint 0 fixed, the crank tip joint 1,
and a floating fixed joint 2. Each step adds a joint by one of two operators, which both keep
mobility one (two new links for one new moving joint) and every loop dyadic:

- N_s: a simple joint linked to two existing joints that are not both fixed;
- N_g: a fixed joint.

The dataset rules also ask that the last joint depends on every joint (non-reducible) and is not
linked to a fixed joint: every joint but the last must be a parent of a later joint. Two sets of
rules pick the operators and the parents, both tracking the joints nobody depends on yet
("leaves"):

- `links` (the default), the rules of the LINKS release's own generator: a new joint is fixed
  only if the newest fixed joint already has a dependent, a draw of GROUND_SHARE succeeds, it is
  not one of the last two joints, and there are fewer leaves than joints left to add. A simple
  joint is linked to two leaves drawn uniformly when there are at least as many leaves as joints
  left to add; otherwise to a moving joint drawn uniformly and a second joint drawn uniformly
  from the other moving joints and all fixed joints (so never to two fixed joints). The
  second-to-last joint is linked to the newest fixed joint if it is still a leaf, and the last
  joint to two leaves, or to the only leaf (the joint before it) and a moving joint: never to
  ground.
- `feasible`: N_g is drawn with GROUND_SHARE, and a simple joint's parents are drawn uniformly
  among all pairs after which the remaining steps can still absorb every leaf. It links more
  moving joints to ground than `links` does (docs/benchmarks.md has the shares).

Pure numpy/numba: no Ray.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from links_ray.engine.inputs import MAX_JOINTS, as_int
from links_ray.engine.kinematics.mechanism import (
    ACTUATED,
    FIXED,
    MAX_DATASET_JOINTS,
    MIN_DATASET_JOINTS,
    SIMPLE,
    Topology,
    analyze_topology,
    structure_violations,
)
from links_ray.engine.kinematics.solution_path import obeys_structure, solution_order

#: The smallest mechanism the rules allow: crank, floating ground, two simple joints.
MIN_TOPOLOGY_JOINTS = 5
#: The chance that a step may add a fixed joint (N_g), when its rules allow one.
GROUND_SHARE = 0.25
#: The generators' rules (the module says what each does); the first is the default.
TOPOLOGY_RULES = ("links", "feasible")

SeedLike = int | np.random.Generator | None


@njit(cache=True, nogil=True, inline="always")
def _can_finish(leaves: int, fixed_leaves: int, remaining: int) -> bool:
    """Whether `remaining` N_s steps can leave exactly one leaf, a simple joint not on ground.

    A step absorbs at most two leaves, at most one of them fixed, and adds one simple leaf; the
    last step may not touch a fixed joint, so every fixed leaf must go before it.
    """
    if remaining == 0:
        return leaves == 1 and fixed_leaves == 0
    # With no simple leaf to pair it with, the first fixed leaf is absorbed without a gain.
    wasted = 1 if leaves == fixed_leaves and fixed_leaves > 0 else 0
    return fixed_leaves <= remaining - 1 and leaves - 1 <= remaining - wasted


@njit(cache=True, nogil=True)
def _grow_feasible(uniforms: np.ndarray, adjacency: np.ndarray, node_types: np.ndarray) -> None:
    """Apply the operators from the start mechanism until `adjacency` (n, n) is full.

    `uniforms` holds two draws per step: one picks the operator, one picks among the joint
    pairs the step may link (uniformly among those after which the rules can still be met).
    """
    n = node_types.shape[0]
    node_types[:] = SIMPLE
    node_types[0] = node_types[2] = FIXED
    node_types[1] = ACTUATED
    adjacency[:] = 0
    adjacency[0, 1] = adjacency[1, 0] = 1
    is_leaf = np.zeros(n, dtype=np.bool_)
    is_leaf[1] = is_leaf[2] = True
    fixed = node_types == FIXED
    feasible_i = np.empty(n * n, dtype=np.int64)
    feasible_j = np.empty(n * n, dtype=np.int64)
    for size in range(3, n):
        remaining = n - size - 1  # steps after this one
        leaves = fixed_leaves = 0
        for k in range(size):
            leaves += is_leaf[k]
            fixed_leaves += is_leaf[k] and fixed[k]
        draw_operator, draw_pair = uniforms[2 * (size - 3)], uniforms[2 * (size - 3) + 1]
        if draw_operator < GROUND_SHARE and _can_finish(leaves + 1, fixed_leaves + 1, remaining):
            node_types[size] = FIXED
            fixed[size] = is_leaf[size] = True
            continue
        count = 0
        for i in range(size):
            for j in range(i + 1, size):
                if fixed[i] and fixed[j]:
                    continue
                if remaining == 0 and (fixed[i] or fixed[j]):
                    continue
                new_leaves = leaves + 1 - is_leaf[i] - is_leaf[j]
                new_fixed = fixed_leaves - (is_leaf[i] and fixed[i]) - (is_leaf[j] and fixed[j])
                if _can_finish(new_leaves, new_fixed, remaining):
                    feasible_i[count] = i
                    feasible_j[count] = j
                    count += 1
        pick = min(int(draw_pair * count), count - 1)
        a, b = feasible_i[pick], feasible_j[pick]
        adjacency[size, a] = adjacency[a, size] = 1
        adjacency[size, b] = adjacency[b, size] = 1
        is_leaf[a] = is_leaf[b] = False
        is_leaf[size] = True


@njit(cache=True, nogil=True, inline="always")
def _draw(uniform: float, count: int) -> int:
    """An index below `count`, uniformly, from one uniform draw."""
    return min(int(uniform * count), count - 1)


@njit(cache=True, nogil=True)
def _pick(uniform: float, allowed: np.ndarray, size: int, exclude: int) -> int:
    """A joint below `size` drawn uniformly among those `allowed`, `exclude` left out."""
    count = 0
    for k in range(size):
        count += allowed[k] and k != exclude
    chosen = _draw(uniform, count)
    for k in range(size):
        if allowed[k] and k != exclude:
            if chosen == 0:
                return k
            chosen -= 1
    return -1


@njit(cache=True, nogil=True)
def _grow_links(uniforms: np.ndarray, adjacency: np.ndarray, node_types: np.ndarray) -> None:
    """Add joints by the LINKS release's rules (the module) until `adjacency` (n, n) is full.

    `uniforms` holds three draws per step: the operator and the two parents.
    """
    n = node_types.shape[0]
    node_types[:] = SIMPLE
    node_types[0] = node_types[2] = FIXED
    node_types[1] = ACTUATED
    adjacency[:] = 0
    adjacency[0, 1] = adjacency[1, 0] = 1
    is_leaf = np.zeros(n, dtype=np.bool_)
    is_leaf[1] = is_leaf[2] = True
    fixed = node_types == FIXED
    moving = ~fixed
    anything = np.ones(n, dtype=np.bool_)
    newest_fixed = 2
    for size in range(3, n):
        draws = uniforms[3 * (size - 3) : 3 * (size - 2)]
        left = n - size  # joints left to add, this one included
        leaves = 0
        for k in range(size):
            leaves += is_leaf[k]
        if not is_leaf[newest_fixed] and draws[0] < GROUND_SHARE and left > 2 and leaves < left:
            node_types[size] = FIXED
            fixed[size] = is_leaf[size] = True
            moving[size] = False
            newest_fixed = size
            continue
        if left == 2 and is_leaf[newest_fixed]:
            a = newest_fixed
            moving_leaves = is_leaf & moving
            b = _pick(draws[2], moving_leaves if moving_leaves[:size].any() else moving, size, a)
        elif left == 1 and leaves == 1:  # the only leaf is the joint before
            a = size - 1
            b = _pick(draws[2], moving, size, a)
        elif leaves >= left:
            a = _pick(draws[1], is_leaf, size, -1)
            b = _pick(draws[2], is_leaf, size, a)
        else:
            a = _pick(draws[1], moving, size, -1)
            b = _pick(draws[2], anything, size, a)
        adjacency[size, a] = adjacency[a, size] = 1
        adjacency[size, b] = adjacency[b, size] = 1
        is_leaf[a] = is_leaf[b] = False
        is_leaf[size] = True
        moving[size] = True


def grow_topology(rng: np.random.Generator, n_joints: int, rules: str = "links") -> Topology:
    """A validated random topology of `n_joints` joints drawn from `rng` by `rules` (one of
    TOPOLOGY_RULES: see the module)."""
    if rules not in TOPOLOGY_RULES:
        raise ValueError(f"rules must be one of {', '.join(TOPOLOGY_RULES)}, got {rules!r}")
    adjacency = np.empty((n_joints, n_joints), dtype=np.uint8)
    node_types = np.empty(n_joints, dtype=np.int8)
    if rules == "links":
        _grow_links(rng.random(3 * (n_joints - 3)), adjacency, node_types)
    else:
        _grow_feasible(rng.random(2 * (n_joints - 3)), adjacency, node_types)
    # The construction makes a valid topology: the compiled path and checks confirm it, and
    # the Python statements say what went wrong if they ever do not (tests/engine/
    # test_topology.py holds the two equal on every grown topology it draws).
    order = solution_order(adjacency, node_types)
    if order is not None and obeys_structure(adjacency, node_types, order):
        return Topology(adjacency=adjacency, node_types=node_types, order=order)
    problems = structure_violations(analyze_topology(adjacency, node_types))
    raise AssertionError(f"generated topology breaks the dataset rules: {problems}")


def random_topology(
    seed: SeedLike = None, n_joints: int | None = None, rules: str = "links"
) -> tuple[np.ndarray, np.ndarray]:
    """A random topology obeying the dataset rules: (adjacency (n, n) uint8, node_types (n,) int8).

    `n_joints` defaults to a uniform draw from 8 to 20. The same `seed` gives the same topology;
    a `numpy.random.Generator` is advanced in place. `rules` is one of TOPOLOGY_RULES.
    """
    rng = np.random.default_rng(seed)
    if n_joints is None:
        n = int(rng.integers(MIN_DATASET_JOINTS, MAX_DATASET_JOINTS + 1))
    else:
        n = as_int("n_joints", n_joints, MIN_TOPOLOGY_JOINTS, MAX_JOINTS)
    topology = grow_topology(rng, n, rules)
    return topology.adjacency, topology.node_types
