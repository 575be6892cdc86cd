"""Position samplers: every variant valid (re-simulated by the plain-Python solver), rules kept,
negatives really lock, seeds reproduce."""

from __future__ import annotations

import numpy as np
import pytest

import links_ray
from links_ray import LockingError, PositionSampler, TopologySimulator, random_topology
from links_ray.engine.kinematics.mechanism import dataset_rule_violations
from links_ray.engine.kinematics.reference import simulate_reference

SAMPLERS = ["sequential", "rejection"]


@pytest.mark.parametrize("sampler", SAMPLERS)
def test_variants_are_valid_distinct_and_obey_the_rules(sampler: str) -> None:
    rng = np.random.default_rng(11)
    sizes = range(8, 21) if sampler == "sequential" else range(8, 13)
    for n in sizes:
        adjacency, node_types = random_topology(rng, n_joints=n)
        simulator = TopologySimulator(adjacency, node_types)
        found = PositionSampler(simulator).search(5, rng, sampler, max_negatives=4)
        assert found.positions.shape == (5, n, 2)
        assert len({p.tobytes() for p in found.positions}) == 5, "distinct variants"
        for positions in found.positions:
            assert dataset_rule_violations(simulator.topology, positions) == []
        trajectories, valid = links_ray.simulate_batch(adjacency, node_types, found.positions)
        assert valid.all()
        np.testing.assert_array_equal(trajectories, found.trajectories)
        # Independent re-simulation: plain Python, graph search at every step.
        reference = np.array(simulate_reference(adjacency, node_types, found.positions[0]))
        np.testing.assert_allclose(reference, trajectories[0], atol=1e-9)
        assert found.candidates >= 5


@pytest.mark.parametrize("sampler", SAMPLERS)
def test_negatives_really_lock_where_they_say(sampler: str) -> None:
    rng = np.random.default_rng(5)
    seen = 0
    for n in (8, 10, 12):
        adjacency, node_types = random_topology(rng, n_joints=n)
        sampler_ = PositionSampler(TopologySimulator(adjacency, node_types))
        found = sampler_.search(2, rng, sampler, max_negatives=10)
        assert len(found.negatives) <= 10
        for positions, step, node in zip(
            found.negatives, found.negative_step, found.negative_node, strict=True
        ):
            assert np.all((positions >= 0) & (positions <= 1))
            with pytest.raises(LockingError) as compiled:
                links_ray.simulate(adjacency, node_types, positions)
            with pytest.raises(LockingError) as plain:
                simulate_reference(adjacency, node_types, positions)
            assert (compiled.value.step, compiled.value.node) == (step, node)
            assert (plain.value.step, plain.value.node) == (step, node)
            seen += 1
    assert seen > 0


@pytest.mark.parametrize("sampler", SAMPLERS)
def test_seeded_and_reproducible(sampler: str) -> None:
    adjacency, node_types = random_topology(3, n_joints=10)
    first = links_ray.sample_positions(adjacency, node_types, 5, seed=42, sampler=sampler)
    again = links_ray.sample_positions(adjacency, node_types, 5, seed=42, sampler=sampler)
    other = links_ray.sample_positions(adjacency, node_types, 5, seed=43, sampler=sampler)
    np.testing.assert_array_equal(first, again)
    assert not np.array_equal(first, other)


def test_rejection_needs_more_candidates_for_larger_mechanisms() -> None:
    """The paper's infeasibility trend, on a small sample: 8 joints vs 12 joints."""
    rng = np.random.default_rng(0)

    def mean_candidates(n: int) -> float:
        counts = []
        for _ in range(8):
            simulator = TopologySimulator(*random_topology(rng, n_joints=n))
            counts.append(PositionSampler(simulator).search(3, rng, "rejection").candidates / 3)
        return float(np.mean(counts))

    assert mean_candidates(12) > 2 * mean_candidates(8)


def test_sampler_errors_are_clear() -> None:
    adjacency, node_types = random_topology(0, n_joints=8)
    with pytest.raises(ValueError, match="sampler"):
        links_ray.sample_positions(adjacency, node_types, sampler="magic")
    with pytest.raises(ValueError, match="count"):
        links_ray.sample_positions(adjacency, node_types, count=0)
    simulator = TopologySimulator(*random_topology(1, n_joints=20))
    with pytest.raises(RuntimeError, match="found 0 of 5"):
        PositionSampler(simulator).search(
            5, np.random.default_rng(0), "rejection", max_candidates=3
        )


def test_negatives_are_completed_as_by_a_draw_each() -> None:
    """The joints after a negative's rejected one take uniform draws, negative by negative in
    solving order: one draw for all gives the values of a draw per negative."""
    from links_ray.engine.kinematics.sampling import _complete_negatives

    topology = TopologySimulator(*random_topology(4, n_joints=14)).topology
    rejected = np.array([0, 3, len(topology.order) - 1, 5], dtype=np.int64)
    one, each = np.zeros((4, 14, 2)), np.zeros((4, 14, 2))
    later = len(topology.order) - 1 - rejected
    _complete_negatives(
        topology.order, rejected, np.random.default_rng(9).random((later.sum(), 2)), one
    )
    rng = np.random.default_rng(9)
    for row, k in zip(each, rejected, strict=True):
        joints = topology.order[k + 1 :, 0]
        row[joints] = rng.random((len(joints), 2))
    np.testing.assert_array_equal(one, each)
    assert np.count_nonzero(one) == 2 * later.sum()
