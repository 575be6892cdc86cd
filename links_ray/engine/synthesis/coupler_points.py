"""A coupler point added to a mechanism: one more joint, on a link of the joint that traces.

When refinement stalls, the mechanism has no freedom left that lowers the fit. One more joint,
fixed to a link of the tracing joint (a rigid triangle: the new joint's two links keep their
lengths and the angle between them), gives it a coupler point: two new coordinates whose path
is the tracing joint's path plus a vector turning with that link. Placed a small offset from
the tracing joint, square to the link so the triangle is far from flat, it traces nearly the
same curve, and refinement goes on from there with the new freedom. This is the J-operator's
step (a new joint joined to two known ones) at the place it helps most.

Pure numpy: no Ray.
"""

from __future__ import annotations

import numpy as np

from links_ray.engine.kinematics.mechanism import Topology
from links_ray.engine.node_kinds import SIMPLE

__all__ = ["COUPLER_POINT_MAX_JOINTS", "with_coupler_point"]

#: A mechanism grows only while it has fewer joints than this (the dataset's largest).
COUPLER_POINT_MAX_JOINTS = 20


def with_coupler_point(
    topology: Topology,
    positions: np.ndarray,
    joint: int,
    offset: float,
    max_joints: int = COUPLER_POINT_MAX_JOINTS,
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(adjacency, node_types, positions) of each way to add a coupler
    point on a link of `joint`: one for each neighbour of `joint` it shares a link with, the new
    joint (the last) `offset` from `joint` square to that link, on the side away from the
    mechanism's centre. Empty if the mechanism with it would have more than `max_joints` joints
    (at most COUPLER_POINT_MAX_JOINTS), or `joint` has no neighbour farther than `offset`."""
    n = topology.n_joints
    if positions.shape != (n, 2):
        raise ValueError(f"positions must be ({n}, 2), got {positions.shape}")
    if not 0 <= joint < n:
        raise ValueError(f"joint must be in 0..{n - 1}, got {joint}")
    if not offset > 0.0:
        raise ValueError(f"offset must be positive, got {offset}")
    if n >= min(max_joints, COUPLER_POINT_MAX_JOINTS):
        return []
    centre = positions.mean(axis=0)
    node_types = np.append(topology.node_types, np.int8(SIMPLE)).astype(np.int8)
    added = []
    for neighbour in np.flatnonzero(topology.adjacency[joint]):
        along = positions[joint] - positions[neighbour]
        length = float(np.hypot(*along))
        if length <= offset:
            continue  # the triangle would be as long as the link: no small step
        square = np.array([-along[1], along[0]]) / length
        if np.dot(square, positions[joint] - centre) < 0.0:
            square = -square
        adjacency = np.zeros((n + 1, n + 1), dtype=np.uint8)
        adjacency[:n, :n] = topology.adjacency
        adjacency[n, [joint, neighbour]] = adjacency[[joint, neighbour], n] = 1
        at = np.vstack([positions, positions[joint] + offset * square])
        added.append((adjacency, node_types.copy(), at))
    return added
