"""Kernels of one refinement step (`engine.synthesis.refinement.step` calls them): the IRLS system
of the chamfer from its nearest-point pairs (`chamfer_system`), the rows of the transmission guards
(`guard_minima`), and the damped step within linear guards (`guarded_minimum`: Cholesky factors, and
Lawson and Hanson's active set on the dual).

A step's systems are small (2n coordinates, a few dozen guards) and an iteration makes a few of
them: in numpy, their calls' overhead, not their arithmetic, was most of a step's time, and
held the interpreter's lock the other refinement threads wait on.

The entry points, called from Python with the caller's buffers, check their shapes first
(`buffers.check_buffer`): numba checks no bounds.

Pure numpy/numba, plain-array signatures: no Ray.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from links_ray.engine.buffers import check_buffer
from links_ray.engine.synthesis.refinement.kernels import LANES, _nearest_pairs

__all__ = ["GUARD_ROUNDS", "SINGULAR", "chamfer_system", "guard_minima", "guarded_minimum"]

#: Most rounds of the active set that keeps a step within its guards.
GUARD_ROUNDS = 12
#: `guarded_minimum`'s answer when a system has no Cholesky factor (it is not positive
#: definite, to the precision of its arithmetic).
SINGULAR = 1


@njit(cache=True, nogil=True)
def _cholesky(a: np.ndarray, lower: np.ndarray) -> bool:
    """lower (n, n) = the Cholesky factor of a (n, n); False if a is not positive definite
    (lower then holds no factor)."""
    n = a.shape[0]
    for j in range(n):
        s = a[j, j]
        for k in range(j):
            s -= lower[j, k] * lower[j, k]
        if not s > 0.0:  # also refuses NaN
            return False
        root = np.sqrt(s)
        lower[j, j] = root
        for i in range(j + 1, n):
            t = a[i, j]
            for k in range(j):
                t -= lower[i, k] * lower[j, k]
            lower[i, j] = t / root
        for i in range(j):
            lower[i, j] = 0.0
    return True


@njit(cache=True, nogil=True)
def _cholesky_solve(lower: np.ndarray, b: np.ndarray) -> None:
    """b (n,) = (lower lower^T)^-1 b, in place."""
    n = lower.shape[0]
    for i in range(n):
        t = b[i]
        for k in range(i):
            t -= lower[i, k] * b[k]
        b[i] = t / lower[i, i]
    for i in range(n - 1, -1, -1):
        t = b[i]
        for k in range(i + 1, n):
            t -= lower[k, i] * b[k]
        b[i] = t / lower[i, i]


@njit(cache=True, nogil=True)
def _active_set(q: np.ndarray, c: np.ndarray, tolerance: float, mu: np.ndarray) -> int:
    """mu (r,) >= 0 minimizing 1/2 mu.q.mu - c.mu, by Lawson and Hanson's rounds for
    non-negativity (at most GUARD_ROUNDS, leaving the last iterate); SINGULAR if an active
    set's system has no factor, NaN in mu if a solve overflowed, else 0."""
    r = c.shape[0]
    on = np.zeros(r, dtype=np.bool_)
    mu[:] = 0.0
    trial = np.empty(r)
    sub = np.empty((r, r))
    lower = np.empty((r, r))
    rhs = np.empty(r)
    index = np.empty(r, dtype=np.int64)
    for _ in range(GUARD_ROUNDS):
        entering, most = -1, -np.inf
        for i in range(r):
            if not on[i]:
                descent = c[i]
                for k in range(r):
                    descent -= q[i, k] * mu[k]
                if descent > most:
                    entering, most = i, descent
        if entering < 0 or most <= tolerance:
            break
        on[entering] = True
        while True:
            size = 0
            for i in range(r):
                if on[i]:
                    index[size] = i
                    size += 1
            for a in range(size):
                rhs[a] = c[index[a]]
                for b in range(size):
                    sub[a, b] = q[index[a], index[b]]
            if not _cholesky(sub[:size, :size], lower[:size, :size]):
                return SINGULAR
            _cholesky_solve(lower[:size, :size], rhs[:size])
            trial[:] = 0.0
            positive = True
            for a in range(size):
                value = rhs[a]
                if not np.isfinite(value):
                    mu[:] = np.nan  # no multiplier to move toward: the caller refuses the step
                    return 0
                trial[index[a]] = value
                positive = positive and value > 0.0
            if positive:
                mu[:] = trial
                break
            # Move toward the trial as far as every multiplier stays >= 0; free those at 0.
            share = np.inf
            for a in range(size):
                i = index[a]
                if trial[i] <= 0.0:
                    share = min(share, mu[i] / (mu[i] - trial[i]))
            any_on = False
            for i in range(r):
                mu[i] += share * (trial[i] - mu[i])
                on[i] = on[i] and mu[i] > tolerance
                if not on[i]:
                    mu[i] = 0.0
                any_on = any_on or on[i]
            if not any_on:
                break
    return 0


