"""Whether a mechanism that assembles at every sampled crank angle also assembles between them.

A dyad (joint j on parents a and b, radii r1 and r2) assembles while its parents' distance d
stays in [|r1 - r2|, r1 + r2]. Its slack, g = min(r1 + r2 - d, d - |r1 - r2|), changes no
faster than d, and d no faster than the vector b - a: over a crank interval, g can fall by at
most the length L of the path that b - a draws across it. So if g at the interval's two ends
adds up to more than L, g stays positive in between: g(t) >= max(g0 - L(t), g1 - (L - L(t)))
>= (g0 + g1 - L) / 2 > 0.

A dyad whose parents are one rigid body (one is the other's parent, say, or both are joints of
a triangle of links) keeps d fixed: assembled once, it assembles everywhere, and is not
checked. It is recognised by d varying less than `RIGID_TOLERANCE` (relative) over the sampled
steps: rounding moves a rigid body's distances by about 1e-15, and a distance that moves
does so far more than 1e-9 somewhere among 200 samples of a smooth turn.

A path's length over a short interval is its chord unless it turns sharply inside it, which
happens only near a dead centre of some dyad up the chain, where that dyad's own slack is
small and its interval is split anyway. The check asks `ARC_FACTOR` times the chord, splits an
interval that fails into `SPLIT` parts (solved at the crank angles in between, on the same
frozen branches) and checks those in turn. An interval still unsure after `MAX_DEPTH` splits
(SPLIT ** MAX_DEPTH times finer than the sampled steps) counts as a lock: a dead centre touched.
So does a turn that needs more than `MAX_SPLITS` splits in all to prove: a dyad that grazes
its dead centre along a stretch of the turn, its slack never quite zero, leaves nearly every
part of every interval there unsure down to the last depth, and proving that it turns could
take far longer than the rest of a synthesis (docs/benchmarks.md, The check between steps).
The budget keeps every check to milliseconds; what it refuses turns, if at all, by a hair.

Most intervals of most mechanisms pass at once. The first pass goes dyad by dyad over the
sampled turn (`_unsure_intervals`), each parents' distance measured once per step; only the
intervals it leaves unsure are split, and each split keeps the poses at its ends for its
parts. On valid 8-20 joint mechanisms the check costs two to three simulations of the turn.

Pure numpy/numba: no Ray.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from links_ray.engine.buffers import check_buffer, check_solution_path

#: The parents' path length over an interval is taken as at most this times their chord.
ARC_FACTOR = 2.0
#: Parts an unsure interval is split into, and how many times it may be split.
SPLIT, MAX_DEPTH = 8, 6
#: The splits one check may make over the whole turn before it counts the turn as locking.
MAX_SPLITS = 4096
#: A dyad whose parents' distance varies less than this (relative) over the turn is rigid.
RIGID_TOLERANCE = 1e-9


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _distance(dx: float, dy: float) -> float:
    """The length of (dx, dy). Not `hypot`, several times slower: coordinates stay within
    MAX_COORDINATE (engine.inputs), so the squares neither overflow nor underflow."""
    return np.sqrt(dx * dx + dy * dy)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _slack(d: float, r1: float, r2: float) -> float:
    """How far the parents' distance d is inside [|r1 - r2|, r1 + r2] (negative outside)."""
    if d == 0.0:
        return -1.0
    return min(r1 + r2 - d, d - abs(r1 - r2))


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _moved(start: np.ndarray, end: np.ndarray, a: int, b: int) -> float:
    """How far the vector from joint a to joint b moves from pose `start` to pose `end`."""
    return _distance(
        (end[b, 0] - end[a, 0]) - (start[b, 0] - start[a, 0]),
        (end[b, 1] - end[a, 1]) - (start[b, 1] - start[a, 1]),
    )


@njit(cache=True, nogil=True, error_model="numpy")
def _pose_at(
    order: np.ndarray, pos: np.ndarray, geometry: np.ndarray, angle: float, out: np.ndarray
) -> int:
    """Every joint at crank `angle` into `out` (n, 2), on the branches of `geometry`; returns
    the solution-path index of the first dyad that cannot be assembled, else -1."""
    out[:] = pos
    c, s = np.cos(angle), np.sin(angle)
    vx, vy = pos[1, 0] - pos[0, 0], pos[1, 1] - pos[0, 1]
    out[1, 0] = pos[0, 0] + c * vx - s * vy
    out[1, 1] = pos[0, 1] + s * vx + c * vy
    for k in range(order.shape[0]):
        j, a, b = order[k, 0], order[k, 1], order[k, 2]
        r1, r2, side = geometry[k, 0], geometry[k, 1], geometry[k, 2]
        ax, ay = out[a, 0], out[a, 1]
        dx, dy = out[b, 0] - ax, out[b, 1] - ay
        d_sq = dx * dx + dy * dy
        if _slack(np.sqrt(d_sq), r1, r2) < 0.0:
            return k
        inv_d_sq = 1.0 / d_sq
        along = 0.5 * (d_sq + r1 * r1 - r2 * r2) * inv_d_sq
        height = side * np.sqrt(max(r1 * r1 * inv_d_sq - along * along, 0.0))
        out[j, 0] = ax + along * dx - height * dy
        out[j, 1] = ay + along * dy + height * dx
    return -1


