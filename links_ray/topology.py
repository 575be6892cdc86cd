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

Pure numpy: no numba, no Ray.
"""

from __future__ import annotations

import numpy as np

from links_ray.mechanism import (
    ACTUATED,
    FIXED,
    MAX_DATASET_JOINTS,
    MAX_JOINTS,
    MIN_DATASET_JOINTS,
    SIMPLE,
    analyze_topology,
    structure_violations,
)

#: The smallest mechanism the rules allow: crank, floating ground, two simple joints.
MIN_TOPOLOGY_JOINTS = 5
#: P(N_g) / P(N_s), as in the paper.
GROUND_TO_SIMPLE = 1 / 3

SeedLike = int | np.random.Generator | None


def _can_finish(leaves: np.ndarray, fixed_leaves: np.ndarray, remaining: int) -> np.ndarray:
    """Whether `remaining` N_s steps can leave exactly one leaf, a simple joint not on ground.

    A step absorbs at most two leaves, at most one of them fixed, and adds one simple leaf; the
    last step may not touch a fixed joint, so every fixed leaf must go before it. Elementwise.
    """
    leaves, fixed_leaves = np.asarray(leaves), np.asarray(fixed_leaves)
    if remaining == 0:
        return (leaves == 1) & (fixed_leaves == 0)
    # With no simple leaf to pair it with, the first fixed leaf is absorbed without a gain.
    wasted = (leaves == fixed_leaves) & (fixed_leaves > 0)
    return (fixed_leaves <= remaining - 1) & (leaves - 1 <= remaining - wasted)


def _grow(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    adjacency = np.zeros((n, n), dtype=np.uint8)
    node_types = np.full(n, SIMPLE, dtype=np.int8)
    node_types[[0, 2]] = FIXED
    node_types[1] = ACTUATED
    adjacency[0, 1] = adjacency[1, 0] = 1
    is_leaf = np.zeros(n, dtype=bool)
    is_leaf[[1, 2]] = True
    fixed = np.zeros(n, dtype=bool)
    fixed[[0, 2]] = True
    pairs_i, pairs_j = np.triu_indices(n, 1)

    for size in range(3, n):
        remaining = n - size - 1  # steps after this one
        leaves = int(is_leaf[:size].sum())
        fixed_leaves = int((is_leaf & fixed)[:size].sum())
        want_ground = rng.random() < GROUND_TO_SIMPLE / (1 + GROUND_TO_SIMPLE)
        if want_ground and _can_finish(leaves + 1, fixed_leaves + 1, remaining):
            node_types[size] = FIXED
            fixed[size] = is_leaf[size] = True
            continue
        in_range = pairs_j < size
        i, j = pairs_i[in_range], pairs_j[in_range]
        allowed = ~(fixed[i] & fixed[j])
        if remaining == 0:
            allowed &= ~fixed[i] & ~fixed[j]
        new_leaves = leaves + 1 - is_leaf[i].astype(int) - is_leaf[j].astype(int)
        new_fixed_leaves = fixed_leaves - (is_leaf & fixed)[i] - (is_leaf & fixed)[j]
        feasible = allowed & _can_finish(new_leaves, new_fixed_leaves, remaining)
        choice = rng.choice(np.flatnonzero(feasible))
        a, b = int(i[choice]), int(j[choice])
        adjacency[size, [a, b]] = adjacency[[a, b], size] = 1
        is_leaf[[a, b]] = False
        is_leaf[size] = True
    return adjacency, node_types


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
        if isinstance(n_joints, bool) or not isinstance(n_joints, int | np.integer):
            raise ValueError(f"n_joints must be an integer, got {n_joints!r}")
        if not MIN_TOPOLOGY_JOINTS <= n_joints <= MAX_JOINTS:
            raise ValueError(
                f"n_joints must be between {MIN_TOPOLOGY_JOINTS} and {MAX_JOINTS}, got {n_joints}"
            )
        n = int(n_joints)
    adjacency, node_types = _grow(rng, n)
    problems = structure_violations(analyze_topology(adjacency, node_types))
    if problems:  # the construction rules this out; fail loudly rather than emit a bad row
        raise AssertionError(f"generated topology breaks the dataset rules: {problems}")
    return adjacency, node_types
