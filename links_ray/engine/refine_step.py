"""One refinement step: the IRLS Gauss-Newton system of the chamfer toward a drawing, the
linearized transmission guards, and the damped step solved within them.

`engine.refine` iterates these: each iteration fixes the nearest-point correspondences between
the path and the drawing (`normal_equations`), linearizes the transmission sines near their
floors (`transmission_guards`), and solves the damped system subject to those guards
(`constrained_minimum`, by a small active set), shortened to a longest move (`guarded_step`).

Pure numpy/numba: no Ray, no files.
"""

from __future__ import annotations

import numpy as np

from links_ray.engine.refine_kernels import nearest_pairs
from links_ray.engine.target import Target

#: Distances below this share of the drawing's chord weigh as much as this (the IRLS weight
#: floor: how near a pair may come before its weight stops growing).
IRLS_WEIGHT_FLOOR = 1e-4
#: The floor is at least this share of the current chamfer too: pairs nearer than that weigh
#: alike, as in least squares, and only the far ones as the chamfer weighs them. The floor
#: follows the fit down, so the steps aim at the chamfer more closely as it falls.
IRLS_RELATIVE = 0.25
#: Most rounds of the active set that keeps a step within its guards.
GUARD_ROUNDS = 12


def normal_equations(
    target: Target,
    path: np.ndarray,
    jac: np.ndarray,
    interval: tuple[int, int] | None,
    weight_floor: float = IRLS_WEIGHT_FLOOR,
) -> tuple[np.ndarray, np.ndarray]:
    """IRLS Gauss-Newton system (A, g) of the chamfer with correspondences fixed at `path`.

    jac (steps, 2, P) is d path / d positions. Residuals of the two directions that land on
    the same path step are summed into one weight and one weighted residual per step.
    Distances below the floor, the larger of `weight_floor` times the chord and IRLS_RELATIVE
    times the current chamfer, weigh as the floor does.
    """
    steps = len(path)
    rows = np.arange(steps) if interval is None else (interval[0] + np.arange(interval[1])) % steps
    sub = np.ascontiguousarray(path[rows])
    drawn = target.points
    count, points = len(sub), len(drawn)
    path_nn = np.empty(count, dtype=np.int64)
    path_d = np.empty(count)
    drawn_nn = np.empty(points, dtype=np.int64)
    drawn_d = np.empty(points)
    nearest_pairs(sub, drawn, path_nn, path_d, drawn_nn, drawn_d)
    current = path_d.mean() + drawn_d.mean()  # the chamfer (engine.paths.chamfer)
    least = max(weight_floor * target.chord, IRLS_RELATIVE * current)
    # Weight 1 / (count x distance): the weighted squares' gradient is the mean distance's.
    w_path = 1.0 / (count * np.maximum(path_d, least))
    w_drawn = 1.0 / (points * np.maximum(drawn_d, least))
    weight = w_path.copy()
    np.add.at(weight, drawn_nn, w_drawn)
    residual = w_path[:, None] * (sub - drawn[path_nn])
    np.add.at(residual, drawn_nn, w_drawn[:, None] * (sub[drawn_nn] - drawn))
    j = jac[rows]
    cols = j.shape[2]
    scaled = (j * np.sqrt(weight)[:, None, None]).reshape(-1, cols)
    return scaled.T @ scaled, residual.reshape(-1) @ j.reshape(-1, cols)


def timed_equations(
    target: Target,
    timed_path: np.ndarray,
    jac: np.ndarray,
    weight_floor: float = IRLS_WEIGHT_FLOOR,
) -> tuple[np.ndarray, np.ndarray]:
    """IRLS Gauss-Newton system (A, g) of the timed error: the mean distance of each drawn
    point from `timed_path` (T, 2), the path at that point's crank angle, whose derivative is
    jac (T, 2, P). The pairs are fixed by timing, so this is the error's exact linearization;
    weights as `normal_equations`'s."""
    gaps = timed_path - target.points
    distances = np.hypot(gaps[:, 0], gaps[:, 1])
    least = max(weight_floor * target.chord, IRLS_RELATIVE * float(distances.mean()))
    weight = 1.0 / (len(gaps) * np.maximum(distances, least))
    cols = jac.shape[2]
    scaled = (jac * np.sqrt(weight)[:, None, None]).reshape(-1, cols)
    residual = weight[:, None] * gaps
    return scaled.T @ scaled, residual.reshape(-1) @ jac.reshape(-1, cols)


