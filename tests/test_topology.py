"""The J-operator generator obeys every dataset rule, checked from the graph itself."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest

from links_ray import random_topology
from links_ray.engine.mechanism import FIXED, SIMPLE, analyze_topology, dataset_rule_violations


def depends_on(adjacency: np.ndarray, node_types: np.ndarray, joint: int) -> set[int]:
    """Brute force: every joint whose removal would leave `joint` undetermined.

    Independent of the solution path code: re-solve the mechanism by plain iteration with one
    joint deleted at a time and see whether `joint` still gets two known neighbours.
    """
    n = len(node_types)
    needed = set()
    for removed in range(n):
        if removed == joint:
            continue
        known = {k for k in range(n) if node_types[k] != SIMPLE and k != removed}
        if removed in (0,):  # without joint 0 there is no crank: joint 1 is undetermined
            known.discard(1)
        changed = True
        while changed:
            changed = False
            for k in range(n):
                if k in known or k == removed or node_types[k] != SIMPLE:
                    continue
                if sum(1 for m in np.flatnonzero(adjacency[k]) if m in known) >= 2:
                    known.add(k)
                    changed = True
        if joint not in known:
            needed.add(removed)
    return needed | {joint}


def test_many_topologies_obey_every_rule() -> None:
    rng = np.random.default_rng(2024)
    sizes = Counter()
    fixed_share = []
    for _ in range(400):
        adjacency, node_types = random_topology(rng)
        n = len(node_types)
        sizes[n] += 1
        assert adjacency.shape == (n, n) and adjacency.dtype == np.uint8
        assert np.array_equal(adjacency, adjacency.T) and not np.any(np.diag(adjacency))
        assert node_types[0] == FIXED and node_types[1] == 2
        assert np.count_nonzero(node_types == 2) == 1 and adjacency[0, 1] == 1
        moving = np.count_nonzero(node_types != FIXED)
        links = np.count_nonzero(np.triu(adjacency, 1))
        assert 2 * moving - links == 1, "mobility one with no redundant links"
        topology = analyze_topology(adjacency, node_types)  # dyadic-solvable, or it raises
        last = topology.last_joint
        assert depends_on(adjacency, node_types, last) == set(range(n)), "non-reducible"
        assert not np.any(adjacency[last] & (node_types == FIXED)), "last joint off the ground"
        assert dataset_rule_violations(topology) == []
        fixed_share.append(np.count_nonzero(node_types == FIXED) / n)
    assert set(sizes) == set(range(8, 21)), "8 to 20 joints"
    # Uniform over 13 sizes: each expected about 31 of 400; a 4-sigma band.
    assert all(10 <= count <= 55 for count in sizes.values()), sizes
    # N_g at a third of N_s makes roughly a quarter to a third of the joints fixed.
    assert 0.2 < np.mean(fixed_share) < 0.4


@pytest.mark.parametrize("n", [5, 6, 8, 13, 20, 40])
def test_requested_joint_count(n: int) -> None:
    for seed in range(20):
        adjacency, node_types = random_topology(seed, n_joints=n)
        assert len(node_types) == n
        topology = analyze_topology(adjacency, node_types)
        assert depends_on(adjacency, node_types, topology.last_joint) == set(range(n))


def test_seeded_and_reproducible() -> None:
    first = random_topology(7)
    again = random_topology(7)
    assert all(np.array_equal(a, b) for a, b in zip(first, again, strict=True))
    rng_a, rng_b = np.random.default_rng(3), np.random.default_rng(3)
    seq_a = [random_topology(rng_a) for _ in range(5)]
    seq_b = [random_topology(rng_b) for _ in range(5)]
    for (adj_a, types_a), (adj_b, types_b) in zip(seq_a, seq_b, strict=True):
        assert np.array_equal(adj_a, adj_b) and np.array_equal(types_a, types_b)
    distinct = {random_topology(seed)[0].tobytes() for seed in range(30)}
    assert len(distinct) > 25


@pytest.mark.parametrize("bad", [4, 0, -3, 1001, 2.5, "10", True])
def test_bad_joint_count_is_refused(bad: object) -> None:
    with pytest.raises(ValueError, match="n_joints"):
        random_topology(0, n_joints=bad)