@njit(cache=True, nogil=True, error_model="numpy")
def _rigid_dyads(order: np.ndarray, traj: np.ndarray) -> np.ndarray:
    """(m,) bool: dyads whose parents keep their distance over the sampled turn `traj`
    (n, steps, 2) to within `RIGID_TOLERANCE` of it: parts of one rigid body."""
    rigid = np.empty(order.shape[0], dtype=np.bool_)
    for k in range(order.shape[0]):
        a, b = order[k, 1], order[k, 2]
        low, high = np.inf, 0.0
        for t in range(traj.shape[1]):
            dx = traj[b, t, 0] - traj[a, t, 0]
            dy = traj[b, t, 1] - traj[a, t, 1]
            d = np.sqrt(dx * dx + dy * dy)
            low = min(low, d)
            high = max(high, d)
        rigid[k] = high - low <= RIGID_TOLERANCE * high
    return rigid


@njit(cache=True, nogil=True, error_model="numpy")
def _unsure_dyad(
    order: np.ndarray,
    geometry: np.ndarray,
    rigid: np.ndarray,
    start: np.ndarray,
    end: np.ndarray,
) -> int:
    """The first dyad (solution-path index) whose slack at poses `start` and `end` (n, 2)
    does not prove it assembles in between, else -1."""
    for k in range(order.shape[0]):
        if rigid[k]:
            continue
        a, b = order[k, 1], order[k, 2]
        r1, r2 = geometry[k, 0], geometry[k, 1]
        g0 = _slack(_distance(start[b, 0] - start[a, 0], start[b, 1] - start[a, 1]), r1, r2)
        g1 = _slack(_distance(end[b, 0] - end[a, 0], end[b, 1] - end[a, 1]), r1, r2)
        # How far b - a moved: d changes by no more.
        if not g0 + g1 > ARC_FACTOR * _moved(start, end, a, b):
            return k
    return -1


@njit(cache=True, nogil=True, error_model="numpy")
def _unsure_intervals(
    order: np.ndarray, geometry: np.ndarray, traj: np.ndarray, rigid: np.ndarray
) -> np.ndarray:
    """(steps,) bool: the sampled intervals (t, t + 1) of `traj` (n, steps, 2), the last
    wrapping to step 0, where `_unsure_dyad` finds a dyad unsure; fills `rigid` (m,) as
    `_rigid_dyads` does.

    Dyad by dyad, so each parents' distance is measured once per step rather than at both
    ends of two intervals; the numbers compared are `_unsure_dyad`'s.
    """
    steps = traj.shape[1]
    unsure = np.zeros(steps, dtype=np.bool_)
    slack = np.empty(steps)
    for k in range(order.shape[0]):
        a, b = order[k, 1], order[k, 2]
        r1, r2 = geometry[k, 0], geometry[k, 1]
        low, high = np.inf, 0.0
        for t in range(steps):
            d = _distance(traj[b, t, 0] - traj[a, t, 0], traj[b, t, 1] - traj[a, t, 1])
            low = min(low, d)
            high = max(high, d)
            slack[t] = _slack(d, r1, r2)
        rigid[k] = high - low <= RIGID_TOLERANCE * high
        if rigid[k]:
            continue
        for t in range(steps):
            u = t + 1 if t + 1 < steps else 0
            moved = _distance(
                (traj[b, u, 0] - traj[a, u, 0]) - (traj[b, t, 0] - traj[a, t, 0]),
                (traj[b, u, 1] - traj[a, u, 1]) - (traj[b, t, 1] - traj[a, t, 1]),
            )
            if not slack[t] + slack[u] > ARC_FACTOR * moved:
                unsure[t] = True
    return unsure


