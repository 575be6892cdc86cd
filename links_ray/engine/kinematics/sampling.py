"""Random valid initial positions (paper, "Finding Valid Initial Positions").

Every position set obeys the dataset rules: joint 0 at (0.5, 0.5), joint 1 at (0.55, 0.5), every
other joint uniform in [0, 1]^2, and no lock over a full crank turn. Two samplers:

- ``rejection`` (the paper's): draw every joint at once, check the mechanism at 50 crank steps,
  then verify survivors at full resolution. A candidate costs only the steps it survives.
- ``sequential``: in solution order, draw each joint until its dyad can be assembled at every
  step given its parents' trajectories: ``|r1 - r2| <= min d(t)`` and ``max d(t) <= r1 + r2``
  for the distance d between the parents. A joint that finds no place after a few draws restarts
  the mechanism. It is far faster for large mechanisms, but its distribution differs from the
  rejection sampler's: joints drawn early are not conditioned on the ones after them.

Either way a set is valid only if the turn also assembles between the steps
(`engine.kinematics.turning`); one that fails there is a negative.

Both also keep some of the locking candidates they met (the dataset's negatives).

Pure numpy/numba: no Ray.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numba import njit

from links_ray.engine.inputs import DEFAULT_STEPS, as_int
from links_ray.engine.kinematics.mechanism import CRANK_CENTER, CRANK_TIP, Topology
from links_ray.engine.kinematics.solver import (
    CHECK_BLOCK,
    TopologySimulator,
    _dyad_geometry,
    _place_crank,
    _place_fixed,
    _simulate_one,
    _simulate_turn,
    _solve_span,
    dyad_fails,
)
from links_ray.engine.kinematics.topology import SeedLike, grow_topology
from links_ray.engine.kinematics.turning import _turn_lock

Sampler = Literal["sequential", "rejection"]
SAMPLERS: tuple[str, ...] = ("sequential", "rejection")
#: Crank steps of the rejection sampler's cheap first check (the paper's figure).
LOW_FIDELITY_STEPS = 50
#: Draws of one joint before the sequential sampler restarts the mechanism.
DRAWS_PER_JOINT = 32
#: Candidates (rejection) or restarts (sequential) before giving up on a topology.
DEFAULT_MAX_CANDIDATES = 2_000_000


class PositionSearchError(RuntimeError):
    """No `count` valid position sets were found within the search's budget."""


@dataclass(frozen=True)
class PositionSearch:
    """The outcome of a position search for one topology."""

    positions: np.ndarray  # (count, n, 2) valid initial positions
    trajectories: np.ndarray  # (count, n, steps, 2) their simulations
    candidates: int  # complete position sets tried (rejection) or attempts begun (sequential)
    negatives: np.ndarray  # (k, n, 2) locking candidates met on the way
    negative_step: np.ndarray  # (k,) first locking step at full resolution
    negative_node: np.ndarray  # (k,) joint that cannot be assembled there

    @property
    def candidates_per_valid(self) -> float:
        """`candidates` over the valid position sets found (ZeroDivisionError if none)."""
        return self.candidates / len(self.positions)


@njit(cache=True, nogil=True)
def _seed_numba(seed: int) -> None:
    np.random.seed(seed)


_CRANK_POSE = np.array([CRANK_CENTER, CRANK_TIP])


@njit(cache=True, nogil=True)
def _place_crank_and_ground(fixed: np.ndarray, pos: np.ndarray) -> None:
    """The dataset's crank pose, and every fixed joint but joint 0 uniform in [0, 1]^2."""
    pos[:2] = _CRANK_POSE
    for i in range(fixed.shape[0]):
        if fixed[i] != 0:
            pos[fixed[i], 0] = np.random.random()
            pos[fixed[i], 1] = np.random.random()


