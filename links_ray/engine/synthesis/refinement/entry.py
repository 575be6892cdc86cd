"""Refinement's entry points for a caller's own arrays: `refine` refines one mechanism toward
a drawing and `refine_many` many of them, after checking every input
(`engine.synthesis.refinement.loop` says how refinement works; `refine_validated` is the loop they
run).

Pure numpy/numba: no Ray, no files.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np
from numpy.typing import ArrayLike

from links_ray.engine.inputs import (
    DEFAULT_MIN_TRANSMISSION_DEG,
    DEFAULT_STEPS,
    MIN_POINTS,
    InvalidMechanismError,
    as_int,
    as_positions,
    as_transmission_deg,
    check_positions,
)
from links_ray.engine.kinematics.mechanism import LockingError, Topology, analyze_topology
from links_ray.engine.node_kinds import FIXED
from links_ray.engine.synthesis.limits import (
    DEFAULT_REFINE_ITERATIONS,
    MAX_REFINE_ITERATIONS,
    check_refine_size,
)
from links_ray.engine.synthesis.refinement.loop import Refinement, refine_validated
from links_ray.engine.synthesis.target import as_target

__all__ = ["refine", "refine_many"]


def _prepare(
    adjacency: ArrayLike,
    node_types: ArrayLike,
    positions: ArrayLike,
    joint: object,
    steps: int,
) -> tuple[Topology, np.ndarray, int]:
    """(topology, positions, joint) of a caller's mechanism, checked: `InvalidMechanismError`
    names a malformed mechanism, one too large to refine or a fixed `joint`, and `ValueError`
    more `steps` than refinement takes."""
    topology = analyze_topology(adjacency, node_types)
    n = topology.n_joints
    check_refine_size(n, steps)
    pos = as_positions(positions, n)
    check_positions(topology.adjacency, pos)
    joint = as_int("joint", joint, 0, n - 1, InvalidMechanismError)
    if topology.node_types[joint] == FIXED:
        raise InvalidMechanismError(f"joint {joint} is fixed: it traces no path to refine")
    return topology, pos, joint


def refine(
    adjacency: ArrayLike,
    node_types: ArrayLike,
    positions: ArrayLike,
    joint: int,
    target_points: ArrayLike,
    *,
    partial: bool = False,
    iterations: int = DEFAULT_REFINE_ITERATIONS,
    min_transmission_deg: float = DEFAULT_MIN_TRANSMISSION_DEG,
    steps: int = DEFAULT_STEPS,
) -> Refinement:
    """Move the joints of a mechanism so that `joint`'s path at `steps` crank steps traces
    `target_points` (in the mechanism's frame), as `engine.synthesis.refinement.loop` says.

    `partial`: the points are an open stroke matched to part of a turn. `iterations`: most
    Levenberg-Marquardt iterations. `min_transmission_deg`: least transmission angle kept. Raises
    `InvalidMechanismError` or `ValueError` for bad input and `LockingError` if the mechanism
    locks as given (at `steps` or REFINE_CHECK_STEPS steps).
    """
    steps = as_int("steps", steps, MIN_POINTS, None, InvalidMechanismError)
    topology, pos, joint = _prepare(adjacency, node_types, positions, joint, steps)
    target = as_target(target_points, partial)
    iterations = as_int("iterations", iterations, 0, MAX_REFINE_ITERATIONS)
    min_transmission_deg = as_transmission_deg(min_transmission_deg)
    return refine_validated(topology, pos, joint, target, steps, iterations, min_transmission_deg)


def refine_many(
    candidates: Iterable[Sequence[object]],
    target_points: ArrayLike,
    *,
    partial: bool = False,
    iterations: int = DEFAULT_REFINE_ITERATIONS,
    min_transmission_deg: float = DEFAULT_MIN_TRANSMISSION_DEG,
    steps: int = DEFAULT_STEPS,
) -> list[Refinement]:
    """`refine` for many candidates (adjacency, node_types, positions, joint) of one drawing.

    Every input is checked before any work, and a bad one raises ValueError naming the
    candidate. A candidate that locks as given gets a result with `error` set and its own
    positions, so one retrieved mechanism cannot sink the rest.
    """
    steps = as_int("steps", steps, MIN_POINTS, None, InvalidMechanismError)
    target = as_target(target_points, partial)
    iterations = as_int("iterations", iterations, 0, MAX_REFINE_ITERATIONS)
    min_transmission_deg = as_transmission_deg(min_transmission_deg)
    prepared = []
    for index, candidate in enumerate(candidates):
        try:
            adjacency, node_types, positions, joint = candidate
        except (TypeError, ValueError):
            raise ValueError(
                f"candidate {index} must be (adjacency, node_types, positions, joint)"
            ) from None
        try:
            prepared.append(_prepare(adjacency, node_types, positions, joint, steps))
        except ValueError as exc:
            raise type(exc)(f"candidate {index}: {exc}") from None
    results = []
    for topology, pos, joint in prepared:
        try:
            results.append(
                refine_validated(
                    topology, pos, joint, target, steps, iterations, min_transmission_deg
                )
            )
        except LockingError as exc:
            results.append(
                Refinement(pos, math.nan, math.nan, None, 0, 0, math.nan, error=str(exc))
            )
    return results
