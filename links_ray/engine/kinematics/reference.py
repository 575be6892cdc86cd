"""A plain-Python dyadic solver: the readable reference, and the paper's Table 1 row 1.

It does what the compiled solver does, without the shortcuts: at every crank step it searches the
graph again for joints with two known neighbours (lowest index first) and solves them with the
`math` module, one position set at a time. Use `links_ray.simulate` for real work.
"""

from __future__ import annotations

import math

from links_ray.engine.kinematics.mechanism import FIXED, LockingError

Point = tuple[float, float]


def simulate_reference(
    adjacency: list[list[int]],
    node_types: list[int],
    positions: list[list[float]],
    steps: int = 200,
) -> list[list[Point]]:
    """Trajectories [joint][step] = (x, y); raises `LockingError` at the first lock.

    Expects a valid mechanism (see `links_ray.engine.kinematics.mechanism.analyze_topology`); plain
    lists or arrays.
    """
    n = len(node_types)
    neighbours = [[k for k in range(n) if adjacency[j][k]] for j in range(n)]
    start = [(float(x), float(y)) for x, y in positions]
    radius = [[math.dist(start[j], start[k]) for k in range(n)] for j in range(n)]
    x0, y0 = start[0]
    crank_angle = math.atan2(start[1][1] - y0, start[1][0] - x0)
    crank_length = radius[0][1]

    trajectories: list[list[Point]] = [[] for _ in range(n)]
    for t in range(steps):
        pose: list[Point | None] = [None] * n
        for j in range(n):
            if node_types[j] == FIXED:
                pose[j] = start[j]
        angle = crank_angle + 2 * math.pi * t / steps
        pose[1] = (x0 + crank_length * math.cos(angle), y0 + crank_length * math.sin(angle))
        while any(p is None for p in pose):
            j = next(
                j
                for j in range(n)
                if pose[j] is None and sum(pose[k] is not None for k in neighbours[j]) >= 2
            )
            a, b = (k for k in neighbours[j] if pose[k] is not None)
            solved = _circle_intersection(
                start, pose[a], pose[b], radius[j][a], radius[j][b], j, a, b
            )
            if solved is None:
                raise LockingError(t, j)
            pose[j] = solved
        for j in range(n):
            trajectories[j].append(pose[j])
    return trajectories


def _circle_intersection(
    start: list[Point], pa: Point, pb: Point, r1: float, r2: float, j: int, a: int, b: int
) -> Point | None:
    """The point at r1 from pa and r2 from pb on the side of a -> b where joint j started."""
    d = math.dist(pa, pb)
    if d > r1 + r2 or d < abs(r1 - r2) or d == 0:
        return None
    along = (d * d + r1 * r1 - r2 * r2) / (2 * d)
    height = math.sqrt(max(r1 * r1 - along * along, 0.0))
    (ax, ay), (bx, by), (jx, jy) = start[a], start[b], start[j]
    if (bx - ax) * (jy - ay) - (by - ay) * (jx - ax) < 0:
        height = -height
    ux, uy = (pb[0] - pa[0]) / d, (pb[1] - pa[1]) / d
    return (pa[0] + along * ux - height * uy, pa[1] + along * uy + height * ux)