def transmission_guards(
    trans: np.ndarray, dtrans: np.ndarray, floors: np.ndarray, clearance: float
) -> tuple[np.ndarray, np.ndarray]:
    """Linearized transmission constraints (A, b), A delta >= b, for the next step.

    Each dyad whose sine comes within 2 x `clearance` of its floor contributes one row per
    local minimum of its sine over the steps: that minimum must stay `clearance` above the
    floor (the check steps lie between these steps and dip lower).
    """
    near = trans < (floors + 2.0 * clearance)[:, None]
    low = near & (trans <= np.roll(trans, 1, axis=1)) & (trans <= np.roll(trans, -1, axis=1))
    dyads, steps = np.nonzero(low)
    return dtrans[dyads, steps], floors[dyads] + clearance - trans[dyads, steps]


def constrained_minimum(
    system: np.ndarray, gradient: np.ndarray, rows: np.ndarray, bounds: np.ndarray
) -> np.ndarray:
    """argmin of 1/2 d.system.d + gradient.d subject to rows.d >= bounds (`system` positive
    definite). Raises LinAlgError if `system` is singular.

    Solved in the dual: the step is free + system^-1 rows^T mu for the multipliers mu >= 0
    that minimize 1/2 mu.Q.mu - c.mu, Q = rows system^-1 rows^T and c = bounds - rows.free,
    by Lawson and Hanson's active set for non-negativity (exact in finitely many rounds; at
    most GUARD_ROUNDS, leaving the last iterate: the trial is checked in full anyway)."""
    free = np.linalg.solve(system, -gradient)
    if not len(rows):
        return free
    towards = np.linalg.solve(system, rows.T)  # system^-1 rows^T
    q = rows @ towards
    # Dependent constraints (more than the coordinates, or two steps of one dead centre)
    # make Q singular, and the active set then cycles; a ridge this small keeps it exact to
    # the tests' tolerance.
    q += 1e-10 * max(float(np.trace(q)), 1e-300) * np.eye(len(rows))
    c = bounds - rows @ free
    tolerance = 1e-12 * (1.0 + float(np.abs(c).max()))
    mu = np.zeros(len(rows))
    on = np.zeros(len(rows), dtype=bool)  # multipliers free to be positive
    with np.errstate(invalid="ignore", over="ignore"):
        # A nearly singular active set can overflow: `guarded_step` refuses a step that is
        # not finite, and a shorter one is tried.
        mu = _active_set(q, c, mu, on, tolerance)
    return free + towards @ mu


def _active_set(
    q: np.ndarray, c: np.ndarray, mu: np.ndarray, on: np.ndarray, tolerance: float
) -> np.ndarray:
    """Lawson and Hanson's rounds for `constrained_minimum`'s multipliers, from `mu` and the
    free set `on` (changed in place), at most GUARD_ROUNDS."""
    for _ in range(GUARD_ROUNDS):
        descent = c - q @ mu
        descent[on] = -np.inf
        entering = int(np.argmax(descent))
        if descent[entering] <= tolerance:
            break
        on[entering] = True
        while True:
            trial = np.zeros(len(c))
            index = np.flatnonzero(on)
            trial[index] = np.linalg.solve(q[np.ix_(index, index)], c[index])
            if not np.all(np.isfinite(trial[index])):
                # An overflowed solve has no multiplier to move toward: the step it gives is
                # not finite, and `guarded_step` refuses it (a more damped one comes next).
                return np.full(len(c), np.nan)
            if np.all(trial[index] > 0.0):
                mu = trial
                break
            # Move toward the trial as far as every multiplier stays >= 0; free the one at 0.
            falling = index[trial[index] <= 0.0]
            share = float(np.min(mu[falling] / (mu[falling] - trial[falling])))
            mu = mu + share * (trial - mu)
            on &= mu > tolerance
            mu[~on] = 0.0
            if not on.any():
                break
    return mu


def guarded_step(
    pos: np.ndarray,
    system: np.ndarray,
    gradient: np.ndarray,
    guards: tuple[np.ndarray, np.ndarray],
    longest: float,
) -> np.ndarray | None:
    """pos + the damped Gauss-Newton step within the linearized guards, shortened to move no
    joint coordinate more than `longest`; None if the system cannot be solved."""
    try:
        delta = constrained_minimum(system, gradient, *guards)
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(delta)):
        return None
    size = float(np.abs(delta).max())
    if size > longest:
        delta *= longest / size
    return pos + delta.reshape(pos.shape)
