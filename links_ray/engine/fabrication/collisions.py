"""Which links of a mechanism built as bars come within a clearance of each other, or of a pin,
at any crank angle of a full turn.

Bodies. A link is a bar of width W around the segment between its two joints, its ends rounded
(a stadium: every point within W / 2 of the segment); a pin is a disc of diameter D at a joint.
Every link of the adjacency matrix is one bar. Two links' bodies come within the clearance C of
each other where their segments are closer than W + C; a link's body comes within C of a pin
where its segment is closer than W / 2 + D / 2 + C to the pin's joint (the pins of the link's
own joints are its own). Links that share a joint always meet at its pin: they conflict, at
distance 0, and no geometry is computed for them. Each pair's threshold is its distance limit.

At the steps. The mechanism is simulated at S crank steps (`solver.simulate`, which proves it turns
between them, `engine.kinematics.turning`); each pair's distance is measured at every step. A pair
closer than its threshold at a step conflicts: that is a pose of the mechanism.

Between the steps, from the dyad geometry. Over an interval of crank angles (θ0, θ1), h wide,
every two joints x and y get a bound on their relative speed |v_x - v_y| (v = dp/dθ) and one
on their relative acceleration |a_x - a_y| (a = d2p/dθ2), found in solution order. Fixed
joints are still; the crank's tip turns about joint 0 at one radian per radian, so its speed
and its acceleration are its radius R. A dyad's joint j on parents a and b (radii r1, r2)
keeps u = p_j - p_a and w = p_j - p_b at their lengths: u . (v_j - v_a) = 0 and
w . (v_j - v_a) = w . (v_b - v_a), so |v_j - v_a| <= |v_b - v_a| / |sin g| (and so for
|v_j - v_b|), g the angle between u and w (d^2 = r1^2 + r2^2 - 2 r1 r2 cos g, d the parents'
distance). Differentiated once more, u . (a_j - a_a) = -|v_j - v_a|^2 and
w . (a_j - a_a) = w . (a_b - a_a) - |v_j - v_b|^2, so |a_j - a_a| <= (|v_j - v_a|^2 / r1 +
|v_j - v_b|^2 / r2 + |a_b - a_a|) / |sin g|. d moves no faster than |v_b - v_a|, so over the
interval it stays within (d(θ0) + d(θ1) -+ h |v_b - v_a|) / 2; where that range lies strictly
inside (|r1 - r2|, r1 + r2) the dyad assembles throughout and |sin g| is least at one of the
range's ends; where it reaches a dead centre the bounds are inf. Parents that keep their
distance (joined by a link, or both fixed) make a rigid triangle with j: d stays at its
values at the ends, and j's motion relative to a is the triangle's turning, at most r1 times
its angular speed |v_b - v_a| / d (and r1 (|a_b - a_a| / d + 2 (|v_b - v_a| / d)^2) for the
acceleration). The triangle inequality carries each bound from a and b to every joint known
before j. Last, the joints' velocities at the interval's two ends are solved exactly (the
same relations, at the two poses), and a relative speed changes no faster than the relative
acceleration: |v_x - v_y| <= (c0 + c1 + A h) / 2 throughout, c0 and c1 the exact relative
speeds at the ends and A the acceleration bound. That bound (taken where it is the smaller)
feeds the dyads solved after, and as intervals shrink it tends to the true relative speed.

A pair's distance f changes no faster than the fastest relative speed between an end of one
segment and an end of the other (a pin is a segment whose two ends are its joint): every
point of a segment is a mean of its ends, so every difference of two points is a mean of the
four differences of ends. With K that rate, f >= max(f(θ0) - K (θ - θ0), f(θ1) - K (θ1 - θ))
>= (f(θ0) + f(θ1) - K h) / 2 throughout. Where that bound reaches the threshold, the pair is
proven clear on the interval. Where it does not, the interval is split in `SPLIT`, the poses
at the angles in between solved (`turning._pose_at`, on the solver's frozen branches), and
each part measured and bounded again, with its own bounds.

What is proved. A pair reported clear keeps at least its threshold at every crank angle of
the turn, up to the floating-point rounding of the poses: no safety factor, no assumption but
that the mechanism turns on its branches, which `solver.simulate` proves first. A pair
reported conflicting either came closer than its threshold at a solved pose, or was neither
so found nor proven clear before its interval was `MAX_DEPTH` splits deep (SPLIT ** MAX_DEPTH
times finer than the steps), it had taken part in `MAX_PAIR_SPLITS` splits, or the check's
`MAX_SPLITS` were spent. Those are marked unresolved and count as conflicts, so a plan never
rests on a clearance not proven. A pair whose least distance lies within a hair of its
threshold, or a dyad that passes within a degree or so of its dead centre, is where that
happens.

Pure numpy/numba: no Ray.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import ArrayLike

from links_ray.engine.fabrication.limits import (
    DEFAULT_COLLISION_STEPS,
    MAX_LAYERED_JOINTS,
    as_bar_sizes,
)
from links_ray.engine.inputs import InvalidMechanismError
from links_ray.engine.kinematics.solver import (
    _dyad_geometry,
    checked_input,
    simulate,
    topology_cache,
)
from links_ray.engine.kinematics.turning import _pose_at
from links_ray.engine.node_kinds import FIXED

__all__ = ["MAX_DEPTH", "MAX_PAIR_SPLITS", "MAX_SPLITS", "SPLIT", "Collisions", "find_collisions"]

#: Parts an unproven interval is split into, and how many times it may be split.
SPLIT, MAX_DEPTH = 4, 10
#: The splits one pair may take part in over the whole turn before it counts as a conflict
#: (unresolved): a pair that cannot be decided does not hold up the others.
MAX_PAIR_SPLITS = 1 << 16
#: The splits one check may make over the whole turn, all pairs together, before the pairs
#: still unproven count as conflicts (unresolved): the check's time is bounded.
MAX_SPLITS = 1 << 18


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _point_segment_sq(px: float, py: float, ax: float, ay: float, bx: float, by: float) -> float:
    """The squared distance from point p to segment ab (a point where a = b)."""
    dx, dy = bx - ax, by - ay
    length_sq = dx * dx + dy * dy
    along = 0.0
    if length_sq > 0.0:
        along = min(max(((px - ax) * dx + (py - ay) * dy) / length_sq, 0.0), 1.0)
    ex, ey = ax + along * dx - px, ay + along * dy - py
    return ex * ex + ey * ey


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _segment_distance(pose: np.ndarray, a: int, b: int, c: int, d: int) -> float:
    """The least distance between segments ab and cd of joints at `pose` (n, 2); c = d makes
    cd a point. 0 where they cross; otherwise the least is at an end of one of them."""
    ax, ay, bx, by = pose[a, 0], pose[a, 1], pose[b, 0], pose[b, 1]
    cx, cy, dx, dy = pose[c, 0], pose[c, 1], pose[d, 0], pose[d, 1]
    # Sides of each segment's ends about the other's line: opposite on both means they cross.
    side_c = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
    side_d = (bx - ax) * (dy - ay) - (by - ay) * (dx - ax)
    side_a = (dx - cx) * (ay - cy) - (dy - cy) * (ax - cx)
    side_b = (dx - cx) * (by - cy) - (dy - cy) * (bx - cx)
    if side_c * side_d < 0.0 and side_a * side_b < 0.0:
        return 0.0
    least = min(
        min(_point_segment_sq(ax, ay, cx, cy, dx, dy), _point_segment_sq(bx, by, cx, cy, dx, dy)),
        min(_point_segment_sq(cx, cy, ax, ay, bx, by), _point_segment_sq(dx, dy, ax, ay, bx, by)),
    )
    return np.sqrt(least)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _least_sine(d_low: float, d_high: float, r1: float, r2: float) -> float:
    """The least |sin g| of a dyad (radii r1, r2) whose parents' distance stays within
    [d_low, d_high], g the angle at its joint; 0 if the range reaches a dead centre."""
    if not (d_low > abs(r1 - r2) and d_high < r1 + r2):
        return 0.0
    twice = 2.0 * r1 * r2
    # cos g falls as d grows: |cos g| is greatest at an end of the range.
    cos_low = (r1 * r1 + r2 * r2 - d_low * d_low) / twice
    cos_high = (r1 * r1 + r2 * r2 - d_high * d_high) / twice
    cosine = max(abs(cos_low), abs(cos_high))
    return np.sqrt(max(1.0 - cosine * cosine, 0.0))


@njit(cache=True, nogil=True, error_model="numpy")
def _velocities(order: np.ndarray, pose: np.ndarray, velocity: np.ndarray) -> None:
    """velocity (n, 2) = every joint's dp/dθ at `pose` (n, 2): the crank's tip turning about
    joint 0, fixed joints still, and each dyad's joint from its parents' (u . v_j = u . v_a,
    w . v_j = w . v_b, solved)."""
    velocity[:] = 0.0
    velocity[1, 0] = -(pose[1, 1] - pose[0, 1])
    velocity[1, 1] = pose[1, 0] - pose[0, 0]
    for k in range(order.shape[0]):
        j, a, b = order[k, 0], order[k, 1], order[k, 2]
        ux, uy = pose[j, 0] - pose[a, 0], pose[j, 1] - pose[a, 1]
        wx, wy = pose[j, 0] - pose[b, 0], pose[j, 1] - pose[b, 1]
        along_u = ux * velocity[a, 0] + uy * velocity[a, 1]
        along_w = wx * velocity[b, 0] + wy * velocity[b, 1]
        det = ux * wy - uy * wx
        velocity[j, 0] = (wy * along_u - uy * along_w) / det
        velocity[j, 1] = (ux * along_w - wx * along_u) / det


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _gap(velocity: np.ndarray, x: int, y: int) -> float:
    """|v_x - v_y| of `velocity` (n, 2)."""
    dx, dy = velocity[x, 0] - velocity[y, 0], velocity[x, 1] - velocity[y, 1]
    return np.sqrt(dx * dx + dy * dy)


@njit(cache=True, nogil=True, error_model="numpy")
def _relative_speeds(
    order: np.ndarray,
    geometry: np.ndarray,
    fixed_distance: np.ndarray,
    still: np.ndarray,
    crank_radius: float,
    start: np.ndarray,
    end: np.ndarray,
    v_start: np.ndarray,
    v_end: np.ndarray,
    span: float,
    relative: np.ndarray,
    accel: np.ndarray,
) -> None:
    """relative (n, n) = a bound on |v_x - v_y| (v = dp/dθ), and accel (n, n) one on
    |a_x - a_y| (a = d2p/dθ2), for every two joints over crank angles `span` wide whose end
    poses are `start` and `end` (n, 2), their velocities `v_start` and `v_end`
    (`_velocities`); as the module's docstring derives them, inf where a dyad on the way may
    pass a dead centre there. `still` holds the fixed joints; `fixed_distance` (m,) marks
    the dyads whose parents keep their distance."""
    relative[:] = np.inf
    accel[:] = np.inf
    known = np.empty(relative.shape[0], dtype=np.int64)
    count = 0
    for f in range(still.shape[0]):
        known[count] = still[f]
        count += 1
    known[count] = 1
    count += 1
    for p in range(count):
        for q in range(count):
            relative[known[p], known[q]] = accel[known[p], known[q]] = 0.0
    for f in range(still.shape[0]):
        # The tip turns at one radian per radian: its speed and its acceleration are R.
        relative[1, still[f]] = relative[still[f], 1] = crank_radius
        accel[1, still[f]] = accel[still[f], 1] = crank_radius
    for k in range(order.shape[0]):
        j, a, b = order[k, 0], order[k, 1], order[k, 2]
        r1, r2 = geometry[k, 0], geometry[k, 1]
        parents, parents_accel = relative[a, b], accel[a, b]
        d0 = np.sqrt((start[b, 0] - start[a, 0]) ** 2 + (start[b, 1] - start[a, 1]) ** 2)
        d1 = np.sqrt((end[b, 0] - end[a, 0]) ** 2 + (end[b, 1] - end[a, 1]) ** 2)
        if fixed_distance[k]:
            d_low, d_high = min(d0, d1), max(d0, d1)
        else:
            drift = parents * span
            d_low, d_high = 0.5 * (d0 + d1 - drift), 0.5 * (d0 + d1 + drift)
        sine = _least_sine(d_low, d_high, r1, r2)
        # |v_j - v_a| and |v_j - v_b|, then |a_j - a_a| and |a_j - a_b|, at most.
        from_a = from_b = np.inf
        accel_a = accel_b = np.inf
        if sine > 0.0:
            from_a = from_b = parents / sine
            accel_a = accel_b = (from_a * from_a / r1 + from_b * from_b / r2 + parents_accel) / sine
        if fixed_distance[k] and d_low > 0.0:
            turn = parents / d_low  # the rigid triangle's angular speed, at most
            spin = parents_accel / d_low + turn * turn  # its angular acceleration, at most
            from_a, from_b = min(from_a, r1 * turn), min(from_b, r2 * turn)
            accel_a = min(accel_a, r1 * (spin + turn * turn))
            accel_b = min(accel_b, r2 * (spin + turn * turn))
        for p in range(count):
            y = known[p]
            speed = min(relative[a, y] + from_a, relative[b, y] + from_b)
            change = min(accel[a, y] + accel_a, accel[b, y] + accel_b)
            # Exact at both ends, changing at most `change` per radian in between.
            ends = 0.5 * (_gap(v_start, j, y) + _gap(v_end, j, y) + change * span)
            relative[j, y] = relative[y, j] = min(speed, ends)
            accel[j, y] = accel[y, j] = change
        relative[j, j] = accel[j, j] = 0.0
        known[count] = j
        count += 1


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _interval_bound(
    relative: np.ndarray, items: np.ndarray, i: int, f0: float, f1: float, span: float
) -> float:
    """The least pair i of `items` can be apart over an interval `span` wide whose ends find
    it f0 and f1 apart, its joints' relative speeds at most `relative` (n, n) there."""
    a, b, c, d = items[i, 0], items[i, 1], items[i, 2], items[i, 3]
    rate = max(max(relative[a, c], relative[a, d]), max(relative[b, c], relative[b, d]))
    return 0.5 * (f0 + f1 - rate * span)


