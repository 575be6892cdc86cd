"""Prescribed timing: where in its turn a mechanism should start so that its joint reaches
each drawn point at that point's crank angle.

A timed target (`target.Target.timed`) gives each drawn point a crank angle relative to a
free start. Refinement moves the joints' initial positions, which can shift the start only a
little at a time; `best_start` picks it outright. It traces the joint over a fine turn, finds
the start among those steps (coarsely, then finely around the best) whose timed error (the
mean distance of each point from the path at its angle, the path interpolated between steps)
is least, and returns the mechanism as it stands at that step: the same mechanism, its crank
started there, its joints on the same branches, so that only the timing has changed.

Pure numpy: no numba of its own, no Ray.
"""

from __future__ import annotations

import numpy as np

from links_ray.engine.kinematics.mechanism import Topology
from links_ray.engine.kinematics.solver import simulate
from links_ray.engine.synthesis.limits import REFINE_CHECK_STEPS
from links_ray.engine.synthesis.target import Target

__all__ = ["best_start"]

#: Most (start, point) pairs interpolated at once: a bound on the search's memory.
BLOCK = 1 << 20
#: The search tries every STRIDE-th step of the fine turn, then every step around the best.
STRIDE = 10


def best_start(topology: Topology, positions: np.ndarray, joint: int, target: Target) -> np.ndarray:
    """`positions` (n, 2) moved along their own turn to the start, among REFINE_CHECK_STEPS
    steps, that brings `joint` nearest the timed `target`'s points at their angles. Raises
    LockingError if the mechanism locks over the turn and ValueError for an untimed target."""
    if target.crank is None:
        raise ValueError("best_start needs a timed target")
    steps = REFINE_CHECK_STEPS
    traj = simulate(topology.adjacency, topology.node_types, positions, steps)
    path = traj[joint]
    # Each point's angle as a fractional step of the fine turn, from a start at step 0.
    angles = np.arctan2(target.crank[:, 1], target.crank[:, 0]) % (2.0 * np.pi)
    offsets = angles * steps / (2.0 * np.pi)
    coarse = _best_of(path, offsets, target.points, np.arange(0, steps, STRIDE))
    best = _best_of(path, offsets, target.points, np.arange(coarse - STRIDE, coarse + STRIDE))
    return np.ascontiguousarray(traj[:, best % steps, :])


def _best_of(path: np.ndarray, offsets: np.ndarray, points: np.ndarray, starts: np.ndarray) -> int:
    """The start among `starts` (steps of `path` (steps, 2), any integers) whose timed error
    is least: each point i compared with the path at start + offsets[i], interpolated."""
    steps = len(path)
    best, best_error = 0, np.inf
    block = max(1, BLOCK // len(offsets))
    for first in range(0, len(starts), block):
        chosen = starts[first : first + block]
        at = (chosen[:, None] + offsets[None, :]) % steps
        low = np.floor(at).astype(np.int64)
        share = (at - low)[..., None]
        traced = (1.0 - share) * path[low % steps] + share * path[(low + 1) % steps]
        errors = np.hypot(*(traced - points).transpose(2, 0, 1)).mean(axis=1)
        i = int(np.argmin(errors))
        if errors[i] < best_error:
            best, best_error = int(chosen[i]), float(errors[i])
    return best
