"""Kernels of refinement: the dyadic solver with forward-mode derivatives, and the nearest-point
work of the chamfer objective.

`solve_tangents` runs the solver's own arithmetic (`place_crank`, `place_fixed`, `dyad_geometry`
and the formulas of `solve_span`), so its trajectories equal `simulate`'s, and carries beside
every value its exact derivative with respect to all 2n initial coordinates. The radii and the
lever of each dyad are functions of the initial positions, so their derivatives count; the
branch sign is piecewise constant and contributes none.

The kernels' entry points, called from Python with the caller's buffers, check their shapes
first (`buffers.check_buffer`): numba checks no bounds.

Pure numpy/numba, plain-array signatures: no Ray.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from links_ray.engine.buffers import check_buffer, check_solution_path
from links_ray.engine.paths import _nearest_sq
from links_ray.engine.solver import _dyad_geometry, _place_crank, _place_fixed, dyad_fails


@njit(cache=True, nogil=True, error_model="numpy")
def _solve_tangents(
    order: np.ndarray,
    fixed: np.ndarray,
    pos: np.ndarray,
    crank: np.ndarray,
    traj: np.ndarray,
    dtraj: np.ndarray,
    trans: np.ndarray,
    dtrans: np.ndarray,
    geometry: np.ndarray,
) -> tuple[int, int]:
    """Trajectories, transmission and (optionally) their derivatives, for one mechanism.

    Writes traj (n, steps, 2), the solver's trajectories; trans (m, steps), per dyad k of
    `order` the sine of the angle at its solved joint between the links to its two parents
    (0 at a dead centre); geometry (m, 3) as `_dyad_geometry`. If dtraj has shape
    (n, steps, 2, 2n) it receives d traj / d pos, column 2i + c for coordinate c of joint i, and
    dtrans (m, steps, 2n) likewise; pass zero-width arrays (last axis 0) for values only.
    Returns (-1, -1) when every step assembles, else (first locking step, joint) as
    `simulate_one` reports them; values at and after a lock are meaningless.

    A joint's path depends only on the coordinates of itself and its ancestors: each dyad's
    derivatives are carried in those columns alone (the rest stay 0), which halves the work
    for a typical mechanism.
    """
    steps = crank.shape[0]
    cols = dtraj.shape[3]
    _dyad_geometry(order, pos, geometry)
    _place_fixed(fixed, pos, traj, steps)
    _place_crank(pos, crank, traj, 0, steps, 0)
    if cols:
        dtraj[:] = 0.0
        for i in range(fixed.shape[0]):
            f = fixed[i]
            for s in range(steps):
                dtraj[f, s, 0, 2 * f] = 1.0
                dtraj[f, s, 1, 2 * f + 1] = 1.0
        # Joint 1 is pos[0] + R(t) (pos[1] - pos[0]).
        for s in range(steps):
            c, si = crank[s, 0], crank[s, 1]
            dtraj[1, s, 0, 0] = 1.0 - c
            dtraj[1, s, 0, 1] = si
            dtraj[1, s, 0, 2] = c
            dtraj[1, s, 0, 3] = -si
            dtraj[1, s, 1, 0] = -si
            dtraj[1, s, 1, 1] = 1.0 - c
            dtraj[1, s, 1, 2] = si
            dtraj[1, s, 1, 3] = c
    # depends[i, p]: joint i's path depends on coordinate p (so d traj[i] / d p may be nonzero).
    depends = np.zeros((pos.shape[0], cols), dtype=np.bool_)
    live = np.empty(cols, dtype=np.int64)  # the columns a dyad's loops visit
    if cols:
        dtrans[:] = 0.0
        for i in range(fixed.shape[0]):
            depends[fixed[i], 2 * fixed[i]] = True
            depends[fixed[i], 2 * fixed[i] + 1] = True
        depends[1, 0:4] = True
    # Derivatives of the frozen dyad constants: r1^2, r2^2 (so the lever) and r1, r2.
    dr1_sq = np.zeros(cols)
    dr2_sq = np.zeros(cols)
    lock_step, lock_node = -1, -1
    for k in range(order.shape[0]):
        j, a, b = order[k, 0], order[k, 1], order[k, 2]
        r1, r2, side = geometry[k, 0], geometry[k, 1], geometry[k, 2]
        r1_sq = r1 * r1
        lever = r1_sq - r2 * r2
        if cols:
            dr1_sq[:] = 0.0
            dr2_sq[:] = 0.0
            for c in range(2):
                u = 2.0 * (pos[j, c] - pos[a, c])
                v = 2.0 * (pos[j, c] - pos[b, c])
                dr1_sq[2 * j + c] += u
                dr1_sq[2 * a + c] -= u
                dr2_sq[2 * j + c] += v
                dr2_sq[2 * b + c] -= v
            depends[j, 2 * j] = True
            depends[j, 2 * j + 1] = True
        count = 0
        for p in range(cols):
            if depends[a, p] or depends[b, p]:
                depends[j, p] = True
            if depends[j, p]:
                live[count] = p
                count += 1
        inv_r12 = 1.0 / (r1 * r2)
        for s in range(steps):
            ax = traj[a, s, 0]
            ay = traj[a, s, 1]
            dx = traj[b, s, 0] - ax
            dy = traj[b, s, 1] - ay
            d_sq = dx * dx + dy * dy
            if dyad_fails(d_sq, r1, r2) and (lock_step < 0 or s < lock_step):
                lock_step, lock_node = s, j
            # Exactly `solve_span`'s expressions, in its order: the values match bit for bit.
            inv_d_sq = 1.0 / d_sq
            along = 0.5 * (d_sq + lever) * inv_d_sq
            h_sq = r1_sq * inv_d_sq - along * along
            root = np.sqrt(max(h_sq, 0.0))
            height = side * root
            traj[j, s, 0] = ax + along * dx - height * dy
            traj[j, s, 1] = ay + along * dy + height * dx
            # Triangle a-j-b: twice its area is root * d_sq = r1 r2 sin(angle at j).
            tau = root * d_sq * inv_r12
            trans[k, s] = tau
            if cols == 0:
                continue
            # d root is unbounded at a dead centre (root = 0); the margin keeps steps away.
            half_inv_root = 0.5 / root if root > 0.0 else 0.0
            for q in range(count):
                p = live[q]
                ddx = dtraj[b, s, 0, p] - dtraj[a, s, 0, p]
                ddy = dtraj[b, s, 1, p] - dtraj[a, s, 1, p]
                dd_sq = 2.0 * (dx * ddx + dy * ddy)
                dinv = -inv_d_sq * inv_d_sq * dd_sq
                dlever = dr1_sq[p] - dr2_sq[p]
                dalong = 0.5 * (dd_sq + dlever) * inv_d_sq + 0.5 * (d_sq + lever) * dinv
                dh_sq = dr1_sq[p] * inv_d_sq + r1_sq * dinv - 2.0 * along * dalong
                droot = dh_sq * half_inv_root
                dheight = side * droot
                dtraj[j, s, 0, p] = (
                    dtraj[a, s, 0, p] + dalong * dx + along * ddx - dheight * dy - height * ddy
                )
                dtraj[j, s, 1, p] = (
                    dtraj[a, s, 1, p] + dalong * dy + along * ddy + dheight * dx + height * ddx
                )
                # d(r1 r2) / (r1 r2) = dr1/r1 + dr2/r2 = (dr1_sq/r1^2 + dr2_sq/r2^2) / 2.
                rel = 0.5 * (dr1_sq[p] / r1_sq + dr2_sq[p] / (r2 * r2))
                dtrans[k, s, p] = (droot * d_sq + root * dd_sq) * inv_r12 - tau * rel
    return lock_step, lock_node


@njit(cache=True, nogil=True)
def _nearest_pairs(
    path: np.ndarray,
    target: np.ndarray,
    path_nn: np.ndarray,
    path_d: np.ndarray,
    target_nn: np.ndarray,
    target_d: np.ndarray,
) -> None:
    """For each path point its nearest target point (index, distance), and the other way.

    Each side is searched sorted by x (`paths._nearest_sq`), as the chamfer itself is."""
    path_x = np.ascontiguousarray(path[:, 0])
    path_y = np.ascontiguousarray(path[:, 1])
    target_x = np.ascontiguousarray(target[:, 0])
    target_y = np.ascontiguousarray(target[:, 1])
    by_x = np.argsort(target_x)
    _nearest_sq(target_x[by_x], target_y[by_x], path_x, path_y, path_d, path_nn)
    for s in range(path.shape[0]):
        path_nn[s] = by_x[path_nn[s]]
        path_d[s] = np.sqrt(path_d[s])
    by_x = np.argsort(path_x)
    _nearest_sq(path_x[by_x], path_y[by_x], target_x, target_y, target_d, target_nn)
    for i in range(target.shape[0]):
        target_nn[i] = by_x[target_nn[i]]
        target_d[i] = np.sqrt(target_d[i])


@njit(cache=True, nogil=True)
def _best_interval(path: np.ndarray, stroke: np.ndarray, min_count: int) -> tuple[int, int, float]:
    """The run of consecutive path points (cyclic) whose chamfer to `stroke` is least.

    Tries every start and every count from `min_count` to all the points: (start, count,
    chamfer), the shortest run and then the lowest start on ties. O(steps^2 x points): the
    stroke's running nearest distances are kept while a run grows one point at a time.
    """
    steps = path.shape[0]
    m = stroke.shape[0]
    dist = np.empty((steps, m))
    column = np.empty(steps)  # nearest stroke distance of each path point
    for s in range(steps):
        best = np.inf
        for i in range(m):
            dx = stroke[i, 0] - path[s, 0]
            dy = stroke[i, 1] - path[s, 1]
            d = np.sqrt(dx * dx + dy * dy)
            dist[s, i] = d
            best = min(best, d)
        column[s] = best
    nearest = np.empty(m)
    best_start, best_count, best_value = 0, steps, np.inf
    for start in range(steps):
        nearest[:] = np.inf
        total = np.inf  # sum of `nearest`, once finite
        path_sum = 0.0
        for count in range(1, steps + 1):
            s = (start + count - 1) % steps
            path_sum += column[s]
            if count == 1:
                total = 0.0
                for i in range(m):
                    nearest[i] = dist[s, i]
                    total += dist[s, i]
            else:
                for i in range(m):
                    d = dist[s, i]
                    if d < nearest[i]:
                        total -= nearest[i] - d
                        nearest[i] = d
            if count < min_count:
                continue
            value = total / m + path_sum / count
            if value < best_value or (value == best_value and count < best_count):
                best_start, best_count, best_value = start, count, value
    return best_start, best_count, best_value


# -- entry points ------------------------------------------------------------------------------


def solve_tangents(
    order: np.ndarray,
    fixed: np.ndarray,
    pos: np.ndarray,
    crank: np.ndarray,
    traj: np.ndarray,
    dtraj: np.ndarray,
    trans: np.ndarray,
    dtrans: np.ndarray,
    geometry: np.ndarray,
) -> tuple[int, int]:
    """Trajectories traj (n, steps, 2), per-dyad transmission sines trans (m, steps) and
    geometry (m, 3) of the positions `pos` (n, 2), and with dtraj (n, steps, 2, 2n) and dtrans
    (m, steps, 2n) their derivatives (zero-width last axes for values only): `_solve_tangents`.
    """
    check_buffer("pos", pos, (None, 2))
    n = pos.shape[0]
    check_solution_path(order, n, fixed)
    check_buffer("crank", crank, (None, 2))
    m, steps = order.shape[0], crank.shape[0]
    check_buffer("traj", traj, (n, steps, 2))
    cols = dtraj.shape[3] if isinstance(dtraj, np.ndarray) and dtraj.ndim == 4 else 0
    cols = cols if cols in (0, 2 * n) else 2 * n  # a width that is neither is refused below
    check_buffer("dtraj", dtraj, (n, steps, 2, cols))
    check_buffer("trans", trans, (m, steps))
    check_buffer("dtrans", dtrans, (m, steps, cols))
    check_buffer("geometry", geometry, (m, 3))
    return _solve_tangents(order, fixed, pos, crank, traj, dtraj, trans, dtrans, geometry)


def nearest_pairs(
    path: np.ndarray,
    target: np.ndarray,
    path_nn: np.ndarray,
    path_d: np.ndarray,
    target_nn: np.ndarray,
    target_d: np.ndarray,
) -> None:
    """For each point of `path` (P, 2) its nearest point of `target` (T, 2), into path_nn (P,)
    int64 and path_d (P,), and the other way into target_nn (T,) int64 and target_d (T,)."""
    check_buffer("path", path, (None, 2))
    check_buffer("target", target, (None, 2))
    points, targets = path.shape[0], target.shape[0]
    if points == 0 or targets == 0:
        raise ValueError(f"path and target must hold points, got {points} and {targets}")
    check_buffer("path_nn", path_nn, (points,), np.int64)
    check_buffer("path_d", path_d, (points,))
    check_buffer("target_nn", target_nn, (targets,), np.int64)
    check_buffer("target_d", target_d, (targets,))
    _nearest_pairs(path, target, path_nn, path_d, target_nn, target_d)


def best_interval(path: np.ndarray, stroke: np.ndarray, min_count: int) -> tuple[int, int, float]:
    """The run of consecutive points of `path` (S, 2), cyclic, whose chamfer to `stroke` (M, 2)
    is least: (start, count, chamfer) (`_best_interval`)."""
    check_buffer("path", path, (None, 2))
    check_buffer("stroke", stroke, (None, 2))
    if path.shape[0] == 0 or stroke.shape[0] == 0:
        raise ValueError(
            f"path and stroke must hold points, got {path.shape[0]} and {stroke.shape[0]}"
        )
    return _best_interval(path, stroke, min_count)