@njit(cache=True, nogil=True)
def _rejection_kernel(
    order: np.ndarray,
    fixed: np.ndarray,
    crank_low: np.ndarray,
    crank: np.ndarray,
    max_candidates: int,
    positions: np.ndarray,
    trajectories: np.ndarray,
    negatives: np.ndarray,
) -> tuple[int, int]:
    """Fill `positions`/`trajectories` with valid sets; returns (found, candidates, kept)."""
    n = positions.shape[1]
    geometry = np.empty((order.shape[0], 3))
    scratch = np.empty((n, CHECK_BLOCK, 2))
    pos = np.empty((n, 2))
    found = kept = candidates = 0
    while found < positions.shape[0] and candidates < max_candidates:
        candidates += 1
        _place_crank_and_ground(fixed, pos)
        for k in range(order.shape[0]):
            pos[order[k, 0], 0] = np.random.random()
            pos[order[k, 0], 1] = np.random.random()
        step, _ = _simulate_one(order, fixed, pos, crank_low, False, scratch, geometry)
        if step < 0:
            step, _ = _simulate_turn(order, fixed, pos, crank, trajectories[found], geometry)
        if step < 0:
            positions[found] = pos
            found += 1
        elif kept < negatives.shape[0]:
            negatives[kept] = pos
            kept += 1
    return found, candidates, kept


@njit(cache=True, nogil=True)
def _sequential_kernel(
    order: np.ndarray,
    fixed: np.ndarray,
    crank: np.ndarray,
    draws_per_joint: int,
    max_attempts: int,
    positions: np.ndarray,
    trajectories: np.ndarray,
    negatives: np.ndarray,
    negative_joint: np.ndarray,
) -> tuple[int, int]:
    """Fill `positions`/`trajectories` joint by joint; returns (found, attempts, kept).

    A kept negative holds the joints placed so far plus the rejected draw; the joints after it
    (`negative_joint` gives the solution-path index of the rejected one) are left for the caller
    to draw.
    """
    n = positions.shape[1]
    steps = crank.shape[0]
    geometry = np.empty((order.shape[0], 3))
    whole = np.empty((order.shape[0], 3))  # every dyad's, for the check between steps
    pos = np.empty((n, 2))
    found = kept = attempts = 0
    while found < positions.shape[0] and attempts < max_attempts:
        attempts += 1
        traj = trajectories[found]
        _place_crank_and_ground(fixed, pos)
        _place_fixed(fixed, pos, traj, steps)
        _place_crank(pos, crank, traj, 0, steps, 0)
        placed_all = True
        for k in range(order.shape[0]):
            j, a, b = order[k, 0], order[k, 1], order[k, 2]
            # Extremes of the parents' squared distance over the turn.
            d_sq_min, d_sq_max = np.inf, 0.0
            for t in range(steps):
                dx = traj[b, t, 0] - traj[a, t, 0]
                dy = traj[b, t, 1] - traj[a, t, 1]
                d_sq = dx * dx + dy * dy
                d_sq_min = min(d_sq_min, d_sq)
                d_sq_max = max(d_sq_max, d_sq)
            placed = False
            for _ in range(draws_per_joint):
                pos[j, 0] = np.random.random()
                pos[j, 1] = np.random.random()
                _dyad_geometry(order[k : k + 1], pos, geometry)
                r1, r2 = geometry[0, 0], geometry[0, 1]
                # Exactly the lock test of the solver, at the extremes of the parents' distance.
                if not (dyad_fails(d_sq_max, r1, r2) or dyad_fails(d_sq_min, r1, r2)):
                    placed = _solve_span(traj, j, a, b, r1, r2, geometry[0, 2], 0, steps) == 0
                if placed:
                    break
                if kept < negatives.shape[0]:
                    negatives[kept] = pos
                    negative_joint[kept] = k
                    kept += 1
            if not placed:
                placed_all = False
                break
        if placed_all:
            # Every dyad assembles at every step; the turn must also pass between them.
            _dyad_geometry(order, pos, whole)
            if _turn_lock(order, pos, whole, traj)[0] < 0:
                positions[found] = pos
                found += 1
            elif kept < negatives.shape[0]:
                negatives[kept] = pos
                negative_joint[kept] = order.shape[0] - 1
                kept += 1
    return found, attempts, kept


@njit(cache=True, nogil=True)
def _complete_negatives(
    order: np.ndarray, negative_joint: np.ndarray, draws: np.ndarray, negatives: np.ndarray
) -> None:
    """Place the joints after `order` row negative_joint[i] of each negative i at the next
    rows of `draws`, negative by negative and in solving order."""
    row = 0
    for i in range(negatives.shape[0]):
        for k in range(negative_joint[i] + 1, order.shape[0]):
            negatives[i, order[k, 0], 0] = draws[row, 0]
            negatives[i, order[k, 0], 1] = draws[row, 1]
            row += 1