@njit(cache=True, nogil=True, error_model="numpy")
def _refine_interval(
    order: np.ndarray,
    pos: np.ndarray,
    geometry: np.ndarray,
    fixed_distance: np.ndarray,
    still: np.ndarray,
    crank_radius: float,
    items: np.ndarray,
    thresholds: np.ndarray,
    lo: float,
    hi: float,
    start: np.ndarray,
    end: np.ndarray,
    pending: np.ndarray,
    least: np.ndarray,
    conflict: np.ndarray,
    unresolved: np.ndarray,
    spent: np.ndarray,
    splits_left: np.ndarray,
) -> None:
    """Decide the pairs `pending` (indices into `items`) on crank angles (lo, hi), whose poses
    are `start` and `end` (n, 2): split, depth first, until each is found within its threshold
    at a solved pose (`conflict`) or proven clear on every part, updating `least`. A pair
    still unproven at `MAX_DEPTH`, past `MAX_PAIR_SPLITS` splits of its own (`spent` (p,)
    counts them) or when `splits_left` (1,) runs out, is marked conflicting and
    `unresolved`.

    Each waiting part keeps the poses at its ends and its list of pairs; the lists sit in one
    buffer in the order the parts were pushed, so the part popped owns the topmost list."""
    n, m = pos.shape[0], pending.shape[0]
    stack_size = MAX_DEPTH * SPLIT + 1
    lows = np.empty(stack_size)
    highs = np.empty(stack_size)
    depths = np.empty(stack_size, dtype=np.int64)
    firsts = np.empty(stack_size, dtype=np.int64)
    counts = np.empty(stack_size, dtype=np.int64)
    ends = np.empty((stack_size, 2, n, 2))
    # Every waiting list, and the children a popped part writes above its own before they
    # are moved down over it.
    queue = np.empty((stack_size + SPLIT + 1) * m, dtype=np.int64)
    poses = np.empty((SPLIT + 1, n, 2))
    velocities = np.empty((SPLIT + 1, n, 2))
    relatives = np.empty((SPLIT, n, n))
    accel = np.empty((n, n))
    apart = np.empty((m, SPLIT + 1))
    lows[0], highs[0], depths[0], firsts[0], counts[0] = lo, hi, 0, 0, m
    queue[:m] = pending
    ends[0, 0] = start
    ends[0, 1] = end
    top = 1
    while top > 0:
        top -= 1
        lo, hi, depth = lows[top], highs[top], depths[top]
        first, count = firsts[top], counts[top]
        poses[0] = ends[top, 0]
        poses[SPLIT] = ends[top, 1]
        solved = depth < MAX_DEPTH and splits_left[0] > 0
        if solved:
            splits_left[0] -= 1
            for s in range(1, SPLIT):
                if _pose_at(order, pos, geometry, lo + (hi - lo) * s / SPLIT, poses[s]) >= 0:
                    # The turn was proven to assemble here; rounding says otherwise.
                    solved = False
                    break
        if not solved:
            for q in range(count):
                i = queue[first + q]
                if not conflict[i]:
                    conflict[i] = True
                    unresolved[i] = True
            continue
        width = (hi - lo) / SPLIT
        for s in range(SPLIT + 1):
            _velocities(order, poses[s], velocities[s])
        for s in range(SPLIT):
            _relative_speeds(
                order,
                geometry,
                fixed_distance,
                still,
                crank_radius,
                poses[s],
                poses[s + 1],
                velocities[s],
                velocities[s + 1],
                width,
                relatives[s],
                accel,
            )
        # Measure the live pairs at every pose; keep those found nowhere within, compacted.
        live = 0
        for q in range(count):
            i = queue[first + q]
            if conflict[i]:
                continue  # found within, or given up, at another part meanwhile
            spent[i] += 1
            if spent[i] > MAX_PAIR_SPLITS:
                conflict[i] = True
                unresolved[i] = True
                continue
            a, b, c, d = items[i, 0], items[i, 1], items[i, 2], items[i, 3]
            within = False
            for s in range(SPLIT + 1):
                f = _segment_distance(poses[s], a, b, c, d)
                apart[live, s] = f
                least[i] = min(least[i], f)
                within |= f < thresholds[i]
            if within:
                conflict[i] = True
                continue
            queue[first + live] = i
            live += 1
        # Each part's unproven pairs, written above the live list, the last part first so the
        # first is popped first.
        written = first + live
        for s in range(SPLIT - 1, -1, -1):
            child = written
            for q in range(live):
                i = queue[first + q]
                bound = _interval_bound(relatives[s], items, i, apart[q, s], apart[q, s + 1], width)
                if not bound >= thresholds[i]:
                    queue[written] = i
                    written += 1
            if written > child:
                lows[top], highs[top] = lo + width * s, lo + width * (s + 1)
                depths[top] = depth + 1
                firsts[top], counts[top] = child - live, written - child
                ends[top, 0] = poses[s]
                ends[top, 1] = poses[s + 1]
                top += 1
        # The parent's list is done with: its children's lists take its place.
        for q in range(first + live, written):
            queue[q - live] = queue[q]