@njit(cache=True, nogil=True)
def _guarded_minimum(
    system: np.ndarray,
    gradient: np.ndarray,
    rows: np.ndarray,
    bounds: np.ndarray,
    delta: np.ndarray,
) -> int:
    """delta = argmin 1/2 d.system.d + gradient.d subject to rows.d >= bounds; SINGULAR if
    `system` (or an active set's dual system) has no Cholesky factor, else 0 (delta then may
    hold NaN or infinities where a solve overflowed).

    Solved in the dual: delta is free + system^-1 rows^T mu for the multipliers mu >= 0 that
    minimize 1/2 mu.Q.mu - c.mu, Q = rows system^-1 rows^T and c = bounds - rows.free."""
    n, r = gradient.shape[0], rows.shape[0]
    lower = np.empty((n, n))
    if not _cholesky(system, lower):
        return SINGULAR
    for i in range(n):
        delta[i] = -gradient[i]
    _cholesky_solve(lower, delta)  # the free step
    if r == 0:
        return 0
    towards = np.empty((r, n))  # row g: system^-1 rows[g]
    for g in range(r):
        towards[g] = rows[g]
        _cholesky_solve(lower, towards[g])
    q = np.empty((r, r))
    trace = 0.0
    for a in range(r):
        for b in range(r):
            t = 0.0
            for i in range(n):
                t += rows[a, i] * towards[b, i]
            q[a, b] = t
        trace += q[a, a]
    # Dependent guards (more than the coordinates, or two steps of one dead centre) make Q
    # singular, and the active set then cycles; a ridge this small keeps it exact to the
    # tests' tolerance.
    ridge = 1e-10 * max(trace, 1e-300)
    c = np.empty(r)
    largest = 0.0
    for a in range(r):
        q[a, a] += ridge
        t = bounds[a]
        for i in range(n):
            t -= rows[a, i] * delta[i]
        c[a] = t
        largest = max(largest, abs(t))
    mu = np.empty(r)
    status = _active_set(q, c, 1e-12 * (1.0 + largest), mu)
    if status != 0:
        return status
    for g in range(r):
        for i in range(n):
            delta[i] += towards[g, i] * mu[g]
    return 0


@njit(cache=True, nogil=True, fastmath=LANES)
def _dot(a: np.ndarray, b: np.ndarray) -> float:
    total = 0.0
    for i in range(a.shape[0]):
        total += a[i] * b[i]
    return total


@njit(cache=True, nogil=True)
def _chamfer_system(
    path: np.ndarray,
    drawn: np.ndarray,
    jac: np.ndarray,
    first: int,
    count: int,
    floor: float,
    relative: float,
    system: np.ndarray,
    gradient: np.ndarray,
) -> float:
    """The IRLS system of the chamfer between the run of `count` steps of `path` from step
    `first` (cyclic) and `drawn`, with its pairs fixed; returns the run's chamfer.

    jac (steps, 2, p) is d path / d coordinates. Residuals of the two directions that land on
    the same path step are summed into one weight and one weighted residual per step.
    Distances below the larger of `floor` and `relative` times the chamfer weigh as it does."""
    steps, points, cols = path.shape[0], drawn.shape[0], jac.shape[2]
    sub = np.empty((count, 2))
    for i in range(count):
        s = (first + i) % steps
        sub[i, 0] = path[s, 0]
        sub[i, 1] = path[s, 1]
    path_nn = np.empty(count, dtype=np.int64)
    path_d = np.empty(count)
    drawn_nn = np.empty(points, dtype=np.int64)
    drawn_d = np.empty(points)
    _nearest_pairs(sub, drawn, path_nn, path_d, drawn_nn, drawn_d)
    current = path_d.mean() + drawn_d.mean()  # the chamfer (engine.kinematics.paths.chamfer)
    least = max(floor, relative * current)
    # Weight 1 / (count x distance): the weighted squares' gradient is the mean distance's.
    weight = np.empty(count)
    residual = np.empty((count, 2))
    for i in range(count):
        w = 1.0 / (count * max(path_d[i], least))
        weight[i] = w
        j = path_nn[i]
        residual[i, 0] = w * (sub[i, 0] - drawn[j, 0])
        residual[i, 1] = w * (sub[i, 1] - drawn[j, 1])
    for k in range(points):
        w = 1.0 / (points * max(drawn_d[k], least))
        i = drawn_nn[k]
        weight[i] += w
        residual[i, 0] += w * (sub[i, 0] - drawn[k, 0])
        residual[i, 1] += w * (sub[i, 1] - drawn[k, 1])
    # system = S S^T for the scaled derivatives S (p, 2 count), one row per coordinate: each
    # entry is then a dot product of two contiguous rows, which runs in vector lanes.
    scaled = np.empty((cols, 2 * count))
    gradient[:] = 0.0
    for i in range(count):
        s = (first + i) % steps
        root = np.sqrt(weight[i])
        for axis in range(2):
            r = residual[i, axis]
            for a in range(cols):
                derivative = jac[s, axis, a]
                scaled[a, 2 * i + axis] = root * derivative
                gradient[a] += r * derivative
    for a in range(cols):
        for b in range(a, cols):
            value = _dot(scaled[a], scaled[b])
            system[a, b] = value
            system[b, a] = value
    return current