class PositionSampler:
    """Draws valid initial positions for one topology; reuses its compiled simulator."""

    def __init__(self, simulator: TopologySimulator, steps: int = DEFAULT_STEPS) -> None:
        self.simulator = simulator
        self.steps = steps

    @property
    def topology(self) -> Topology:
        """The validated topology whose positions are drawn."""
        return self.simulator.topology

    def search(
        self,
        count: int,
        rng: np.random.Generator,
        sampler: Sampler = "sequential",
        *,
        max_negatives: int = 0,
        max_candidates: int = DEFAULT_MAX_CANDIDATES,
    ) -> PositionSearch:
        """Find `count` valid position sets, keeping up to `max_negatives` locking candidates."""
        if sampler not in SAMPLERS:
            raise ValueError(f"sampler must be one of {', '.join(SAMPLERS)}, got {sampler!r}")
        count = as_int("count", count, 1)
        topology = self.topology
        n, steps = topology.n_joints, self.steps
        positions = np.empty((count, n, 2))
        trajectories = np.empty((count, n, steps, 2))
        negatives = np.empty((max_negatives, n, 2))
        crank = self.simulator.crank(steps)
        _seed_numba(int(rng.integers(2**32)))
        if sampler == "rejection":
            low = self.simulator.crank(min(LOW_FIDELITY_STEPS, steps))
            found, candidates, kept = _rejection_kernel(
                topology.order,
                topology.fixed_joints,
                low,
                crank,
                max_candidates,
                positions,
                trajectories,
                negatives,
            )
            negatives = negatives[:kept]
        else:
            negative_joint = np.empty(max_negatives, dtype=np.int64)
            found, candidates, kept = _sequential_kernel(
                topology.order,
                topology.fixed_joints,
                crank,
                DRAWS_PER_JOINT,
                max_candidates,
                positions,
                trajectories,
                negatives,
                negative_joint,
            )
            negatives = negatives[:kept]
            # Complete each partial negative with uniform draws for the joints after it: one
            # draw for all, in the order of a draw per negative (the stream is the same).
            later = len(topology.order) - 1 - negative_joint[:kept]
            _complete_negatives(
                topology.order, negative_joint, rng.random((later.sum(), 2)), negatives
            )
        if found < count:
            raise PositionSearchError(
                f"found {found} of {count} valid position sets in {candidates} "
                f"{'candidates' if sampler == 'rejection' else 'attempts'}; "
                "the topology may be nearly impossible to assemble"
            )
        lock_step, lock_node = self.simulator.lock_check(negatives, steps)
        # A candidate that failed only between the coarse steps' rounding is not a negative.
        locks = lock_step >= 0
        return PositionSearch(
            positions=positions,
            trajectories=trajectories,
            candidates=int(candidates),
            negatives=negatives[locks],
            negative_step=lock_step[locks],
            negative_node=lock_node[locks],
        )


def sample_positions(
    adjacency: np.ndarray,
    node_types: np.ndarray,
    count: int = 5,
    seed: SeedLike = None,
    sampler: Sampler = "sequential",
) -> np.ndarray:
    """`count` distinct valid initial positions (count, n, 2) obeying the dataset rules."""
    simulator = TopologySimulator(adjacency, node_types)
    rng = np.random.default_rng(seed)
    return PositionSampler(simulator).search(count, rng, sampler).positions


def measure_candidates_per_valid(
    sizes: range,
    topologies_per_size: int,
    count: int,
    rng: np.random.Generator,
    sampler: Sampler = "rejection",
    max_candidates: int = DEFAULT_MAX_CANDIDATES,
) -> dict[int, dict[str, float]]:
    """Candidates tried per valid position set, and valid sets per second, by joint count.

    Draws `topologies_per_size` random topologies of each size and finds `count` valid sets for
    each; a topology that exhausts `max_candidates` counts them all and is abandoned.
    """
    result = {}
    for n in sizes:
        start = time.perf_counter()
        candidates = valid = abandoned = 0
        for _ in range(topologies_per_size):
            simulator = TopologySimulator.from_topology(grow_topology(rng, n))
            try:
                found = PositionSampler(simulator).search(
                    count, rng, sampler, max_candidates=max_candidates
                )
                candidates += found.candidates
                valid += count
            except PositionSearchError:
                candidates += max_candidates
                abandoned += 1
        elapsed = time.perf_counter() - start
        result[n] = {
            "candidates_per_valid": candidates / valid if valid else float("inf"),
            "valid_per_second": valid / elapsed,
            "abandoned": abandoned,
        }
    return result