@njit(cache=True, nogil=True, error_model="numpy")
def _interval_lock(
    order: np.ndarray,
    pos: np.ndarray,
    geometry: np.ndarray,
    rigid: np.ndarray,
    lo: float,
    hi: float,
    start: np.ndarray,
    end: np.ndarray,
    ends: np.ndarray,
    splits_left: np.ndarray,
) -> int:
    """The dyad that locks (or may) somewhere in crank angles (lo, hi), whose poses are
    `start` and `end`; -1 when it certainly turns through. Splits depth first, in angle order,
    so the lock reported is the earliest. `ends` is scratch (MAX_DEPTH * SPLIT + 1, 2, n, 2):
    each waiting interval keeps the poses at its ends, solved when it was split off.
    `splits_left` (1,) is the turn's budget of splits, spent here: an unsure interval with
    none left counts as a lock."""
    n = pos.shape[0]
    stack_size = MAX_DEPTH * SPLIT + 1
    lows = np.empty(stack_size)
    highs = np.empty(stack_size)
    depths = np.empty(stack_size, dtype=np.int64)
    dyads = np.empty(stack_size, dtype=np.int64)  # the unsure dyad of each waiting interval
    poses = np.empty((SPLIT + 1, n, 2))
    k = _unsure_dyad(order, geometry, rigid, start, end)
    if k < 0:
        return -1
    lows[0], highs[0], depths[0], dyads[0] = lo, hi, 0, k
    ends[0, 0] = start
    ends[0, 1] = end
    top = 1
    while top > 0:
        top -= 1
        lo, hi, depth = lows[top], highs[top], depths[top]
        if depth == MAX_DEPTH or splits_left[0] <= 0:
            return dyads[top]
        splits_left[0] -= 1
        poses[0] = ends[top, 0]
        poses[SPLIT] = ends[top, 1]
        for s in range(1, SPLIT):
            failed = _pose_at(order, pos, geometry, lo + (hi - lo) * s / SPLIT, poses[s])
            if failed >= 0:
                return failed
        # Only the unsure parts go on the stack, the latest first so the earliest comes out.
        for s in range(SPLIT - 1, -1, -1):
            k = _unsure_dyad(order, geometry, rigid, poses[s], poses[s + 1])
            if k >= 0:
                lows[top] = lo + (hi - lo) * s / SPLIT
                highs[top] = lo + (hi - lo) * (s + 1) / SPLIT
                depths[top] = depth + 1
                dyads[top] = k
                ends[top, 0] = poses[s]
                ends[top, 1] = poses[s + 1]
                top += 1
    return -1


@njit(cache=True, nogil=True, error_model="numpy")
def _turn_lock(
    order: np.ndarray,
    pos: np.ndarray,
    geometry: np.ndarray,
    traj: np.ndarray,
    max_splits: int = MAX_SPLITS,
) -> tuple[int, int]:
    """(step, joint) of the first lock between the sampled steps of `traj` (n, steps, 2), a
    turn that assembles at every one of them, else (-1, -1). A lock between steps t - 1 and t
    is reported at step t (the first the crank cannot reach); after the last step, at `steps`.
    A turn not proven within `max_splits` splits counts as locking where the budget ran out.
    """
    n, steps = traj.shape[0], traj.shape[1]
    rigid = np.empty(order.shape[0], dtype=np.bool_)
    unsure = _unsure_intervals(order, geometry, traj, rigid)
    start = np.empty((n, 2))
    end = np.empty((n, 2))
    ends = np.empty((0, 2, n, 2))  # scratch of `_interval_lock`, made when first needed
    splits_left = np.array([max_splits], dtype=np.int64)
    step_angle = 2.0 * np.pi / steps
    for t in range(steps):
        if not unsure[t]:
            continue
        if ends.shape[0] == 0:
            ends = np.empty((MAX_DEPTH * SPLIT + 1, 2, n, 2))
        start[:] = traj[:, t]
        end[:] = traj[:, t + 1] if t + 1 < steps else traj[:, 0]
        lo, hi = t * step_angle, (t + 1) * step_angle
        k = _interval_lock(order, pos, geometry, rigid, lo, hi, start, end, ends, splits_left)
        if k >= 0:
            return t + 1, order[k, 0]
    return -1, -1


# -- entry points, called from Python with the caller's buffers: numba checks no bounds, so
# each checks their shapes first (`buffers.check_buffer`).


def turn_lock(
    order: np.ndarray,
    pos: np.ndarray,
    geometry: np.ndarray,
    traj: np.ndarray,
    max_splits: int = MAX_SPLITS,
) -> tuple[int, int]:
    """(step, joint) of the first lock between the sampled steps of `traj` (n, steps, 2), a
    turn of the positions `pos` (n, 2) on the branches of `geometry` (m, 3) that assembles at
    every sampled step, else (-1, -1) (`_turn_lock` says how it is reported)."""
    check_buffer("pos", pos, (None, 2))
    n = pos.shape[0]
    check_solution_path(order, n)
    check_buffer("geometry", geometry, (order.shape[0], 3))
    check_buffer("traj", traj, (n, None, 2))
    if traj.shape[1] == 0:
        raise ValueError(f"traj must hold at least one step, got shape {traj.shape}")
    return _turn_lock(order, pos, geometry, traj, max_splits)


def rigid_dyads(order: np.ndarray, traj: np.ndarray) -> np.ndarray:
    """(m,) bool: the dyads of `order` whose parents keep their distance over the sampled turn
    `traj` (n, steps, 2) (`_rigid_dyads`)."""
    check_buffer("traj", traj, (None, None, 2))
    check_solution_path(order, traj.shape[0], positions="traj")
    return _rigid_dyads(order, traj)
