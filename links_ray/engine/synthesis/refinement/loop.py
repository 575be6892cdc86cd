"""Refinement: move a mechanism's joints so that one joint's path traces a drawn curve.

Retrieval finds a stored mechanism whose path is near a drawing; refinement then moves its
initial joint positions (which carry the placement, turn and scale too) to bring the path onto
the drawing, keeping the mechanism valid.

What is optimized. The measure is the chamfer distance (`engine.kinematics.paths.chamfer`) between
the drawn points and the path at the simulation's steps, divided by the drawing's longest chord. It
is a mean of nearest-point distances, so it is not smooth: the nearest point jumps. Each iteration
therefore fixes the correspondences, as ICP does (each path point's nearest drawn point, each drawn
point's nearest path point), and takes one damped Gauss-Newton (Levenberg-Marquardt) step on those
point pairs, weighted 1 / distance (iteratively reweighted least squares): at the current positions
the weighted sum of squares has the value and the gradient of the mean distance, so the step aims at
the chamfer itself rather than at its squares, and far outliers (parts of a drawing the mechanism
cannot reach) do not dominate. Pairs nearer than a floor weigh alike: a quarter of the current
chamfer (the floor follows the fit down), or a larger share of the chord if the caller asks
(`weight_floor`: synthesis's short pass does, to pull harder on the parts of a drawing the path is
far from). The exact derivatives of the path come from `refine_kernels.solve_tangents`.

The margin is a constraint, and steps slide along it. Each step is solved subject to the linearized
transmission sines at their lowest steps: those near a dyad's floor must stay CLEARANCE_DEG above
it, a rigid dyad's triangle as a moving dyad (`engine.synthesis.refinement.step`:
`transmission_guards`, solved by a small active set in `step_kernels`). A best fit often lies across
the margin; without the guards every step toward it would be refused and refinement would stop
there.

A step is kept only if the true chamfer falls and the mechanism stays valid: it turns fully at the
simulation's steps and at REFINE_CHECK_STEPS steps and between them (`engine.kinematics.turning`),
every joint keeps its assembly branch (the signs of `dyad_geometry`), its links keep
MIN_LINK_LENGTH, and every dyad keeps a transmission angle of at least the margin at every check
step (a dyad that starts below the margin keeps half its starting sine until it reaches the margin,
and the margin from then on; rigid dyads too, whose angle never changes: a triangle of bars
flattened toward a line no longer holds its joint). Otherwise the damping grows and a shorter step
is tried. So the chamfer never rises, and the result is valid whenever the input was. The check at
REFINE_CHECK_STEPS comes every FINE_EVERY kept steps and before positions are returned; until then a
step is checked at the simulation's steps (`refine_checks.coarse_trial`), and one the fine check
refuses sends refinement back to the last positions it passed.

A caller's own arrays go through the entry points (`engine.synthesis.refinement.entry`: `refine`,
`refine_many`), which check them. Synthesis (`engine.synthesis.pipeline`) drives refinement in
pieces through the interface below them: `as_target` validates a drawing once, `target_chamfer`
measures a path against it, `refine_validated` refines a validated mechanism within a deadline and
continues a refinement from its origin, and `engine.synthesis.refinement.checks.check_mechanism`
tells whether positions are valid.

Partial strokes (`partial=True`): an open stroke matches part of a turn. The measure is then the
least chamfer between the stroke and a run of consecutive steps (cyclic) of the path, over
every run; its start and length are returned. Finding that run costs more than the rest of a
trial, so trials are measured on the run last found (a chamfer no lower than the best run's)
and the run is searched again every RUN_EVERY kept steps, when no step gains on it, and
before positions are returned.

Pure numpy/numba: no Ray, no files.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass

import numpy as np

from links_ray.engine.kinematics.mechanism import LockingError, Topology
from links_ray.engine.synthesis.constraints import (
    KEPT,
    Constraints,
    Violation,
    guard_rows,
    joined,
    violation,
)
from links_ray.engine.synthesis.limits import REFINE_CHECK_STEPS
from links_ray.engine.synthesis.refinement.checks import (
    Check,
    below_margin,
    check_mechanism,
    coarse_trial,
    least_deg,
    solve_turn,
    target_error,
    valid_trial,
)
from links_ray.engine.synthesis.refinement.step import (
    IRLS_WEIGHT_FLOOR,
    guarded_step,
    normal_equations,
    timed_equations,
    transmission_guards,
)
from links_ray.engine.synthesis.target import Target

__all__ = ["Refinement", "refine_validated"]

#: A step may bring a dyad's least transmission angle at the simulation's steps no nearer its
#: floor than about this many degrees: the check steps between them dip lower.
CLEARANCE_DEG = 0.25
#: Refinement stops once the chamfer is below this share of the chord, or after STALL kept
#: steps in a row each gaining less than STALL_GAIN of it.
CONVERGED, STALL, STALL_GAIN = 1e-12, 5, 1e-8
#: Most a step moves any joint coordinate, per chord length of the drawing: the nearest-point
#: correspondences hold only nearby, and a long step lands among other local minima.
MAX_MOVE = 0.25
#: A dyad below the margin at the start keeps at least this share of its starting sine.
BELOW_MARGIN = 0.5
#: Restoring the margin (`refine_validated`'s `restore`), each step aims every dyad below it
#: this much higher in sine (about a degree), never past the margin.
RESTORE_STEP = 0.02
#: A kept step is checked at the simulation's steps alone (`refine_checks.coarse_trial`); every
#: FINE_EVERY kept steps, and before positions are returned, the last is checked at
#: REFINE_CHECK_STEPS (`check_mechanism`), and if it fails refinement goes back to the last
#: positions that passed and checks every step so from then on. The fine check costs as much
#: as the rest of an iteration, and the guards' clearance makes it fail rarely.
FINE_EVERY = 8
#: A partial stroke's best run (`target_chamfer`) costs more to find than the rest of a trial.
#: Between searches a trial is measured on the run last found (`run_chamfer`), never below the
#: best run's chamfer, so a kept step still lowers the measure; the run is searched again
#: every RUN_EVERY kept steps, when no step gains on it, and before positions are returned.
RUN_EVERY = 8
#: Damping (times the system's diagonal): start, growth on a rejected step, shrink on a kept
#: one, the least it shrinks to, the least it grows to on a rejection (below it a rejected step
#: barely shortens), and the end of trying. Steps stay damped (DAMPING_MIN): undamped
#: Gauss-Newton steps jump between the nearest-point correspondences' local minima.
DAMPING_START, DAMPING_UP, DAMPING_DOWN = 1.0, 4.0, 3.0
DAMPING_MIN, DAMPING_REJECTED, DAMPING_MAX = 1e-3, 1e-3, 1e8


@dataclass(frozen=True)
class Refinement:
    """The outcome of refining one mechanism.

    `positions` (n, 2) are the refined initial positions (the input's when no step helped).
    Chamfers are divided by the drawing's longest chord. `interval` is (start step, count) of
    the matched run for a partial stroke, else None. `min_transmission_deg` is the least
    transmission angle over the dyads and the check steps (90 without any).
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
    violation: Violation = KEPT


def refine_validated(
    topology: Topology,
    start: np.ndarray,
    joint: int,
    target: Target,
    steps: int,
    iterations: int,
    min_transmission_deg: float,
    deadline: float | None = None,
    origin: np.ndarray | None = None,
    damping: float = DAMPING_START,
    weight_floor: float = IRLS_WEIGHT_FLOOR,
    constraints: Constraints | None = None,
    restore: bool = False,
    stop: threading.Event | None = None,
) -> Refinement:
    """Refine a validated mechanism (`topology`, start positions (n, 2) float64, a moving
    `joint`) toward `target` at `steps` steps, for at most `iterations` iterations, keeping a
    transmission margin of `min_transmission_deg` degrees; `refine`'s checks of its input are the
    caller's. Raises LockingError if it locks as given.

    Stops once `time.perf_counter()` passes `deadline`: checked before each iteration, each
    damping trial and each trial's check at REFINE_CHECK_STEPS, so a refinement ends within
    one such piece of work of it (the last kept step stands; a trial cut short is not). `stop`,
    once set, ends it as a passed deadline does (its caller has called the work off). With
    `origin` (positions `start` was refined from), the transmission floors and the assembly
    branches are the origin's, so refining in several calls keeps what one call would; a
    `start` on other branches than `origin`, or below its floors, raises ValueError.
    `damping`: the damping to start at (a continued refinement's, which a fresh start at
    DAMPING_START would spend its first iterations shrinking again).

    `constraints` (in the target's frame): steps slide along them as along the margin. A start
    that misses them is first moved toward them, each step lowering the miss whatever it does
    to the fit; once they are kept, no step leaves them. The `Refinement`'s `violation` says
    what is still missed (nothing when kept).

    `restore`: a dyad below the margin is a miss too (`refine_checks.below_margin`), restored
    as the constraints are: each step aims every such dyad RESTORE_STEP higher in sine and
    must lower the misses, until none is left. Without it such a dyad only keeps
    BELOW_MARGIN of its start.
    """
    lock, traj, _, _, _, _ = solve_turn(topology, start, steps, False)
    if lock[0] >= 0:
        raise LockingError(*lock)
    value, interval = target_error(target, topology, start, joint, traj[joint])
    check = check_mechanism(topology, start)
    if check.lock[0] >= 0:
        error = LockingError(*check.lock)
        error.args = (
            f"mechanism locks between the simulation's steps: at step {check.lock[0]} of "
            f"{REFINE_CHECK_STEPS} joint {check.lock[1]} cannot be assembled",
        )
        raise error

    def late() -> bool:
        if stop is not None and stop.is_set():
            return True
        return deadline is not None and time.perf_counter() > deadline

    fixed, links = topology.fixed_joints, topology.links

    def missed_by(positions: np.ndarray, checked: Check) -> Violation:
        missed = violation(constraints, positions, fixed, links, checked.bounds, target.chord)
        return joined(missed, below_margin(checked, min_transmission_deg)) if restore else missed

    missed = missed_by(start, check)
    if late():  # the origin's check would be one more 2,000-step turn past the deadline
        least = least_deg(check.min_transmission_sine)
        return Refinement(
            start.copy(),
            value / target.chord,
            value / target.chord,
            interval,
            0,
            0,
            least,
            damping=damping,
            violation=missed,
        )
    margin = math.sin(math.radians(min_transmission_deg))
    clearance = math.sin(math.radians(min_transmission_deg + CLEARANCE_DEG)) - margin
    # Dyads keep the margin once they have it. One below it at the start may not fall under
    # BELOW_MARGIN of its starting sine: "not at all" would freeze it, as every step moves its
    # least angle a little. Rigid dyads (decided once, from the input) keep it alike: a
    # triangle of bars flattened toward a line no longer holds its joint, and a flat one turns
    # over onto the other branch.
    rigid = check.rigid
    first = check if origin is None else check_mechanism(topology, origin)
    # Every joint keeps the origin's assembly branch: a start shaken off it is no start.
    sides = first.sides
    if not np.array_equal(check.sides, sides):
        raise ValueError("the start is assembled on other branches than its origin")
    floors = np.where(
        first.min_transmission_sine >= margin, margin, BELOW_MARGIN * first.min_transmission_sine
    )
    if origin is not None:  # what the origin gained since, it keeps
        floors = np.where(check.min_transmission_sine >= margin, margin, floors)
        # A start shaken below the origin's margins is no start either: kept as it is, it
        # would hand back a mechanism nearer a dead centre than refinement allows.
        if np.any(check.min_transmission_sine < floors):
            raise ValueError("the start is nearer a dead centre than its origin allows")
    # Steps are guarded off every dyad's floor (a rigid dyad's derivatives are unbounded where
    # it is flat, too).
    before = value
    pos = start.copy()
    damping = min(max(damping, DAMPING_MIN), DAMPING_START)
    done = evaluations = stalled = 0
    # The last positions checked at REFINE_CHECK_STEPS, and the kept steps since.
    confirmed = (pos, value, interval, check, missed)
    unconfirmed, fine_every = 0, FINE_EVERY
    # A partial untimed target's trials hold `interval` (RUN_EVERY); `searched`: whether
    # (value, interval) are the best run's at `pos`, and `held`: kept steps since.
    holds = target.partial and target.crank is None
    searched, held = True, 0

    def search(path: np.ndarray) -> None:
        """The best run of `pos`'s `path` for (value, interval)."""
        nonlocal value, interval, searched, held
        value, interval = target_error(target, topology, pos, joint, path)
        searched, held = True, 0

    def confirmed_now() -> None:
        """The kept positions passed the check at REFINE_CHECK_STEPS (`check` is that
        check's): they are the last confirmed, and the dyads that reached the margin keep it."""
        nonlocal floors, confirmed, unconfirmed
        floors = np.where(check.min_transmission_sine >= margin, margin, floors)
        confirmed, unconfirmed = (pos, value, interval, check, missed), 0

    def confirm() -> bool:
        """Check the kept positions at REFINE_CHECK_STEPS: True (and they are confirmed) if
        they pass, else False (and refinement is back at the last confirmed)."""
        nonlocal pos, value, interval, check, missed, unconfirmed, searched
        fine = valid_trial(topology, pos, sides, floors, rigid)
        if fine is not None:
            fine_missed, was = missed_by(pos, fine), confirmed[4]
            # As a step checked so at once would have to: kept stays kept, a miss only falls.
            if fine_missed.kept or (not was.kept and fine_missed.total < was.total):
                check, missed = fine, fine_missed
                confirmed_now()
                return True
        pos, value, interval, check, missed = confirmed
        unconfirmed, searched = 0, False  # its run may have been held when it was confirmed
        return False

    while done < iterations and stalled < STALL:
        if late() or (missed.kept and value <= CONVERGED * target.chord):
            break
        done += 1
        _, traj, dtraj, trans, dtrans, _ = solve_turn(topology, pos, steps, True)
        if target.crank is None:
            hessian, gradient = normal_equations(
                target, traj[joint], dtraj[joint], interval, weight_floor
            )
        else:  # solved at the target's crank angles, in scratch of its own
            _, timed, dtimed, _, _, _ = solve_turn(
                topology, pos, len(target.crank), True, target.crank
            )
            hessian, gradient = timed_equations(target, timed[joint], dtimed[joint], weight_floor)
        aims = floors
        if restore:  # below the margin, a dyad's floor is where it is going
            low = floors < margin
            aims = np.where(
                low, np.minimum(margin, check.min_transmission_sine + RESTORE_STEP), floors
            )
        margins = transmission_guards(trans, dtrans, aims, clearance)
        kept = guard_rows(constraints, pos, fixed, links, traj, dtraj, target.chord)
        guards = (np.concatenate([margins[0], kept[0]]), np.concatenate([margins[1], kept[1]]))
        diagonal = np.diag(hessian).copy()
        # A joint the path does not depend on has a zero column; this keeps the system regular.
        diagonal += 1e-9 * max(float(diagonal.max()), 1e-300)
        accepted = False
        damping_before = damping
        while damping <= DAMPING_MAX:
            # A trial is a 200-step simulation and, if it gains, a 2,000-step check: on a large
            # mechanism a dozen rejected trials take longer than a synthesis may overrun.
            if late():
                break
            evaluations += 1
            trial = guarded_step(
                pos,
                hessian + damping * np.diag(diagonal),
                gradient,
                guards,
                MAX_MOVE * target.chord,
            )
            if trial is not None:
                lock, trial_traj, _, trial_trans, _, trial_geometry = solve_turn(
                    topology, trial, steps, False
                )
                if lock[0] < 0:
                    trial_turn = (trial_traj, trial_trans, trial_geometry)
                    # A stroke's trial is measured on the run held (RUN_EVERY).
                    trial_value, trial_interval = target_error(
                        target, topology, trial, joint, trial_traj[joint], interval
                    )
                    # Cheap tests first: most rejected trials fail on the fit. While the
                    # constraints are missed, a step need only miss them by less.
                    trial_check = None
                    if (trial_value < value or not missed.kept) and not late():
                        trial_check = (
                            valid_trial(topology, trial, sides, floors, rigid)
                            if fine_every == 1
                            else coarse_trial(topology, trial, trial_turn, sides, floors, rigid)
                        )
                    trial_missed = KEPT
                    if trial_check is not None:
                        trial_missed = missed_by(trial, trial_check)
                        if missed.kept:
                            gain = value - trial_value if trial_missed.kept else -1.0
                        else:
                            gain = (missed.total - trial_missed.total) * target.chord
                        if not gain > 0.0:
                            trial_check = None
                    if trial_check is not None:
                        restored = trial_missed.kept and not missed.kept
                        stalled = (
                            0 if restored or gain >= STALL_GAIN * target.chord else stalled + 1
                        )
                        pos, value, interval, check, missed = (
                            trial,
                            trial_value,
                            trial_interval,
                            trial_check,
                            trial_missed,
                        )
                        damping = max(damping / DAMPING_DOWN, DAMPING_MIN)
                        accepted = True
                        unconfirmed += 1
                        if holds:
                            searched, held = False, held + 1
                            if held >= RUN_EVERY:
                                search(trial_traj[joint])
                        if fine_every == 1:  # checked at REFINE_CHECK_STEPS already
                            confirmed_now()
                        elif unconfirmed >= fine_every and not confirm():
                            fine_every = 1
                        break
            damping = max(damping * DAMPING_UP, DAMPING_REJECTED)
        if not accepted:
            if holds and not searched and not late():
                run = interval
                search(traj[joint])  # `pos` has not moved this iteration
                if interval != run:  # another run fits best now: steps toward it may gain
                    damping = damping_before
                    continue
            break
    if unconfirmed:
        confirm()
    if holds and not searched:
        _, traj, _, _, _, _ = solve_turn(topology, pos, steps, False)
        search(traj[joint])
    return Refinement(
        positions=pos,
        chamfer_before=before / target.chord,
        chamfer_after=value / target.chord,
        interval=interval,
        iterations=done,
        evaluations=evaluations,
        min_transmission_deg=least_deg(check.min_transmission_sine),
        damping=damping,
        violation=missed,
    )
