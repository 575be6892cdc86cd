"""An exact brute force of bars' distances, for the collision and layer tests
(tests/engine/fabrication/test_collisions.py, test_layer_plan.py): every pair's exact segment
distance at every step of a sampled turn, its own formula (the lines' crossing parameters) compiled
apart from the engine's (engine/fabrication/collisions.py).
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True)
def point_to_segment_sq(px: float, py: float, ax: float, ay: float, bx: float, by: float) -> float:
    ux, uy = bx - ax, by - ay
    length_sq = ux * ux + uy * uy
    s = 0.0 if length_sq == 0.0 else ((px - ax) * ux + (py - ay) * uy) / length_sq
    s = min(1.0, max(0.0, s))
    return (ax + s * ux - px) ** 2 + (ay + s * uy - py) ** 2


@numba.njit(cache=True)
def exact_distance(pose: np.ndarray, a: int, b: int, c: int, d: int) -> float:
    """Segments ab and cd: 0 where the lines' crossing lies on both, else an end is closest."""
    px, py, qx, qy = pose[a, 0], pose[a, 1], pose[b, 0], pose[b, 1]
    rx, ry, sx, sy = pose[c, 0], pose[c, 1], pose[d, 0], pose[d, 1]
    ux, uy, vx, vy, wx, wy = qx - px, qy - py, sx - rx, sy - ry, rx - px, ry - py
    denom = ux * vy - uy * vx
    if denom != 0.0:
        s = (wx * vy - wy * vx) / denom
        t = (wx * uy - wy * ux) / denom
        if 0.0 <= s <= 1.0 and 0.0 <= t <= 1.0:
            return 0.0
    return np.sqrt(
        min(
            point_to_segment_sq(px, py, rx, ry, sx, sy),
            point_to_segment_sq(qx, qy, rx, ry, sx, sy),
            point_to_segment_sq(rx, ry, px, py, qx, qy),
            point_to_segment_sq(sx, sy, px, py, qx, qy),
        )
    )


@numba.njit(cache=True)
def brute_force(traj: np.ndarray, pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pair (a, b, c, d): its least distance over the steps of `traj` (n, steps, 2), and
    half the most its ends move between two steps (by how much the distance might dip below
    the least between the steps, to first order)."""
    least = np.full(pairs.shape[0], np.inf)
    dip = np.zeros(pairs.shape[0])
    steps = traj.shape[1]
    for t in range(steps):
        u = (t + 1) % steps
        pose = traj[:, t]
        moves = np.hypot(traj[:, u, 0] - traj[:, t, 0], traj[:, u, 1] - traj[:, t, 1])
        for i in range(pairs.shape[0]):
            a, b, c, d = pairs[i]
            least[i] = min(least[i], exact_distance(pose, a, b, c, d))
            dip[i] = max(dip[i], 0.5 * (max(moves[a], moves[b]) + max(moves[c], moves[d])))
    return least, dip


def pairs_of(adjacency: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(links (L, 2), pairs (p, 4), link pair or (link, joint) (p, 2), is_pin (p,)): the pairs
    with geometry, from the adjacency matrix alone."""
    links = np.argwhere(np.triu(adjacency, 1))
    rows, which, is_pin = [], [], []
    for p in range(len(links)):
        for q in range(p + 1, len(links)):
            if not set(links[p]) & set(links[q]):
                rows.append([*links[p], *links[q]])
                which.append([p, q])
                is_pin.append(False)
        for joint in range(len(adjacency)):
            if joint not in links[p]:
                rows.append([*links[p], joint, joint])
                which.append([p, joint])
                is_pin.append(True)
    return links, np.array(rows), np.array(which), np.array(is_pin)
