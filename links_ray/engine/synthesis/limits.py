"""Limits of refinement, synthesis's local search: how large a mechanism and how fine a turn
it takes, how finely a refined mechanism is checked, and how many iterations it may run.

Shared limits (mechanisms, drawn points, transmission angles) are in `engine.inputs`; a
synthesis request's own options in `engine.synthesis.options`.
"""

from __future__ import annotations

from links_ray.engine.inputs import InvalidMechanismError

#: Largest mechanism refinement takes, in joints: it keeps d(trajectory)/d(positions), joints x
#: steps x 2 x 2 joints numbers (32 MB at 50 joints and 200 steps).
MAX_REFINE_JOINTS = 50
#: Most simulation steps refinement takes (its derivatives grow with the steps).
MAX_REFINE_STEPS = 1000
#: Crank steps of the final check of a refined mechanism: finer than any simulation it is given,
#: so a lock or a dead centre between the simulation's steps is caught.
REFINE_CHECK_STEPS = 2000
DEFAULT_REFINE_ITERATIONS, MAX_REFINE_ITERATIONS = 200, 10_000


def check_refine_size(n_joints: int, steps: int) -> None:
    """Refuse a refinement whose derivatives would be too large (MAX_REFINE_JOINTS joints,
    MAX_REFINE_STEPS steps)."""
    if n_joints > MAX_REFINE_JOINTS:
        raise InvalidMechanismError(
            f"refinement takes at most {MAX_REFINE_JOINTS} joints, got {n_joints}"
        )
    if steps > MAX_REFINE_STEPS:
        raise ValueError(f"refinement takes at most {MAX_REFINE_STEPS} steps, got {steps}")