@njit(cache=True, nogil=True, error_model="numpy")
def _clearances(
    order: np.ndarray,
    pos: np.ndarray,
    geometry: np.ndarray,
    fixed_distance: np.ndarray,
    still: np.ndarray,
    traj: np.ndarray,
    items: np.ndarray,
    thresholds: np.ndarray,
    least: np.ndarray,
    conflict: np.ndarray,
    unresolved: np.ndarray,
    max_splits: int,
) -> int:
    """For each pair of `items` (p, 4) (joints a, b of one segment and c, d of the other; c = d
    for a pin), over the sampled turn `traj` (n, steps, 2) and between its steps: `least` (p,)
    = its least distance at the poses examined, `conflict` (p,) = whether it comes closer than
    its threshold (`thresholds` (p,)) at some crank angle, or is `unresolved` (p,) (the
    module's docstring). Returns the splits made."""
    n, steps = traj.shape[0], traj.shape[1]
    count = items.shape[0]
    least[:] = np.inf
    unresolved[:] = False
    pose = np.empty((n, 2))
    # The steps first: a pair found within at any step needs no proof between them.
    for t in range(steps):
        pose[:] = traj[:, t]
        for i in range(count):
            f = _segment_distance(pose, items[i, 0], items[i, 1], items[i, 2], items[i, 3])
            least[i] = min(least[i], f)
    for i in range(count):
        conflict[i] = least[i] < thresholds[i]
    crank_radius = np.sqrt((pos[1, 0] - pos[0, 0]) ** 2 + (pos[1, 1] - pos[0, 1]) ** 2)
    span = 2.0 * np.pi / steps
    start = np.empty((n, 2))
    end = np.empty((n, 2))
    v_start = np.empty((n, 2))
    v_end = np.empty((n, 2))
    relative = np.empty((n, n))
    accel = np.empty((n, n))
    f_start = np.empty(count)
    f_end = np.empty(count)
    pending = np.empty(count, dtype=np.int64)
    spent = np.zeros(count, dtype=np.int64)
    splits_left = np.array([max_splits], dtype=np.int64)
    start[:] = traj[:, 0]
    _velocities(order, start, v_start)
    for i in range(count):
        f_start[i] = _segment_distance(start, items[i, 0], items[i, 1], items[i, 2], items[i, 3])
    for t in range(steps):
        end[:] = traj[:, t + 1] if t + 1 < steps else traj[:, 0]
        for i in range(count):
            f_end[i] = _segment_distance(end, items[i, 0], items[i, 1], items[i, 2], items[i, 3])
        _velocities(order, end, v_end)
        _relative_speeds(
            order,
            geometry,
            fixed_distance,
            still,
            crank_radius,
            start,
            end,
            v_start,
            v_end,
            span,
            relative,
            accel,
        )
        unsure = 0
        for i in range(count):
            if conflict[i]:
                continue
            bound = _interval_bound(relative, items, i, f_start[i], f_end[i], span)
            if not bound >= thresholds[i]:
                pending[unsure] = i
                unsure += 1
        if unsure:
            _refine_interval(
                order,
                pos,
                geometry,
                fixed_distance,
                still,
                crank_radius,
                items,
                thresholds,
                t * span,
                (t + 1) * span,
                start,
                end,
                pending[:unsure],
                least,
                conflict,
                unresolved,
                spent,
                splits_left,
            )
        start[:] = end
        v_start[:] = v_end
        f_start[:] = f_end
    return max_splits - splits_left[0]


