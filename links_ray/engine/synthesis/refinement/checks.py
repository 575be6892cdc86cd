"""Refinement's simulations and checks: a turn solved with the path's derivatives in
per-thread scratch arrays (`solve_turn`), a position set's validity at REFINE_CHECK_STEPS
(`check_mechanism`, `valid_trial`), and the measure refinement lowers (`target_error`).

Pure numpy/numba: no Ray, no files.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import numpy as np

from links_ray.engine.buffers import check_buffer
from links_ray.engine.inputs import InvalidMechanismError, check_positions
from links_ray.engine.kinematics.mechanism import Topology
from links_ray.engine.kinematics.solver import crank_turn
from links_ray.engine.kinematics.turning import MAX_SPLITS, _turn_lock, rigid_dyads
from links_ray.engine.synthesis.constraints import KEPT, Violation, extent
from links_ray.engine.synthesis.limits import REFINE_CHECK_STEPS
from links_ray.engine.synthesis.refinement.kernels import _solve_tangents
from links_ray.engine.synthesis.target import Target, run_chamfer, target_chamfer, timed_distances

__all__ = [
    "Check",
    "below_margin",
    "check_mechanism",
    "coarse_trial",
    "least_deg",
    "solve_turn",
    "target_error",
    "valid_trial",
]

#: Each thread's scratch arrays of `solve_turn`, by shape; at most SCRATCH_SHAPES shapes are kept.
_SCRATCH = threading.local()
SCRATCH_SHAPES = 12


@dataclass(frozen=True)
class Check:
    """Validity of a position set at REFINE_CHECK_STEPS (`check_mechanism`).

    `lock`: (step, joint) of the first lock, or (-1, -1). `sides` (m,): each dyad's assembly
    branch sign. `min_transmission_sine` (m,): each dyad's least transmission sine over the
    check steps (sine of the transmission angle, 0 to 1; not degrees). `rigid` (m,) bool: the
    dyads whose parents keep their distance, so the angle at the joint never changes (no dead
    centre). `bounds` (4,): xmin, ymin, xmax, ymax of every joint over the check steps.
    """

    lock: tuple[int, int]
    sides: np.ndarray
    min_transmission_sine: np.ndarray
    rigid: np.ndarray
    bounds: np.ndarray


def solve_turn(
    topology: Topology,
    positions: np.ndarray,
    steps: int,
    tangents: bool,
    crank: np.ndarray | None = None,
) -> tuple[tuple[int, int], np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(lock, traj, dtraj, trans, dtrans, geometry) of `solve_tangents` at `steps` steps of a
    turn, or at the crank angles of `crank` (steps, 2) cos and sin (a timed target's).

    The arrays are the calling thread's scratch for this shape: valid until its next `solve_turn`
    of the same shape (an iteration makes one of each of three shapes, and allocating and
    paging in megabytes of derivatives anew each time would cost a share of every iteration).
    A turn's and a timed target's arrays are kept apart, as one iteration needs both."""
    n, m = topology.n_joints, len(topology.order)
    cols = 2 * n if tangents else 0
    key = (n, m, steps, cols, crank is not None)
    scratch = _SCRATCH.__dict__.setdefault("arrays", {})
    if key not in scratch:
        if len(scratch) >= SCRATCH_SHAPES:
            scratch.clear()
        scratch[key] = (
            np.empty((n, steps, 2)),
            np.empty((n, steps, 2, cols)),
            np.empty((m, steps)),
            np.empty((m, steps, cols)),
            np.empty((m, 3)),
        )
    traj, dtraj, trans, dtrans, geometry = scratch[key]
    check_buffer("positions", positions, (n, 2))
    if crank is not None:
        check_buffer("crank", crank, (steps, 2))
    # The kernel's own entry would check every buffer, three times an iteration: the scratch
    # is made here in the topology's shapes, and a Topology's solution path was checked when
    # it was made, so only the positions and the crank are the caller's.
    lock = _solve_tangents(
        topology.order,
        topology.fixed_joints,
        positions,
        crank_turn(steps) if crank is None else crank,
        traj,
        dtraj,
        trans,
        dtrans,
        geometry,
    )
    return (int(lock[0]), int(lock[1])), traj, dtraj, trans, dtrans, geometry