@njit(cache=True, nogil=True)
def _guard_minima(
    trans: np.ndarray,
    dtrans: np.ndarray,
    floors: np.ndarray,
    clearance: float,
) -> tuple[np.ndarray, np.ndarray]:
    """(rows, bounds) of `refine_step.transmission_guards`: one per local minimum (cyclic,
    ties included) of each dyad's sine over the steps within 2 x `clearance` of its floor, by
    dyad, then step."""
    dyads, steps, cols = trans.shape[0], trans.shape[1], dtrans.shape[2]
    low = np.zeros((dyads, steps), dtype=np.bool_)
    count = 0
    for d in range(dyads):
        near = floors[d] + 2.0 * clearance
        for s in range(steps):
            value = trans[d, s]
            if (
                value < near
                and value <= trans[d, s - 1]  # s - 1 = -1 is the last step: cyclic
                and value <= trans[d, (s + 1) % steps]
            ):
                low[d, s] = True
                count += 1
    rows = np.empty((count, cols))
    bounds = np.empty(count)
    g = 0
    for d in range(dyads):
        for s in range(steps):
            if low[d, s]:
                rows[g] = dtrans[d, s]
                bounds[g] = floors[d] + clearance - trans[d, s]
                g += 1
    return rows, bounds


# -- entry points ------------------------------------------------------------------------------


def chamfer_system(
    path: np.ndarray,
    drawn: np.ndarray,
    jac: np.ndarray,
    interval: tuple[int, int] | None,
    floor: float,
    relative: float,
) -> tuple[np.ndarray, np.ndarray]:
    """(system, gradient) of `_chamfer_system` for `path` (steps, 2) and its derivatives
    jac (steps, 2, p), over the run `interval` (start, count) of steps, or all of them."""
    check_buffer("path", path, (None, 2))
    steps = path.shape[0]
    check_buffer("drawn", drawn, (None, 2))
    cols = jac.shape[2] if isinstance(jac, np.ndarray) and jac.ndim == 3 else 0
    check_buffer("jac", jac, (steps, 2, cols))
    first, count = (0, steps) if interval is None else interval
    if steps == 0 or drawn.shape[0] == 0 or not 0 <= first < steps or not 0 < count <= steps:
        raise ValueError(
            f"the run must lie in a path of points, and the drawing hold points: got a run of "
            f"{count} from step {first} of {steps}, and {drawn.shape[0]} drawn points"
        )
    system = np.empty((cols, cols))
    gradient = np.empty(cols)
    _chamfer_system(path, drawn, jac, first, count, floor, relative, system, gradient)
    return system, gradient


def guard_minima(
    trans: np.ndarray, dtrans: np.ndarray, floors: np.ndarray, clearance: float
) -> tuple[np.ndarray, np.ndarray]:
    """`_guard_minima` for the sines trans (m, steps), their derivatives dtrans (m, steps, p)
    and the dyads' floors (m,)."""
    check_buffer("trans", trans, (None, None))
    dyads, steps = trans.shape
    cols = dtrans.shape[2] if isinstance(dtrans, np.ndarray) and dtrans.ndim == 3 else 0
    check_buffer("dtrans", dtrans, (dyads, steps, cols))
    check_buffer("floors", floors, (dyads,))
    return _guard_minima(trans, dtrans, floors, clearance)


def guarded_minimum(
    system: np.ndarray, gradient: np.ndarray, rows: np.ndarray, bounds: np.ndarray
) -> np.ndarray | None:
    """argmin 1/2 d.system.d + gradient.d subject to rows.d >= bounds (`_guarded_minimum`),
    for system (p, p), gradient (p,), rows (r, p) and bounds (r,); None if a system has no
    Cholesky factor."""
    check_buffer("gradient", gradient, (None,))
    cols = gradient.shape[0]
    check_buffer("system", system, (cols, cols))
    check_buffer("rows", rows, (None, cols))
    check_buffer("bounds", bounds, (rows.shape[0],))
    delta = np.empty(cols)
    if _guarded_minimum(system, gradient, rows, bounds, delta) == SINGULAR:
        return None
    return delta
