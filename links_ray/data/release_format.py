"""Facts of the LINKS release's own files that links-ray's import and export share.

The release simulates every mechanism at the absolute crank angles `release_angles()`:
`numpy.linspace(0, 2*pi, RELEASE_STEPS)`, both ends included (so its last point repeats its
first), with joint 1 placed at x0[0] + r (cos theta, sin theta), r the crank's length: the
crank starts along +x, not where x0 has it. links-ray starts the crank at its initial angle and
steps 2*pi*t/steps for t < steps. Each dyad keeps, at every angle, the side of its two parents
it has in x0, as links-ray's solver does; so `release_trajectories` is links-ray's solver on
the release's angles (relative to the crank's initial angle), and equals the release's own
trajectories up to rounding.

Pure numpy: the solver is the engine's. No Ray, no files.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from links_ray.engine.mechanism import analyze_topology
from links_ray.engine.solver import simulate_one

__all__ = ["RELEASE_STEPS", "release_angles", "release_crank", "release_trajectories"]

#: Points of every curve the release holds.
RELEASE_STEPS = 200


def release_angles() -> np.ndarray:
    """(RELEASE_STEPS,) the release's absolute crank angles, 0 to 2 pi, both included."""
    return np.linspace(0.0, 2.0 * np.pi, RELEASE_STEPS)


def release_crank(positions: np.ndarray) -> np.ndarray:
    """(RELEASE_STEPS, 2) cos and sin of the release's angles relative to the crank's initial
    angle in `positions` (n, 2): the crank table the engine's solver turns through."""
    start = np.arctan2(positions[1, 1] - positions[0, 1], positions[1, 0] - positions[0, 0])
    relative = release_angles() - start
    return np.ascontiguousarray(np.stack([np.cos(relative), np.sin(relative)], axis=1))


def release_trajectories(
    adjacency: ArrayLike, node_types: ArrayLike, positions: ArrayLike
) -> tuple[np.ndarray, tuple[int, int]]:
    """(trajectories (n, RELEASE_STEPS, 2), lock) of a mechanism in links-ray's conventions
    (node types FIXED/SIMPLE/ACTUATED, joint 1 the crank's tip) at the release's angles;
    lock is (-1, -1), or the (step, joint) where it first cannot be assembled (only the
    release's steps are checked, as the release checks them; the trajectories are then
    meaningless from that step on). Raises InvalidMechanismError for a malformed mechanism."""
    topology = analyze_topology(adjacency, node_types)
    pos = np.ascontiguousarray(positions, dtype=np.float64)
    if pos.shape != (topology.n_joints, 2):
        raise ValueError(f"positions must be ({topology.n_joints}, 2), got {pos.shape}")
    out = np.empty((topology.n_joints, RELEASE_STEPS, 2))
    geometry = np.empty((len(topology.order), 3))
    step, joint = simulate_one(
        topology.order, topology.fixed_joints, pos, release_crank(pos), True, out, geometry
    )
    return out, (int(step), int(joint))
