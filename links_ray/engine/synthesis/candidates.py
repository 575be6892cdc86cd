"""A retrieved mechanism on its way through synthesis's passes (`Candidate`): its best
positions so far, how it ranks, and one refinement of it.

Pure numpy/numba: no Ray.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np

from links_ray.engine.inputs import DEFAULT_STEPS, link_pairs
from links_ray.engine.kinematics.mechanism import LockingError, Topology, analyze_topology
from links_ray.engine.kinematics.solver import simulate
from links_ray.engine.synthesis.constraints import KEPT, Constraints, Violation, joined, violation
from links_ray.engine.synthesis.coupler_points import with_coupler_point
from links_ray.engine.synthesis.limits import check_refine_size
from links_ray.engine.synthesis.plan import RetrievalResult
from links_ray.engine.synthesis.refinement.checks import below_margin, check_mechanism, target_error
from links_ray.engine.synthesis.refinement.loop import DAMPING_START, Refinement, refine_validated
from links_ray.engine.synthesis.target import Target, target_chamfer
from links_ray.engine.synthesis.timing import best_start

__all__ = ["UNREFINED", "Candidate", "UnrefinedWhy", "candidate", "traced"]

#: Why a result is as retrieved (`Candidate.why_unrefined`): refinement ran on it and kept no
#: step (none lowered its measure and kept it valid); refinement refused its positions; the
#: work was called off first; the time budget was spent before its first iteration.
UnrefinedWhy = Literal["no_step", "cannot_refine", "stopped", "no_time"]
UNREFINED: tuple[str, ...] = get_args(UnrefinedWhy)

#: A rank no candidate is worse than: (misses the constraints, by infinitely much, error).
WORST_RANK = (True, float("inf"), float("inf"))


@dataclass(eq=False)  # candidates are the same only if they are one: `in` compares identities
class Candidate:
    """One retrieved mechanism on its way through the passes."""

    result: RetrievalResult  # the retrieval result it started from
    topology: Topology
    joint: int
    origin: np.ndarray  # the retrieved positions
    positions: np.ndarray  # the best so far
    error: float  # of `positions` against the pass's target (chamfer, or timed), in chords
    retrieved: float  # the chamfer of `origin`, divided by the chord
    interval: tuple[int, int] | None
    missed: Violation = KEPT  # of `positions`: the constraints they miss
    converged: bool = False
    damping: float = DAMPING_START  # where the last kept refinement of `positions` ended
    rounds: int = 0  # long-pass rounds it has had
    coupler_points: int = (
        0  # coupler points added to the retrieved mechanism (`engine.synthesis.coupler_points`)
    )
    parent: Candidate | None = None  # the candidate it was given a coupler point from
    branched: bool = False  # whether its coupler-point children have been made
    # What refinement did to it (`why_unrefined`): whether it kept a step (a coupler-point
    # child starts as its parent's), the iterations run on it, and whether a refinement of
    # its own positions was refused (it locks or is degenerate as refinement checks it).
    moved: bool = False
    iterations: int = 0
    refused: bool = False

    @property
    def retrieved_as(self) -> Candidate:
        """The candidate, as retrieved, that this one comes from (itself if it was retrieved)."""
        return self if self.parent is None else self.parent.retrieved_as

    def coupler_point_children(
        self,
        target: Target,
        constraints: Constraints | None,
        min_transmission_deg: float,
        offset: float,
        max_joints: int,
    ) -> list[Candidate]:
        """New candidates, each this one's best positions given a coupler point `offset`
        from the tracing joint, which traces instead, with at most `max_joints` joints
        (`engine.synthesis.coupler_points.with_coupler_point`); those that lock or cannot be traced
        are left out."""
        self.branched = True
        children = []
        for adjacency, node_types, positions in with_coupler_point(
            self.topology, self.positions, self.joint, offset, max_joints
        ):
            try:
                topology = analyze_topology(adjacency, node_types)
            except ValueError:
                continue
            child = _prepared(
                self.result,
                topology,
                positions,
                len(positions) - 1,
                target,
                constraints,
                min_transmission_deg,
            )
            if child is not None:
                child.retrieved = self.retrieved
                child.coupler_points = self.coupler_points + 1
                child.parent = self
                child.moved = self.moved  # it starts where its parent's refinement left it
                children.append(child)
        return children

    def rank(self) -> tuple[bool, float, float]:
        """Order of merit: keeping the constraints first, then missing them by less, then
        the error."""
        return (not self.missed.kept, self.missed.total, self.error)

    def refined(
        self,
        target: Target,
        start: np.ndarray,
        iterations: int,
        deadline: float | None,
        min_transmission_deg: float,
        weight_floor: float,
        constraints: Constraints | None,
        stop: threading.Event | None = None,
    ) -> Refinement | None:
        """`start` refined toward `target` for at most `iterations` iterations (from where
        the last kept refinement ended, when `start` is the best so far), or None if it is
        past `deadline`, `stop` is set, or the start locks or is degenerate."""
        late = deadline is not None and time.perf_counter() > deadline
        if late or (stop is not None and stop.is_set()):
            return None  # not even its checks of the start: they are 2,000-step turns
        try:
            return refine_validated(
                self.topology,
                start,
                self.joint,
                target,
                DEFAULT_STEPS,
                iterations,
                min_transmission_deg,
                deadline=deadline,
                origin=self.origin,
                damping=self.damping if start is self.positions else DAMPING_START,
                weight_floor=weight_floor,
                constraints=constraints,
                restore=True,
                stop=stop,
            )
        except (LockingError, ValueError):  # a shaken start that locks or is degenerate
            self.refused |= start is self.positions
            return None

    def keep(self, refinement: Refinement | None, iterations: int) -> bool:
        """Take `refinement` if it ranks better (`rank`) and `simulate` traces it at
        DEFAULT_STEPS; True if it did. Refinement checks its steps at REFINE_CHECK_STEPS: a
        dyad it leaves within a hair of its dead centre (one retrieved so, whose margin is half
        its own) can turn there and still be beyond what the check between 200 steps can
        prove. `iterations`: what it was given, to tell whether it converged."""
        if refinement is None:
            return False
        self.iterations += refinement.iterations
        missed = refinement.violation
        rank = (not missed.kept, missed.total, refinement.chamfer_after)
        if not rank < self.rank():
            return False
        if traced(self.topology, refinement.positions) is None:
            return False
        self.positions = refinement.positions
        self.error = refinement.chamfer_after
        self.missed = missed
        self.interval = refinement.interval
        self.damping = refinement.damping
        self.converged = refinement.iterations < iterations
        self.moved = True
        return True

    def why_unrefined(self, stopped: bool) -> UnrefinedWhy | None:
        """None if refinement kept a step of it; else why not (`UNREFINED`): no step it tried
        was kept, its refinement was refused, the work was called off (`stopped`) or the
        budget spent before its first iteration."""
        if self.moved:
            return None
        if self.iterations:
            return "no_step"
        if self.refused:
            return "cannot_refine"
        return "stopped" if stopped else "no_time"

    def start_timed(self, timed: Target) -> None:
        """Move along the turn to the start that suits the timing best, and measure by the
        timed error from now on."""
        topology, joint = self.topology, self.joint
        self.positions = best_start(topology, self.positions, joint, timed)
        path = simulate(topology.adjacency, topology.node_types, self.positions, DEFAULT_STEPS)
        value, _ = target_error(timed, topology, self.positions, joint, path[joint])
        self.error = value / timed.chord
        self.converged = False


def candidate(
    result: RetrievalResult,
    target: Target,
    constraints: Constraints | None,
    min_transmission_deg: float,
) -> Candidate | None:
    """A retrieval result ready to refine, with what it misses (the constraints, and the
    transmission margin `min_transmission_deg`, which refinement restores first), or None if it
    cannot be (it locks between the simulation's steps, or is too large to refine).

    The result's arrays are read as they are: its positions become the candidate's `origin`
    uncopied (refinement copies what it changes). A retriever answering lists works too."""
    mechanism = result["mechanism"]
    try:
        topology = analyze_topology(mechanism["adjacency"], mechanism["node_types"])
        positions = np.ascontiguousarray(mechanism["positions"], dtype=np.float64)
        joint = int(result["mechanism_joint"])
    except ValueError:
        return None
    return _prepared(result, topology, positions, joint, target, constraints, min_transmission_deg)


def _prepared(
    result: RetrievalResult,
    topology: Topology,
    positions: np.ndarray,
    joint: int,
    target: Target,
    constraints: Constraints | None,
    min_transmission_deg: float,
) -> Candidate | None:
    """`candidate` of a mechanism already analyzed: None if it locks between the simulation's
    steps or is too large to refine."""
    try:
        check_refine_size(topology.n_joints, DEFAULT_STEPS)
        check = check_mechanism(topology, positions)
        if check.lock[0] >= 0:
            return None
        path = traced(topology, positions)
    except ValueError:
        return None
    if path is None:
        return None
    value, interval = target_chamfer(target, path[joint])
    chamfer = value / target.chord
    missed = violation(
        constraints,
        positions,
        topology.fixed_joints,
        link_pairs(topology.adjacency),
        check.bounds,
        target.chord,
    )
    missed = joined(missed, below_margin(check, min_transmission_deg))
    return Candidate(
        result, topology, joint, positions, positions, chamfer, chamfer, interval, missed
    )


def traced(topology: Topology, positions: np.ndarray) -> np.ndarray | None:
    """Every joint's path at DEFAULT_STEPS as `simulate` (and so a result) traces it, or None
    if it finds a lock there or cannot rule one out between those steps."""
    try:
        return simulate(topology.adjacency, topology.node_types, positions, DEFAULT_STEPS)
    except LockingError:
        return None
