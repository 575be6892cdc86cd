"""Refinement: move a mechanism's joints so that one joint's path traces a drawn curve.

Retrieval finds a stored mechanism whose path is near a drawing; `refine` then moves its
initial joint positions (which carry the placement, turn and scale too) to bring the path onto
the drawing, keeping the mechanism valid.

What is optimized. The measure is the chamfer distance (`engine.paths.chamfer`) between the
drawn points and the path at the simulation's steps, divided by the drawing's longest chord.
It is a mean of nearest-point distances, so it is not smooth: the nearest point jumps. Each
iteration therefore fixes the correspondences, as ICP does (each path point's nearest drawn
point, each drawn point's nearest path point), and takes one damped Gauss-Newton
(Levenberg-Marquardt) step on those point pairs, weighted 1 / distance (iteratively reweighted
least squares): at the current positions the weighted sum of squares has the value and the
gradient of the mean distance, so the step aims at the chamfer itself rather than at its squares,
and far outliers (parts of a drawing the mechanism cannot reach) do not dominate. The exact
derivatives of the path come from `refine_kernels.solve_tangents`.

The margin is a constraint, and steps slide along it. Each step is solved subject to the
linearized transmission sines at their lowest steps: those near a dyad's floor must stay
CLEARANCE_DEG above it, and a rigid dyad's triangle may not flatten (`_guards`, solved by a
small active set in `_constrained`). A best fit often lies across the margin; without the
guards every step toward it was refused and refinement stopped there (on the bench's letter D,
most of 32 candidates stopped within 150 iterations, their best at 0.0075; guarded, they run
on, their best at 0.0059).

A step is kept only if the true chamfer falls and the mechanism stays valid: it turns fully at
the simulation's steps and at REFINE_CHECK_STEPS steps and between them (`engine.turning`),
every joint keeps its assembly branch (the signs of `dyad_geometry`), its links keep
MIN_LINK_LENGTH, and every dyad keeps a transmission angle of at least the margin at every
check step (a dyad that starts below the margin keeps half its starting sine until it reaches
the margin, and the margin from then on; rigid dyads, whose angle never changes, have none).
Otherwise the damping grows and a shorter step is tried. So the chamfer never rises, and the
result is valid whenever the input was.

Partial strokes (`partial=True`): an open stroke matches part of a turn. The measure is then the
least chamfer between the stroke and a run of consecutive steps (cyclic) of the path, over
every run; its start and length are returned.

Pure numpy/numba: no Ray, no files.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from links_ray.engine.inputs import (
    DEFAULT_MARGIN_DEG,
    DEFAULT_REFINE_ITERATIONS,
    DEFAULT_STEPS,
    FIXED,
    MAX_REFINE_ITERATIONS,
    MIN_POINTS,
    REFINE_CHECK_STEPS,
    InvalidMechanismError,
    as_drawn_points,
    as_int,
    as_positions,
    as_transmission_deg,
    check_positions,
    check_refine_size,
)
from links_ray.engine.mechanism import LockingError, Topology, analyze_topology
from links_ray.engine.paths import chamfer, longest_chord
from links_ray.engine.refine_kernels import best_interval, nearest_pairs, solve_tangents
from links_ray.engine.solver import crank_turn
from links_ray.engine.turning import rigid_dyads, turn_lock

__all__ = ["Refinement", "check_mechanism", "refine", "refine_many"]

#: Distances below this share of the drawing's chord weigh as much as this (the IRLS floor).
IRLS_FLOOR = 1e-4
#: A step may bring a dyad's least transmission angle at the simulation's steps no nearer its
#: floor than about this many degrees: the check steps between them dip lower.
CLEARANCE_DEG = 0.25
#: Most rounds of the active set that keeps a step within its guards.
GUARD_ROUNDS = 12
#: Refinement stops once the chamfer is below this share of the chord, or after STALL kept
#: steps in a row each gaining less than STALL_GAIN of it.
CONVERGED, STALL, STALL_GAIN = 1e-12, 5, 1e-8
#: Most a step moves any joint coordinate, per chord length of the drawing: the nearest-point
#: correspondences hold only nearby, and a long step lands among other local minima.
MAX_MOVE = 0.25
#: A dyad below the margin at the start keeps at least this share of its starting sine.
BELOW_MARGIN = 0.5
#: Damping (times the system's diagonal): start, growth on a rejected step, shrink on a kept
#: one, the least it shrinks to, the least it grows to on a rejection (below it a rejected step
#: barely shortens), and the end of trying. Steps stay damped (DAMPING_MIN): undamped
#: Gauss-Newton steps jump between the nearest-point correspondences' local minima; measured on
#: perturbed four-bars, this recovers the exact curve about twice as often.
DAMPING_START, DAMPING_UP, DAMPING_DOWN = 1.0, 4.0, 3.0
DAMPING_MIN, DAMPING_REJECTED, DAMPING_MAX = 1e-3, 1e-3, 1e8


#: Each thread's scratch arrays of `_solve`, by shape; at most SCRATCH_SHAPES shapes are kept.
_SCRATCH = threading.local()
SCRATCH_SHAPES = 12


@dataclass(frozen=True)
class Refinement:
    """The outcome of refining one mechanism.

    `positions` (n, 2) are the refined initial positions (the input's when no step helped).
    Chamfers are divided by the drawing's longest chord. `interval` is (start step, count) of
    the matched run for a partial stroke, else None. `min_transmission_deg` is the least
    transmission angle over the non-rigid dyads and the check steps (90 without such dyads).
    `error` is set, and the rest is the input's, when a candidate of `refine_many` could not be
    refined (it locks). `damping` is where Levenberg-Marquardt's damping ended: a refinement
    continued from `positions` starts there.
    """

    positions: np.ndarray
    chamfer_before: float
    chamfer_after: float
    interval: tuple[int, int] | None
    iterations: int
    evaluations: int
    min_transmission_deg: float
    error: str | None = None
    damping: float = DAMPING_START


@dataclass(frozen=True)
class Check:
    """Validity of a position set at REFINE_CHECK_STEPS: lock (step, joint) or (-1, -1), the
    branch signs, the least transmission sine of each dyad, and which dyads are rigid (their
    parents keep their distance, so the angle at the joint never changes: no dead centre)."""

    lock: tuple[int, int]
    sides: np.ndarray
    min_transmission: np.ndarray
    rigid: np.ndarray


def _solve(
    topology: Topology, positions: np.ndarray, steps: int, tangents: bool
) -> tuple[tuple[int, int], np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(lock, traj, dtraj, trans, dtrans, geometry) of `solve_tangents` at `steps` steps.

    The arrays are the calling thread's scratch for this shape: valid until its next `_solve`
    of the same shape (an iteration makes one of each of three shapes, and allocating and
    paging in megabytes of derivatives anew each time cost a tenth of an iteration)."""
    n, m = topology.n_joints, len(topology.order)
    cols = 2 * n if tangents else 0
    key = (n, m, steps, cols)
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
    lock = solve_tangents(
        topology.order,
        topology.fixed_joints,
        positions,
        crank_turn(steps),
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
    """Simulate at REFINE_CHECK_STEPS steps: lock, branch signs, least transmission per dyad,
    rigid dyads (found from the trajectories unless given: refinement decides them once)."""
    lock, traj, _, trans, _, geometry = _solve(topology, positions, REFINE_CHECK_STEPS, False)
    if lock[0] < 0:  # and between the steps: valid means it turns
        lock = turn_lock(topology.order, positions, geometry, traj)
    if rigid is None:
        # A rigid dyad (a triangle of links) keeps its angle: no dead centre, no margin.
        rigid = rigid_dyads(topology.order, traj)
    return Check(lock, geometry[:, 2].copy(), trans.min(axis=1), rigid)


def _least_deg(sines: np.ndarray) -> float:
    return math.degrees(math.asin(min(1.0, float(sines.min())))) if len(sines) else 90.0


@dataclass
class _Target:
    """A validated drawing and its scale."""

    points: np.ndarray
    chord: float
    partial: bool


def _as_target(points: object, partial: object) -> _Target:
    if not isinstance(partial, bool | np.bool_):
        raise ValueError(f"partial must be True or False, got {partial!r}")
    drawn = as_drawn_points(points, "target_points")
    i, j = longest_chord(drawn)
    return _Target(drawn, float(np.hypot(*(drawn[j] - drawn[i]))), bool(partial))


def _measure(target: _Target, path: np.ndarray) -> tuple[float, tuple[int, int] | None]:
    """The true objective of a path (not yet divided by the chord) and the matched run."""
    if not target.partial:
        return chamfer(target.points, path), None
    start, count, _ = best_interval(path, target.points, MIN_POINTS)
    rows = (start + np.arange(count)) % len(path)
    # The exact chamfer of the chosen run, so accepted steps compare like with like.
    return chamfer(target.points, path[rows]), (int(start), int(count))


def _normal_equations(
    target: _Target,
    path: np.ndarray,
    jac: np.ndarray,
    interval: tuple[int, int] | None,
) -> tuple[np.ndarray, np.ndarray]:
    """IRLS Gauss-Newton system (A, g) of the chamfer with correspondences fixed at `path`.

    jac (steps, 2, P) is d path / d positions. Residuals of the two directions that land on
    the same path step are summed into one weight and one weighted residual per step.
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
    floor = IRLS_FLOOR * target.chord
    # Weight 1 / (count x distance): the weighted squares' gradient is the mean distance's.
    w_path = 1.0 / (count * np.maximum(path_d, floor))
    w_drawn = 1.0 / (points * np.maximum(drawn_d, floor))
    weight = w_path.copy()
    np.add.at(weight, drawn_nn, w_drawn)
    residual = w_path[:, None] * (sub - drawn[path_nn])
    np.add.at(residual, drawn_nn, w_drawn[:, None] * (sub[drawn_nn] - drawn))
    j = jac[rows]
    cols = j.shape[2]
    scaled = (j * np.sqrt(weight)[:, None, None]).reshape(-1, cols)
    return scaled.T @ scaled, residual.reshape(-1) @ j.reshape(-1, cols)


def _guards(
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


def _constrained(
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
    for _ in range(GUARD_ROUNDS):
        descent = c - q @ mu
        descent[on] = -np.inf
        entering = int(np.argmax(descent))
        if descent[entering] <= tolerance:
            break
        on[entering] = True
        while True:
            trial = np.zeros(len(rows))
            index = np.flatnonzero(on)
            trial[index] = np.linalg.solve(q[np.ix_(index, index)], c[index])
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
    return free + towards @ mu


def _step(
    pos: np.ndarray,
    system: np.ndarray,
    gradient: np.ndarray,
    guards: tuple[np.ndarray, np.ndarray],
    longest: float,
) -> np.ndarray | None:
    """pos + the damped Gauss-Newton step within the linearized guards, shortened to move no
    joint coordinate more than `longest`; None if the system cannot be solved."""
    try:
        delta = _constrained(system, gradient, *guards)
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(delta)):
        return None
    size = float(np.abs(delta).max())
    if size > longest:
        delta *= longest / size
    return pos + delta.reshape(pos.shape)


def _valid_trial(
    topology: Topology,
    trial: np.ndarray,
    sides: np.ndarray,
    floors: np.ndarray,
    rigid: np.ndarray,
) -> Check | None:
    """The trial's check if it is a valid step (links, lock, branches, margins), else None."""
    try:
        check_positions(topology.adjacency, trial)
    except InvalidMechanismError:
        return None
    check = check_mechanism(topology, trial, rigid)
    if check.lock[0] >= 0 or not np.array_equal(check.sides, sides):
        return None
    if np.any(check.min_transmission < floors):
        return None
    return check


def _prepare(
    adjacency: ArrayLike,
    node_types: ArrayLike,
    positions: ArrayLike,
    joint: object,
    steps: int,
) -> tuple[Topology, np.ndarray, int]:
    topology = analyze_topology(adjacency, node_types)
    n = topology.n_joints
    check_refine_size(n, steps)
    pos = as_positions(positions, n)
    check_positions(topology.adjacency, pos)
    joint = as_int("joint", joint, 0, n - 1, InvalidMechanismError)
    if topology.node_types[joint] == FIXED:
        raise InvalidMechanismError(f"joint {joint} is fixed: it traces no path to refine")
    return topology, pos, joint


def _refine_one(
    topology: Topology,
    start: np.ndarray,
    joint: int,
    target: _Target,
    steps: int,
    iterations: int,
    margin_deg: float,
    deadline: float | None = None,
    origin: np.ndarray | None = None,
    damping: float = DAMPING_START,
) -> Refinement:
    """Refine a validated mechanism; raises LockingError if it locks as given.

    Stops once `time.perf_counter()` passes `deadline`: checked before each iteration, each
    damping trial and each trial's check at REFINE_CHECK_STEPS, so a refinement ends within
    one such piece of work of it (the last kept step stands; a trial cut short is not). With
    `origin` (positions `start` was refined from), the transmission floors and the assembly
    branches are the origin's, so refining in several calls keeps what one call would; a
    `start` on other branches than `origin`, or below its floors, raises ValueError.
    `damping`: the damping to start at (a continued refinement's, which a fresh start at
    DAMPING_START would spend its first iterations shrinking again).
    """
    lock, traj, _, _, _, _ = _solve(topology, start, steps, False)
    if lock[0] >= 0:
        raise LockingError(*lock)
    value, interval = _measure(target, traj[joint])  # before `traj` is scratch again
    check = check_mechanism(topology, start)
    if check.lock[0] >= 0:
        error = LockingError(*check.lock)
        error.args = (
            f"mechanism locks between the simulation's steps: at step {check.lock[0]} of "
            f"{REFINE_CHECK_STEPS} joint {check.lock[1]} cannot be assembled",
        )
        raise error

    def late() -> bool:
        return deadline is not None and time.perf_counter() > deadline

    if late():  # the origin's check would be one more 2,000-step turn past the deadline
        least = _least_deg(check.min_transmission[~check.rigid])
        return Refinement(
            start.copy(),
            value / target.chord,
            value / target.chord,
            interval,
            0,
            0,
            least,
            damping=damping,
        )
    margin = math.sin(math.radians(margin_deg))
    clearance = math.sin(math.radians(margin_deg + CLEARANCE_DEG)) - margin
    # Dyads keep the margin once they have it. One below it at the start may not fall under
    # BELOW_MARGIN of its starting sine: "not at all" would freeze it, as every step moves its
    # least angle a little. Rigid dyads (decided once, from the input) have no margin: their
    # sines are >= 0 > -1.
    rigid = check.rigid
    first = check if origin is None else check_mechanism(topology, origin)
    # Every joint keeps the origin's assembly branch: a start shaken off it is no start.
    sides = first.sides
    if not np.array_equal(check.sides, sides):
        raise ValueError("the start is assembled on other branches than its origin")
    floors = np.where(
        rigid,
        -1.0,
        np.where(first.min_transmission >= margin, margin, BELOW_MARGIN * first.min_transmission),
    )
    if origin is not None:  # what the origin gained since, it keeps
        floors = np.where(~rigid & (check.min_transmission >= margin), margin, floors)
        # A start shaken below the origin's margins is no start either: kept as it is, it
        # would hand back a mechanism nearer a dead centre than refinement allows.
        if np.any(check.min_transmission < floors):
            raise ValueError("the start is nearer a dead centre than its origin allows")
    # Steps are guarded off every dyad's floor, and off flattening a rigid dyad: a triangle
    # of links flattened to a line turns over onto the other branch (which the check
    # refuses), and its derivatives are unbounded there.
    flat = np.minimum(margin, BELOW_MARGIN * first.min_transmission)
    before = value
    pos = start.copy()
    damping = min(max(damping, DAMPING_MIN), DAMPING_START)
    done = evaluations = stalled = 0

    while done < iterations and value > CONVERGED * target.chord and stalled < STALL:
        if late():
            break
        done += 1
        _, traj, dtraj, trans, dtrans, _ = _solve(topology, pos, steps, True)
        hessian, gradient = _normal_equations(target, traj[joint], dtraj[joint], interval)
        guards = _guards(trans, dtrans, np.where(rigid, flat, floors), clearance)
        diagonal = np.diag(hessian).copy()
        # A joint the path does not depend on has a zero column; this keeps the system regular.
        diagonal += 1e-9 * max(float(diagonal.max()), 1e-300)
        accepted = False
        while damping <= DAMPING_MAX:
            # A trial is a 200-step simulation and, if it gains, a 2,000-step check: on a large
            # mechanism a dozen rejected trials take longer than a synthesis may overrun.
            if late():
                break
            evaluations += 1
            trial = _step(
                pos,
                hessian + damping * np.diag(diagonal),
                gradient,
                guards,
                MAX_MOVE * target.chord,
            )
            if trial is not None:
                lock, trial_traj, _, _, _, _ = _solve(topology, trial, steps, False)
                if lock[0] < 0:
                    trial_value, trial_interval = _measure(target, trial_traj[joint])
                    # Cheap tests first: most rejected trials fail on the chamfer.
                    trial_check = (
                        _valid_trial(topology, trial, sides, floors, rigid)
                        if trial_value < value and not late()
                        else None
                    )
                    if trial_check is not None:
                        gain = value - trial_value
                        stalled = stalled + 1 if gain < STALL_GAIN * target.chord else 0
                        pos, value, interval, check = (
                            trial,
                            trial_value,
                            trial_interval,
                            trial_check,
                        )
                        gained = ~rigid & (check.min_transmission >= margin)
                        floors = np.where(gained, margin, floors)
                        damping = max(damping / DAMPING_DOWN, DAMPING_MIN)
                        accepted = True
                        break
            damping = max(damping * DAMPING_UP, DAMPING_REJECTED)
        if not accepted:
            break
    return Refinement(
        positions=pos,
        chamfer_before=before / target.chord,
        chamfer_after=value / target.chord,
        interval=interval,
        iterations=done,
        evaluations=evaluations,
        min_transmission_deg=_least_deg(check.min_transmission[~rigid]),
        damping=damping,
    )


def refine(
    adjacency: ArrayLike,
    node_types: ArrayLike,
    positions: ArrayLike,
    joint: int,
    target_points: ArrayLike,
    *,
    partial: bool = False,
    iterations: int = DEFAULT_REFINE_ITERATIONS,
    margin_deg: float = DEFAULT_MARGIN_DEG,
    steps: int = DEFAULT_STEPS,
) -> Refinement:
    """Move the joints of a mechanism so that `joint`'s path at `steps` crank steps traces
    `target_points` (in the mechanism's frame); the module docstring says how.

    `partial`: the points are an open stroke matched to part of a turn. `iterations`: most
    Levenberg-Marquardt iterations. `margin_deg`: least transmission angle kept. Raises
    `InvalidMechanismError` or `ValueError` for bad input and `LockingError` if the mechanism
    locks as given (at `steps` or REFINE_CHECK_STEPS steps).
    """
    steps = as_int("steps", steps, MIN_POINTS, None, InvalidMechanismError)
    topology, pos, joint = _prepare(adjacency, node_types, positions, joint, steps)
    target = _as_target(target_points, partial)
    iterations = as_int("iterations", iterations, 0, MAX_REFINE_ITERATIONS)
    margin_deg = as_transmission_deg(margin_deg)
    return _refine_one(topology, pos, joint, target, steps, iterations, margin_deg)


def refine_many(
    candidates: Iterable[Sequence[object]],
    target_points: ArrayLike,
    *,
    partial: bool = False,
    iterations: int = DEFAULT_REFINE_ITERATIONS,
    margin_deg: float = DEFAULT_MARGIN_DEG,
    steps: int = DEFAULT_STEPS,
) -> list[Refinement]:
    """`refine` for many candidates (adjacency, node_types, positions, joint) of one drawing.

    Every input is checked before any work, and a bad one raises ValueError naming the
    candidate. A candidate that locks as given gets a result with `error` set and its own
    positions, so one retrieved mechanism cannot sink the rest.
    """
    steps = as_int("steps", steps, MIN_POINTS, None, InvalidMechanismError)
    target = _as_target(target_points, partial)
    iterations = as_int("iterations", iterations, 0, MAX_REFINE_ITERATIONS)
    margin_deg = as_transmission_deg(margin_deg)
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
            results.append(_refine_one(topology, pos, joint, target, steps, iterations, margin_deg))
        except LockingError as exc:
            results.append(
                Refinement(pos, math.nan, math.nan, None, 0, 0, math.nan, error=str(exc))
            )
    return results
