"""One refinement step: the IRLS Gauss-Newton system of the chamfer toward a drawing, the
linearized transmission guards, and the damped step solved within them.

`engine.synthesis.refinement.loop` iterates these: each iteration fixes the nearest-point
correspondences between the path and the drawing (`normal_equations`), linearizes the transmission
sines near their floors (`transmission_guards`), and solves the damped system subject to those
guards (by a small active set), shortened to a longest move (`guarded_step`). The arithmetic is
compiled, in `engine.synthesis.refinement.step_kernels`.

Pure numpy/numba: no Ray, no files.
"""

from __future__ import annotations

import numpy as np

from links_ray.engine.synthesis.refinement.step_kernels import (
    chamfer_system,
    guard_minima,
    guarded_minimum,
)
from links_ray.engine.synthesis.target import Target

#: Distances below this share of the drawing's chord weigh as much as this (the IRLS weight
#: floor: how near a pair may come before its weight stops growing).
IRLS_WEIGHT_FLOOR = 1e-4
#: The floor is at least this share of the current chamfer too: pairs nearer than that weigh
#: alike, as in least squares, and only the far ones as the chamfer weighs them. The floor
#: follows the fit down, so the steps aim at the chamfer more closely as it falls.
IRLS_RELATIVE = 0.25


def normal_equations(
    target: Target,
    path: np.ndarray,
    jac: np.ndarray,
    interval: tuple[int, int] | None,
    weight_floor: float = IRLS_WEIGHT_FLOOR,
) -> tuple[np.ndarray, np.ndarray]:
    """IRLS Gauss-Newton system (A, g) of the chamfer with correspondences fixed at `path`
    (`step_kernels.chamfer_system`).

    jac (steps, 2, P) is d path / d positions. Residuals of the two directions that land on
    the same path step are summed into one weight and one weighted residual per step.
    Distances below the floor, the larger of `weight_floor` times the chord and IRLS_RELATIVE
    times the current chamfer, weigh as the floor does.
    """
    return chamfer_system(
        path, target.points, jac, interval, weight_floor * target.chord, IRLS_RELATIVE
    )


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
    """Linearized transmission constraints (A, b), A delta >= b, for the next step
    (`step_kernels.guard_minima`).

    Each dyad whose sine comes within 2 x `clearance` of its floor contributes one row per
    local minimum of its sine over the steps: that minimum must stay `clearance` above the
    floor (the check steps lie between these steps and dip lower).
    """
    return guard_minima(trans, dtrans, floors, clearance)


def guarded_step(
    pos: np.ndarray,
    system: np.ndarray,
    gradient: np.ndarray,
    guards: tuple[np.ndarray, np.ndarray],
    longest: float,
) -> np.ndarray | None:
    """pos + the damped Gauss-Newton step within the linearized guards, shortened to move no
    joint coordinate more than `longest`; None if the system cannot be solved."""
    delta = guarded_minimum(system, gradient, *guards)
    if delta is None or not np.all(np.isfinite(delta)):
        # No factor, or an overflowed solve (a nearly singular system): a more damped step
        # is tried next.
        return None
    size = float(np.abs(delta).max())
    if size > longest:
        delta *= longest / size
    return pos + delta.reshape(pos.shape)