@dataclass(frozen=True, eq=False)
class Collisions:
    """Which bodies of a mechanism built as bars come within the clearance over a crank turn.

    `links` (L, 2) holds each link's joints (i < j, in `inputs.link_pairs` order); the other
    arrays are indexed by those links and by joints. `link_conflicts` (L, L) is symmetric,
    False on its diagonal, True for links that share a joint; `pin_conflicts` (L, n) is False
    at a link's own joints. `link_distance` and `pin_distance` hold the least distance between
    the centre lines (a link's segment and another's, or a joint) at the poses examined: 0 for
    links that share a joint and at a link's own joints; for a pair that conflicts it is the
    least found, which the true least may undercut. `link_unresolved` and `pin_unresolved` mark
    the pairs counted as conflicts without being found within (the module's docstring);
    `splits` is how many intervals the check split.
    """

    links: np.ndarray
    bar_width: float
    clearance: float
    pin_diameter: float
    steps: int
    link_conflicts: np.ndarray
    link_distance: np.ndarray
    link_unresolved: np.ndarray
    pin_conflicts: np.ndarray
    pin_distance: np.ndarray
    pin_unresolved: np.ndarray
    splits: int

    @property
    def link_threshold(self) -> float:
        """The distance between two links' centre lines below which they conflict: W + C."""
        return self.bar_width + self.clearance

    @property
    def pin_threshold(self) -> float:
        """The distance from a link's centre line to a joint below which the link conflicts
        with the joint's pin: W / 2 + D / 2 + C."""
        return (self.bar_width + self.pin_diameter) / 2 + self.clearance


