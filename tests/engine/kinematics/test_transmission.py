"""Transmission angles against independent truth: a four-bar's law of cosines, and plain
numpy angles from a generated data set's stored trajectories (engine.kinematics.transmission)."""

from __future__ import annotations

import numpy as np
import pytest

import links_ray
from links_ray.engine.kinematics.mechanism import analyze_topology
from links_ray.engine.kinematics.solver import simulate
from links_ray.engine.kinematics.transmission import (
    NO_DYAD_DEG,
    _joint_sines,
    joint_transmission_deg,
    least_sines,
    mechanism_transmission_deg,
)
from tests.support.fourbars import stretched_four_bar
from tests.support.nearest_point import agreement


def folded_degrees(cosines: np.ndarray) -> np.ndarray:
    """An angle from its cosine, folded to 0-90 degrees (an angle is as good as its supplement)."""
    return np.degrees(np.arcsin(np.sqrt(np.clip(1 - cosines**2, 0, 1))))


@pytest.mark.parametrize("slack", [0.01, 0.03, 0.1])
def test_four_bar_matches_the_law_of_cosines(slack: float) -> None:
    """Joint 3's angle between its coupler (to the tip) and follower (to the pivot) at each
    step is arccos((r1^2 + r2^2 - s^2) / (2 r1 r2)), s the tip-pivot distance; over the turn
    it comes nearest a dead centre where s is longest, L + R (the fourbars module)."""
    mechanism = stretched_four_bar(7, 200, slack)
    positions = mechanism["positions"]
    trajectories = simulate(mechanism["adjacency"], mechanism["node_types"], positions, 200)
    tip, pivot = trajectories[1], positions[2]
    r1 = np.linalg.norm(positions[3] - positions[1])
    r2 = np.linalg.norm(positions[3] - positions[2])
    s = np.linalg.norm(tip - pivot, axis=1)
    per_step = folded_degrees((r1**2 + r2**2 - s**2) / (2 * r1 * r2))
    order = analyze_topology(mechanism["adjacency"], mechanism["node_types"]).order
    joints = joint_transmission_deg(order, trajectories[None])[0]
    np.testing.assert_allclose(joints[3], per_step.min(), atol=1e-4)
    np.testing.assert_array_equal(joints[:3], NO_DYAD_DEG)  # fixed joints and the crank tip
    assert mechanism_transmission_deg(order, trajectories[None])[0] == joints[3]
    # The folded angle is monotone in s on either side of 90 degrees, so over the whole turn
    # its least is at the shortest or the longest s, L - R or L + R; the sampled least is at
    # most a step's worth above it.
    crank = np.linalg.norm(positions[1] - positions[0])
    ground = np.linalg.norm(positions[2] - positions[0])
    extremes = np.array([ground - crank, ground + crank])
    continuous = folded_degrees((r1**2 + r2**2 - extremes**2) / (2 * r1 * r2)).min()
    assert continuous <= joints[3] < continuous + 0.5


def dyad_degrees(trajectories: np.ndarray, j: int, a: int, b: int) -> np.ndarray:
    """(steps,) the folded angle at joint j between the links to a and b, in plain numpy."""
    u = trajectories[a].astype(np.float64) - trajectories[j]
    v = trajectories[b].astype(np.float64) - trajectories[j]
    cosines = (u * v).sum(axis=1) / (np.linalg.norm(u, axis=1) * np.linalg.norm(v, axis=1))
    return folded_degrees(cosines)


def test_dataset_columns_are_the_angles_of_the_stored_trajectories(dataset: str) -> None:
    """A mechanism's `min_transmission_deg` is the least angle over all its dyads and stored
    steps; a path's is the least over the dyads of its joint and of every joint that joint
    depends on; the least of a mechanism's paths is the mechanism's."""
    mechanisms = links_ray.load(dataset, "mechanisms", reshape=True).set_index("mechanism_id")
    simulations = links_ray.load(dataset, "simulations", reshape=True).set_index("mechanism_id")
    paths = links_ray.load(
        dataset, "paths", columns=["mechanism_id", "joint", "min_transmission_deg"]
    )
    assert len(mechanisms) == 300 and len(paths) > len(mechanisms)
    by_mechanism = paths.groupby("mechanism_id")["min_transmission_deg"].min()
    np.testing.assert_array_equal(
        by_mechanism.sort_index().to_numpy(),
        mechanisms["min_transmission_deg"].sort_index().to_numpy(),
    )
    path_angle = paths.set_index(["mechanism_id", "joint"])["min_transmission_deg"]
    for mechanism_id in mechanisms.index[::7]:
        row = mechanisms.loc[mechanism_id]
        trajectories = simulations.loc[mechanism_id, "trajectories"]
        order = analyze_topology(row["adjacency"], row["node_types"]).order
        own = {int(j): dyad_degrees(trajectories, j, a, b).min() for j, a, b in order}
        least = min(own.values(), default=NO_DYAD_DEG)
        np.testing.assert_allclose(row["min_transmission_deg"], least, atol=1e-3)
        depends = {int(j): {int(j)} for j in np.flatnonzero(row["node_types"] != 0)}
        for j, a, b in order:  # a joint depends on its parents' dyads as well as its own
            depends[int(j)] |= depends.get(int(a), set()) | depends.get(int(b), set())
        for joint, dyads in depends.items():
            expected = min((own[d] for d in dyads if d in own), default=NO_DYAD_DEG)
            np.testing.assert_allclose(path_angle[(mechanism_id, joint)], expected, atol=1e-3)
    assert 0 < mechanisms["min_transmission_deg"].min() < 90


def test_a_nearest_point_solver_agrees_where_the_angle_is_kept() -> None:
    """An independent simulator that picks each assembly by the nearest point (as peer
    simulators do) traces every valid mechanism keeping 10 degrees exactly as the engine does;
    it parts from the engine's frozen branches only on mechanisms passing nearer a dead centre."""
    tally = agreement(60, seed=3)
    for floor in ("10", "20"):
        agree, of = tally[floor]
        assert of == 60 and agree == of, floor
    agree, of = tally["all"]
    assert of == 60 and agree < of  # the two solvers do differ, below 10 degrees


def test_joint_angles_are_the_least_over_each_joints_dyads() -> None:
    """Each joint's angle is the least over its own dyad and every dyad it depends on: the
    compiled pass against a plain loop over the path; NaN spreads as np.minimum spreads it."""
    rng = np.random.default_rng(8)
    for case in range(30):
        topology = analyze_topology(*links_ray.random_topology(rng))
        n = topology.n_joints
        trajectories = rng.random((4, n, 12, 2))
        dyad_sines = np.empty((4, len(topology.order)))
        least_sines(topology.order, trajectories, dyad_sines)
        if case % 2:
            dyad_sines[rng.random(dyad_sines.shape) < 0.1] = np.nan
        joint_sines = np.ones((4, n))
        for k, (j, a, b) in enumerate(topology.order):
            parents = np.minimum(joint_sines[:, a], joint_sines[:, b])
            joint_sines[:, j] = np.minimum(dyad_sines[:, k], parents)
        compiled = np.empty((4, n))
        _joint_sines(topology.order, dyad_sines, compiled)
        np.testing.assert_array_equal(compiled, joint_sines)
        if not case % 2:
            expected = np.degrees(np.arcsin(np.clip(joint_sines, 0, 1))).astype(np.float32)
            np.testing.assert_array_equal(
                joint_transmission_deg(topology.order, trajectories), expected
            )
