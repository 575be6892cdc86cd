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
from links_ray.engine.kinematics.paths import _nearest_sq
from links_ray.engine.kinematics.solver import (
    _dyad_geometry,
    _place_crank,
    _place_fixed,
    dyad_fails,
)


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


#: fastmath flags of the stroke sums: reordered additions, so that they use vector lanes (the
#: rounding then differs from a running sum's in the last bits, the same for equal inputs on
#: one machine); no flag assumes finite values, as `nearest` starts infinite.
LANES = {"reassoc", "nsz", "arcp", "contract"}


@njit(cache=True, nogil=True, fastmath=LANES)
def _sum(row: np.ndarray) -> float:
    total = 0.0
    for i in range(row.shape[0]):
        total += row[i]
    return total


@njit(cache=True, nogil=True, fastmath=LANES)
def _sum_of_least(first: np.ndarray, second: np.ndarray) -> float:
    """The sum over i of the lesser of first[i] and second[i]."""
    total = 0.0
    for i in range(first.shape[0]):
        a, b = first[i], second[i]
        total += a if a < b else b
    return total


@njit(cache=True, nogil=True, fastmath=LANES)
def _lower_and_sum(nearest: np.ndarray, row: np.ndarray) -> float:
    """Lower `nearest` to `row` where it is larger, in place; the sum of the result."""
    total = 0.0
    for i in range(nearest.shape[0]):
        d = row[i]
        lowered = d if d < nearest[i] else nearest[i]
        nearest[i] = lowered
        total += lowered
    return total


@njit(cache=True, nogil=True)
def _lesser(first: np.ndarray, second: np.ndarray, out: np.ndarray) -> None:
    for i in range(out.shape[0]):
        out[i] = first[i] if first[i] < second[i] else second[i]


@njit(cache=True, nogil=True)
def _run_minima(
    dist: np.ndarray, prefix: np.ndarray, suffix: np.ndarray, middle: np.ndarray
) -> None:
    """Each stroke point's least distance over runs of path steps that end or start at an end of
    the path or at its middle (steps // 2): prefix[q] over steps 0..q, suffix[q] over q..last,
    middle[q] over q..middle-1 for q below the middle, middle..q from it."""
    steps = dist.shape[0]
    half = steps // 2
    prefix[0] = dist[0]
    for s in range(1, steps):
        _lesser(prefix[s - 1], dist[s], prefix[s])
    suffix[steps - 1] = dist[steps - 1]
    for s in range(steps - 2, -1, -1):
        _lesser(suffix[s + 1], dist[s], suffix[s])
    if half > 0:
        middle[half - 1] = dist[half - 1]
        for s in range(half - 2, -1, -1):
            _lesser(middle[s + 1], dist[s], middle[s])
    middle[half] = dist[half]
    for s in range(half + 1, steps):
        _lesser(middle[s - 1], dist[s], middle[s])


@njit(cache=True, nogil=True)
def _long_run_sum(
    prefix: np.ndarray, suffix: np.ndarray, middle: np.ndarray, start: int, count: int
) -> float:
    """The sum over the stroke of each point's least distance to the run (start, count) of at
    least half the path's steps (`_run_minima`'s tables): such a run, if it wraps, is a suffix
    and a prefix; if not, it starts at step 0, ends at the last step or holds the middle."""
    steps = prefix.shape[0]
    end = start + count
    if end > steps:
        return _sum_of_least(suffix[start], prefix[end - steps - 1])
    if start == 0:
        return _sum(prefix[end - 1])
    if end == steps:
        return _sum(suffix[start])
    return _sum_of_least(middle[start], middle[end - 1])


@njit(cache=True, nogil=True)
def _path_terms(
    column: np.ndarray,
    least: int,
    long_from: int,
    path_mean: np.ndarray,
    longer: np.ndarray,
    shorter: np.ndarray,
) -> np.ndarray:
    """Fill path_mean[start, count] (the run's path term: the mean of `column` over it),
    longer[start, count] (the least path term of the start's runs of long_from to count
    steps, at least `least`) and shorter[start, count] (the least of its runs of count to
    long_from - 1 steps, at least `least`); return each start's least path term of all."""
    steps = column.shape[0]
    running = np.empty(2 * steps + 1)  # sums of the path's nearest distances, twice round
    running[0] = 0.0
    for k in range(2 * steps):
        running[k + 1] = running[k] + column[k % steps]
    least_of_start = np.empty(steps)
    for start in range(steps):
        means = path_mean[start]
        for count in range(1, steps + 1):
            means[count] = (running[start + count] - running[start]) / count
        lowest = np.inf
        row = longer[start]
        row[:long_from] = np.inf
        for count in range(long_from, steps + 1):
            if count >= least and means[count] < lowest:
                lowest = means[count]
            row[count] = lowest
        lowest_short = np.inf
        row = shorter[start]
        row[long_from:] = np.inf
        for count in range(long_from - 1, -1, -1):
            if count >= least and means[count] < lowest_short:
                lowest_short = means[count]
            row[count] = lowest_short
        least_of_start[start] = min(lowest, lowest_short)
    return least_of_start