def _pair_items(links: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(items (p, 4), which (p,) link pairs (first, second) or (link, joint), is_pin (p,)):
    every pair of links that share no joint, then every link with every joint not its own."""
    first, second = np.triu_indices(len(links), 1)
    shared = (links[first, :, None] == links[second, None, :]).any(axis=(1, 2))
    first, second = first[~shared], second[~shared]
    link_items = np.column_stack([links[first], links[second]])
    link, joint = np.nonzero(
        (np.arange(n)[None, :] != links[:, :1]) & (np.arange(n)[None, :] != links[:, 1:])
    )
    pin_items = np.column_stack([links[link], joint, joint])
    items = np.ascontiguousarray(np.vstack([link_items, pin_items]), dtype=np.int64)
    which = np.vstack([np.column_stack([first, second]), np.column_stack([link, joint])])
    is_pin = np.arange(len(items)) >= len(link_items)
    return items, which, is_pin


def find_collisions(
    adjacency: ArrayLike,
    node_types: ArrayLike,
    positions: ArrayLike,
    *,
    bar_width: float,
    clearance: float,
    pin_diameter: float,
    steps: int = DEFAULT_COLLISION_STEPS,
) -> Collisions:
    """Which links, built as bars `bar_width` wide with pins `pin_diameter` across at the
    joints, come within `clearance` of each other or of a pin at any crank angle of a full
    turn, measured at `steps` steps and proven between them (the module's docstring). The
    lengths are in the unit of `positions`.

    Raises `ValueError` naming the problem: a malformed mechanism or step count
    (`InvalidMechanismError`), one of more than MAX_LAYERED_JOINTS joints, sizes
    `fabrication.limits.as_bar_sizes` refuses, or a mechanism that locks (`LockingError`).
    """
    topology = topology_cache.simulator(adjacency, node_types).topology
    pos, steps = checked_input(topology, positions, steps)
    bar_width, clearance, pin_diameter = as_bar_sizes(bar_width, clearance, pin_diameter)
    n = topology.n_joints
    if n > MAX_LAYERED_JOINTS:
        raise InvalidMechanismError(
            f"a layered build takes at most {MAX_LAYERED_JOINTS} joints, got {n}"
        )
    traj = simulate(topology.adjacency, topology.node_types, pos, steps)
    order = topology.order
    geometry = np.empty((order.shape[0], 3))
    _dyad_geometry(order, pos, geometry)
    parent_a, parent_b = order[:, 1], order[:, 2]
    fixed = topology.node_types == FIXED
    fixed_distance = (topology.adjacency[parent_a, parent_b] != 0) | (
        fixed[parent_a] & fixed[parent_b]
    )
    links = np.column_stack(topology.links).astype(np.int64).reshape(-1, 2)
    items, which, is_pin = _pair_items(links, n)
    pin_threshold = (bar_width + pin_diameter) / 2 + clearance
    thresholds = np.where(is_pin, pin_threshold, bar_width + clearance)
    count = len(items)
    least = np.empty(count)
    conflict = np.empty(count, dtype=np.bool_)
    unresolved = np.empty(count, dtype=np.bool_)
    splits = _clearances(
        order,
        pos,
        geometry,
        fixed_distance,
        topology.fixed_joints,
        traj,
        items,
        thresholds,
        least,
        conflict,
        unresolved,
        MAX_SPLITS,
    )
    count_links = len(links)
    link_conflicts = links[:, :, None, None] == links[None, None, :, :]
    link_conflicts = link_conflicts.any(axis=(1, 3))
    np.fill_diagonal(link_conflicts, False)
    link_distance = np.zeros((count_links, count_links))
    link_unresolved = np.zeros((count_links, count_links), dtype=bool)
    pin_conflicts = np.zeros((count_links, n), dtype=bool)
    pin_distance = np.zeros((count_links, n))
    pin_unresolved = np.zeros((count_links, n), dtype=bool)
    first, second = which[~is_pin, 0], which[~is_pin, 1]
    for matrix, values in (
        (link_conflicts, conflict),
        (link_distance, least),
        (link_unresolved, unresolved),
    ):
        matrix[first, second] = matrix[second, first] = values[~is_pin]
    link, joint = which[is_pin, 0], which[is_pin, 1]
    pin_conflicts[link, joint] = conflict[is_pin]
    pin_distance[link, joint] = least[is_pin]
    pin_unresolved[link, joint] = unresolved[is_pin]
    return Collisions(
        links=links,
        bar_width=bar_width,
        clearance=clearance,
        pin_diameter=pin_diameter,
        steps=steps,
        link_conflicts=link_conflicts,
        link_distance=link_distance,
        link_unresolved=link_unresolved,
        pin_conflicts=pin_conflicts,
        pin_distance=pin_distance,
        pin_unresolved=pin_unresolved,
        splits=int(splits),
    )
