"""Transmission angles: how far each dyad stays from a dead centre over a turn.

At a solved joint j on parents a and b, the transmission angle is the angle between the links
j-a and j-b, folded to 0-90 degrees (an angle and its supplement are as good): 90 transmits
motion best, 0 is a dead centre (the dyad fully stretched or folded), where a real mechanism
jams or flips branch. A mechanism's least transmission angle is the smallest over all its
dyads and sampled steps; a joint's is the smallest over the dyads its motion needs (its own and
those of every joint it depends on), the angle of the reduced mechanism that traces its path.

Rigid dyads (a triangle of links, whose angle never changes) count too: a nearly flat one is a
sliver of a plate, its joint ill-determined by its link lengths, and a nearest-point simulator
flips it to its mirror image when the plate turns faster a step than its two assemblies are
apart: tests/support/nearest_point.py is such a simulator, and on mechanisms whose moving
dyads keep 10 degrees, where it parted from this one a nearly flat rigid triangle was the cause
(docs/benchmarks.md, Simulators that track the nearest point).

Pure numpy/numba: no Ray.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from links_ray.engine.buffers import check_buffer, check_solution_path

#: The angle of a joint whose motion goes through no dyad (fixed joints and the crank tip).
NO_DYAD_DEG = 90.0


@njit(cache=True, nogil=True, error_model="numpy")
def _least_sines(order: np.ndarray, trajectories: np.ndarray, out: np.ndarray) -> None:
    """out[i, k]: the least sine of dyad k's transmission angle over the steps of mechanism i,
    for trajectories (B, n, steps, 2) of one topology whose solution path is `order`."""
    for i in range(trajectories.shape[0]):
        for k in range(order.shape[0]):
            j, a, b = order[k, 0], order[k, 1], order[k, 2]
            least = 1.0
            for t in range(trajectories.shape[2]):
                ux = trajectories[i, a, t, 0] - trajectories[i, j, t, 0]
                uy = trajectories[i, a, t, 1] - trajectories[i, j, t, 1]
                vx = trajectories[i, b, t, 0] - trajectories[i, j, t, 0]
                vy = trajectories[i, b, t, 1] - trajectories[i, j, t, 1]
                lengths = np.sqrt((ux * ux + uy * uy) * (vx * vx + vy * vy))
                if lengths > 0.0:
                    least = min(least, abs(ux * vy - uy * vx) / lengths)
                else:
                    least = 0.0
            out[i, k] = least


@njit(cache=True, nogil=True)
def _joint_sines(order: np.ndarray, sines: np.ndarray, out: np.ndarray) -> None:
    """out (B, n): each joint's least sine over its own dyad and its parents' (1 for a joint
    with no dyad), from each dyad's least sines (B, m); NaN spreads as np.minimum spreads it."""
    out[:] = 1.0
    for i in range(sines.shape[0]):
        for k in range(order.shape[0]):  # parents come before their children
            least = sines[i, k]
            for parent in (out[i, order[k, 1]], out[i, order[k, 2]]):
                if least == least and (parent != parent or parent < least):
                    least = parent
            out[i, order[k, 0]] = least


def least_sines(order: np.ndarray, trajectories: np.ndarray, out: np.ndarray) -> None:
    """out (B, m): the least sine of each dyad's transmission angle over each mechanism's
    steps, for trajectories (B, n, steps, 2) of one topology (`_least_sines`)."""
    check_buffer("trajectories", trajectories, (None, None, None, 2), "f")
    check_solution_path(order, trajectories.shape[1], positions="trajectories")
    check_buffer("out", out, (trajectories.shape[0], order.shape[0]))
    _least_sines(order, trajectories, out)


def joint_transmission_deg(order: np.ndarray, trajectories: np.ndarray) -> np.ndarray:
    """(B, n) float32: each joint's least transmission angle in degrees (the module says which
    dyads count), from trajectories (B, n, steps, 2) of one topology."""
    batch, n = trajectories.shape[:2]
    sines = np.empty((batch, len(order)))
    order = np.asarray(order, dtype=np.int64)
    least_sines(order, trajectories, sines)  # checks order against the trajectories
    joint_sines = np.empty((batch, n))
    _joint_sines(order, sines, joint_sines)
    return np.degrees(np.arcsin(np.clip(joint_sines, 0.0, 1.0))).astype(np.float32)


def mechanism_transmission_deg(order: np.ndarray, trajectories: np.ndarray) -> np.ndarray:
    """(B,) float32: each mechanism's least transmission angle in degrees over all its dyads
    (NO_DYAD_DEG for one without any)."""
    return joint_transmission_deg(order, trajectories).min(axis=1)
