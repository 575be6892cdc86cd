"""reduce_mechanism keeps what a joint needs: re-simulating it traces the same path."""

from __future__ import annotations

import numpy as np
import pytest

import links_ray
from links_ray import InvalidMechanismError, random_topology, reduce_mechanism
from links_ray.engine.kinematics.mechanism import analyze_topology, arc_joints


def test_reduced_mechanism_traces_the_same_path() -> None:
    rng = np.random.default_rng(8)
    for _ in range(12):
        adjacency, node_types = random_topology(rng)
        positions = links_ray.sample_positions(adjacency, node_types, 1, seed=rng)[0]
        full = links_ray.simulate(adjacency, node_types, positions)
        topology = analyze_topology(adjacency, node_types)
        for joint in np.flatnonzero(node_types != 0):
            adj, types, pos, index = reduce_mechanism(adjacency, node_types, positions, joint)
            assert types[0] == 0 and types[1] == 2 and adj[0, 1] == 1, "crank stays joints 0, 1"
            np.testing.assert_array_equal(pos[index], positions[joint])
            reduced = links_ray.simulate(adj, types, pos)
            np.testing.assert_allclose(reduced[index], full[joint], atol=1e-12)
            # Nothing superfluous: the joint's path is the last one the reduced path solves.
            assert analyze_topology(adj, types).last_joint == index or index == 1
            assert len(types) == len(topology.ancestors(int(joint)))
        # The last joint needs every joint (the dataset's non-reducibility rule).
        assert len(reduce_mechanism(adjacency, node_types, positions, topology.last_joint)[1]) == (
            len(node_types)
        )


def test_crank_reduces_to_the_crank() -> None:
    adjacency, node_types = random_topology(2, n_joints=9)
    positions = links_ray.sample_positions(adjacency, node_types, 1, seed=0)[0]
    adj, types, pos, index = reduce_mechanism(adjacency, node_types, positions, 1)
    assert adj.tolist() == [[0, 1], [1, 0]] and types.tolist() == [0, 2] and index == 1
    path = links_ray.simulate(adj, types, pos)[1]
    np.testing.assert_allclose(np.linalg.norm(path - pos[0], axis=1), 0.05)


def test_arc_joints_are_the_moving_joints_on_the_ground() -> None:
    adjacency, node_types = random_topology(4, n_joints=12)
    flags = arc_joints(analyze_topology(adjacency, node_types))
    for joint in range(12):
        on_ground = any(adjacency[joint, k] and node_types[k] == 0 for k in range(12))
        assert flags[joint] == (on_ground and node_types[joint] != 0)
    assert flags[1], "the crank tip turns about joint 0: an arc (a circle, even)"


@pytest.mark.parametrize(
    ("joint", "message"),
    [(0, "fixed"), (99, "does not exist"), (-1, "does not exist"), (1.5, "integer")],
)
def test_bad_joint_is_refused(joint: object, message: str) -> None:
    adjacency, node_types = random_topology(0, n_joints=8)
    positions = links_ray.sample_positions(adjacency, node_types, 1, seed=0)[0]
    with pytest.raises(InvalidMechanismError, match=message):
        reduce_mechanism(adjacency, node_types, positions, joint)
