"""Random topologies from the J-operator (paper: "1-DOF Operator", "Generating Valid Topologies").

The start is the simplest one-degree-of-freedom mechanism: joint 0 fixed, the crank tip joint 1,
and a floating fixed joint 2. Each step applies one of two operators:

- N_s: add a simple joint linked to two existing joints that are not both fixed;
- N_g: add a fixed joint, one third as likely as N_s.

Both keep mobility one (two new links for one new moving joint) and keep every loop dyadic.
The dataset rules also ask that the last joint depends on every joint (non-reducible) and is not
linked to a fixed joint. In a graph grown by N_s every joint except the last must therefore be a
parent of some later joint; the generator tracks the joints nobody depends on yet ("leaves") and
only picks moves after which the remaining steps can still absorb them all.

Pure numpy/numba: no Ray.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from links_ray.engine.inputs import MAX_JOINTS, as_int
from links_ray.engine.mechanism import (
    ACTUATED,
    FIXED,
    MAX_DATASET_JOINTS,
    MIN_DATASET_JOINTS,
    SIMPLE,
    Topology,
    analyze_topology,
    structure_violations,
)

#: The smallest mechanism the rules allow: crank, floating ground, two simple joints.
MIN_TOPOLOGY_JOINTS = 5
#: P(N_g) / P(N_s) = 1/3, as in the paper: N_g is a quarter of all steps.
GROUND_SHARE = 0.25

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
def _grow(uniforms: np.ndarray, adjacency: np.ndarray, node_types: np.ndarray) -> None:
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


def grow_topology(rng: np.random.Generator, n_joints: int) -> Topology:
    """A validated random topology of `n_joints` joints drawn from `rng` (see the module)."""
    adjacency = np.empty((n_joints, n_joints), dtype=np.uint8)
    node_types = np.empty(n_joints, dtype=np.int8)
    _grow(rng.random(2 * (n_joints - 3)), adjacency, node_types)
    topology = analyze_topology(adjacency, node_types)
    problems = structure_violations(topology)
    if problems:  # the construction rules this out; fail loudly rather than emit a bad row
        raise AssertionError(f"generated topology breaks the dataset rules: {problems}")
    return topology


def random_topology(
    seed: SeedLike = None, n_joints: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """A random topology obeying the dataset rules: (adjacency (n, n) uint8, node_types (n,) int8).

    `n_joints` defaults to a uniform draw from 8 to 20. The same `seed` gives the same topology;
    a `numpy.random.Generator` is advanced in place.
    """
    rng = np.random.default_rng(seed)
    if n_joints is None:
        n = int(rng.integers(MIN_DATASET_JOINTS, MAX_DATASET_JOINTS + 1))
    else:
        n = as_int("n_joints", n_joints, MIN_TOPOLOGY_JOINTS, MAX_JOINTS)
    topology = grow_topology(rng, n)
    return topology.adjacency, topology.node_types
