"""Held-out retrieval queries: paths of mechanisms drawn afresh (so in no dataset), placed in a
random frame, as a user's drawing of a curve would be. Benchmarks and tests measure retrieval
on them."""

from __future__ import annotations

import numpy as np

from links_ray.engine.kinematics.mechanism import analyze_topology, arc_joints
from links_ray.engine.kinematics.paths import is_circle, normalize_path
from links_ray.engine.kinematics.sampling import PositionSampler
from links_ray.engine.kinematics.solver import TopologySimulator
from links_ray.engine.kinematics.topology import random_topology


def held_out_queries(count: int, seed: int) -> list[np.ndarray]:
    """`count` paths, each (steps, 2), of fresh random mechanisms drawn with `seed`.

    Each is the trajectory of a moving joint that traces no arc, chosen at random, over one
    crank turn; a circle is drawn again. Each is moved (up to 10 units), turned, scaled (0.5 to
    20 times) and, half the time, mirrored. The same `count` and `seed` give the same paths.
    """
    rng = np.random.default_rng(seed)
    queries = []
    while len(queries) < count:
        adjacency, node_types = random_topology(rng)
        simulator = TopologySimulator(adjacency, node_types)
        found = PositionSampler(simulator).search(1, rng, "sequential")
        arcs = arc_joints(analyze_topology(adjacency, node_types))
        joint = int(rng.choice(np.flatnonzero((node_types != 0) & ~arcs)))
        path = found.trajectories[0, joint]
        if is_circle(normalize_path(path)):
            continue
        angle = rng.uniform(0, 2 * np.pi)
        turn = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
        if rng.random() < 0.5:
            turn = turn @ np.diag([1.0, -1.0])
        queries.append(path @ turn.T * rng.uniform(0.5, 20) + rng.uniform(-10, 10, 2))
    return queries