def check_mechanism(
    topology: Topology, positions: np.ndarray, rigid: np.ndarray | None = None
) -> Check:
    """Simulate `positions` (n, 2) at REFINE_CHECK_STEPS steps: lock, branch signs, least
    transmission sine per dyad, rigid dyads (found from the trajectories unless given:
    refinement decides them once). A lock is reported in the `Check`, not raised."""
    lock, traj, _, trans, _, geometry = solve_turn(topology, positions, REFINE_CHECK_STEPS, False)
    if lock[0] < 0:  # and between the steps: valid means it turns
        # The arrays `solve_turn` made and checked, unchecked again (`turning.turn_lock`).
        found = _turn_lock(topology.order, positions, geometry, traj, MAX_SPLITS)
        lock = (int(found[0]), int(found[1]))
    if rigid is None:
        # A rigid dyad (a triangle of links) keeps its angle: no dead centre, no margin.
        rigid = rigid_dyads(topology.order, traj)
    return Check(lock, geometry[:, 2].copy(), trans.min(axis=1), rigid, extent(traj))


def below_margin(check: Check, min_transmission_deg: float) -> Violation:
    """How far the checked dyads fall below a transmission margin: KEPT if none does, else a
    `Violation` named "min_transmission" whose total adds the dyads' shortfalls in sine and
    whose `by` is the degrees the least angle lacks."""
    margin = math.sin(math.radians(min_transmission_deg))
    shortfall = float(np.maximum(0.0, margin - check.min_transmission_sine).sum())
    if shortfall <= 0.0:
        return KEPT
    return Violation(
        shortfall, "min_transmission", min_transmission_deg - least_deg(check.min_transmission_sine)
    )


def least_deg(sines: np.ndarray) -> float:
    """The least angle in degrees of these transmission sines (90 with none)."""
    return math.degrees(math.asin(min(1.0, float(sines.min())))) if len(sines) else 90.0


def target_error(
    target: Target,
    topology: Topology,
    positions: np.ndarray,
    joint: int,
    path: np.ndarray,
    held: tuple[int, int] | None = None,
) -> tuple[float, tuple[int, int] | None]:
    """(value, interval) of the measure refinement lowers, in the drawing's units: for an
    untimed target `target_chamfer` of `path` (steps, 2), `joint`'s path over the turn; for a
    timed one the mean distance of each point from `joint`'s path at its crank angle. `held`
    (a partial target's run, as an untimed measure returns it): the chamfer of that run of
    `path` (`run_chamfer`: no search for the best run, and no less than its chamfer)."""
    if target.crank is None:
        if held is not None:
            return run_chamfer(target, path, held), held
        return target_chamfer(target, path)
    _, traj, _, _, _, _ = solve_turn(topology, positions, len(target.crank), False, target.crank)
    return float(timed_distances(target, traj[joint]).mean()), None


def coarse_trial(
    topology: Topology,
    trial: np.ndarray,
    turn: tuple[np.ndarray, np.ndarray, np.ndarray],
    sides: np.ndarray,
    floors: np.ndarray,
    rigid: np.ndarray,
) -> Check | None:
    """`valid_trial` read from the trial's own turn at the simulation's steps, which assembled
    (`turn`: its traj, trans and geometry from `solve_turn`), not from a turn at
    REFINE_CHECK_STEPS: a Check if its links, branches and margins hold at those steps, else
    None. Looser than `valid_trial`, never stricter: refinement confirms it with
    `check_mechanism` before any positions leave it."""
    traj, trans, geometry = turn
    if not _links_hold(topology, trial) or not np.array_equal(geometry[:, 2], sides):
        return None
    # `sides`, not the scratch's own column, which the next trial's turn overwrites.
    check = Check((-1, -1), sides, trans.min(axis=1), rigid, extent(traj))
    return check if _keeps(check, sides, floors) else None


def valid_trial(
    topology: Topology,
    trial: np.ndarray,
    sides: np.ndarray,
    floors: np.ndarray,
    rigid: np.ndarray,
) -> Check | None:
    """The trial's check if it is a valid step (links, lock, branches, margins), else None."""
    if not _links_hold(topology, trial):
        return None
    check = check_mechanism(topology, trial, rigid)
    return check if _keeps(check, sides, floors) else None


def _links_hold(topology: Topology, trial: np.ndarray) -> bool:
    """Whether the trial's links keep MIN_LINK_LENGTH (`inputs.check_positions`)."""
    try:
        check_positions(topology.adjacency, trial, topology.links)
    except InvalidMechanismError:
        return False
    return True


def _keeps(check: Check, sides: np.ndarray, floors: np.ndarray) -> bool:
    """Whether a checked trial turns, keeps its assembly branches and every dyad's floor."""
    return (
        check.lock[0] < 0
        and np.array_equal(check.sides, sides)
        and not np.any(check.min_transmission_sine < floors)
    )
