"""The J-operator generator obeys every dataset rule, checked from the graph itself."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest

from links_ray import random_topology
from links_ray.engine.kinematics.mechanism import (
    FIXED,
    SIMPLE,
    analyze_topology,
    dataset_rule_violations,
)
from links_ray.engine.kinematics.topology import TOPOLOGY_RULES


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


@pytest.mark.parametrize("rules", TOPOLOGY_RULES)
def test_many_topologies_obey_every_rule(rules: str) -> None:
    rng = np.random.default_rng(2024)
    sizes = Counter()
    fixed_share = []
    for _ in range(400):
        adjacency, node_types = random_topology(rng, rules=rules)
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
    # N_g drawn a quarter of the time (when allowed) makes about a sixth to a third fixed.
    assert 0.15 < np.mean(fixed_share) < 0.4


def moving_joint_shares(rules: str, count: int = 4000) -> tuple[float, float]:
    """Over `count` topologies of 8-20 joints: moving joints per topology, and the share of
    moving joints linked to a fixed joint (the crank tip included)."""
    rng = np.random.default_rng(11)
    moving = grounded = 0
    for _ in range(count):
        adjacency, node_types = random_topology(rng, rules=rules)
        fixed = node_types == FIXED
        moving += np.count_nonzero(~fixed)
        grounded += np.count_nonzero(adjacency[~fixed][:, fixed].any(axis=1))
    return moving / count, grounded / moving


def test_links_rules_match_the_release_generator() -> None:
    """The release's own generator, run on 4,000 topologies of 8-20 joints, gives 11.2 moving
    joints per topology and 45.8% of them on ground; the older rules 10.25 and 62.8%. With
    about 45,000 moving joints the shares' standard error is under 0.3 points."""
    per_topology, on_ground = moving_joint_shares("links")
    assert per_topology == pytest.approx(11.2, abs=0.15) and on_ground == pytest.approx(
        0.458, abs=0.01
    )
    per_topology, on_ground = moving_joint_shares("feasible")
    assert per_topology == pytest.approx(10.25, abs=0.15) and on_ground == pytest.approx(
        0.628, abs=0.01
    )


def test_links_rules_in_the_graph() -> None:
    """Read from the graphs: a simple joint never has two fixed parents; a joint is fixed only
    while the newest fixed joint before it has a dependent and two or more joints follow."""
    rng = np.random.default_rng(5)
    for _ in range(300):
        adjacency, node_types = random_topology(rng, rules="links")
        n = len(node_types)
        newest_fixed = 2
        for joint in range(3, n):
            parents = np.flatnonzero(adjacency[joint, :joint])
            if node_types[joint] == FIXED:
                assert len(parents) == 0 and joint < n - 2
                assert adjacency[newest_fixed, newest_fixed + 1 : joint].any()
                newest_fixed = joint
            else:
                assert len(parents) == 2 and not fixed_pair(node_types, parents)


def fixed_pair(node_types: np.ndarray, parents: np.ndarray) -> bool:
    return bool(np.all(node_types[parents] == FIXED))


@pytest.mark.parametrize("rules", TOPOLOGY_RULES)
@pytest.mark.parametrize("n", [5, 6, 8, 13, 20, 40])
def test_requested_joint_count(n: int, rules: str) -> None:
    for seed in range(20):
        adjacency, node_types = random_topology(seed, n_joints=n, rules=rules)
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


def test_unknown_rules_are_refused() -> None:
    with pytest.raises(ValueError, match="rules must be one of links, feasible"):
        random_topology(0, rules="paper")


@pytest.mark.parametrize("bad", [4, 0, -3, 1001, 2.5, "10", True])
def test_bad_joint_count_is_refused(bad: object) -> None:
    with pytest.raises(ValueError, match="n_joints"):
        random_topology(0, n_joints=bad)