@njit(cache=True, nogil=True)
def _before(
    value: float, count: int, start: int, best_value: float, best_count: int, best_start: int
) -> bool:
    """Whether run (start, count) of chamfer `value` comes before the best so far: by chamfer,
    then the shorter run, then the lower start."""
    if value != best_value:
        return value < best_value
    return count < best_count or (count == best_count and start < best_start)


@njit(cache=True, nogil=True)
def _best_interval(path: np.ndarray, stroke: np.ndarray, min_count: int) -> tuple[int, int, float]:
    """The run of consecutive path points (cyclic) whose chamfer to `stroke` is least.

    Over every start and every count from `min_count` to all the points: (start, count,
    chamfer), least by chamfer, then the shortest run, then the lowest start. A run's chamfer is
    its stroke term (the mean over the stroke of each point's nearest run point) plus its path
    term (the mean over the run of each point's nearest stroke point).

    Exact, but it skips what cannot win. A run's stroke term only grows as it loses points,
    and no run's is below the whole path's. So each start's runs are taken longest first: the
    long ones (half the steps or more) from tables of least distances (`_run_minima`), each in
    one pass over the stroke, until the stroke term so far plus the least path term of the
    shorter ones passes the best so far; then the short ones, grown a point at a time, only
    while the stroke term of the shortest long run plus their least path term could still
    win. A stroke matched by most of a path visits a few runs per start, not every run.
    """
    steps = path.shape[0]
    m = stroke.shape[0]
    long_from = steps - steps // 2
    least = max(min_count, 1)
    # One block each (not one per table): the allocator then keeps reusing its pages.
    tables = np.empty((4, steps, m))
    dist, prefix, suffix, middle = tables[0], tables[1], tables[2], tables[3]
    column = np.empty(steps)  # nearest stroke distance of each path point
    xs = stroke[:, 0].copy()
    ys = stroke[:, 1].copy()
    for s in range(steps):
        px, py = path[s, 0], path[s, 1]
        row = dist[s]
        nearest = np.inf
        for i in range(m):
            dx = xs[i] - px
            dy = ys[i] - py
            d = np.sqrt(dx * dx + dy * dy)
            row[i] = d
            nearest = min(nearest, d)
        column[s] = nearest
    _run_minima(dist, prefix, suffix, middle)
    whole = _sum(suffix[0])  # the whole path's stroke term, times m: no run's is below it
    terms = np.empty((3, steps, steps + 1))
    path_mean, longer, shorter = terms[0], terms[1], terms[2]
    least_path = _path_terms(column, least, long_from, path_mean, longer, shorter)
    # Bounds are shaded down a little, so that no sum's rounding lets them cut a winner.
    shade = 1.0 - 1e-9
    nearest_run = np.empty(m)
    best_start, best_count, best_value = 0, steps, np.inf
    for start in np.argsort(least_path, kind="mergesort"):
        if (whole / m + least_path[start]) * shade > best_value:
            break  # and so does every later start
        below = whole  # the stroke term (times m) of the start's runs taken so far
        cut = False
        for count in range(steps, long_from - 1, -1):
            if (below / m + longer[start, count]) * shade > best_value:
                cut = count > long_from
                break
            total = whole if count == steps else _long_run_sum(prefix, suffix, middle, start, count)
            below = total
            if count >= least:
                value = total / m + path_mean[start, count]
                if _before(value, count, start, best_value, best_count, best_start):
                    best_start, best_count, best_value = start, count, value
        if long_from <= least:
            continue
        if cut:  # the short runs' stroke terms are at least the shortest long run's
            below = _long_run_sum(prefix, suffix, middle, start, long_from)
        nearest_run[:] = np.inf
        for count in range(1, long_from):
            if (below / m + shorter[start, count]) * shade > best_value:
                break
            total = _lower_and_sum(nearest_run, dist[(start + count - 1) % steps])
            if count < least:
                continue
            value = total / m + path_mean[start, count]
            if _before(value, count, start, best_value, best_count, best_start):
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
