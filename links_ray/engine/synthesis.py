"""Synthesis: mechanisms whose joint traces a drawn curve, found by retrieval and then refined.

`synthesize(index, points)` asks a retrieval index for the `CANDIDATES` stored paths nearest
the drawing (their mechanisms already placed in the drawing's frame), then refines them toward
the drawing itself (`engine.refine`) within a time budget:

1. A short pass: every candidate gets up to `FIRST_ITERATIONS` refinement iterations, in
   rounds of `FIRST_ROUND` over them all, within `FIRST_SHARE` of the time left. Retrieval
   ranks by normalized shape alone; a few iterations show which candidates can really move
   onto the curve. Their steps weigh the point pairs nearer than SHORT_IRLS_FLOOR alike,
   pulling harder toward the parts of the drawing a path is far from than the chamfer would.
2. A long pass: the best `LONG_PASS_CANDIDATES` after the first pass are refined on, in rounds
   of `LONG_ROUND` iterations, each continuing where the first pass left it (at the damping it
   ended with). One that converges gives its place to the next best of the first pass, until
   the budget is spent: the first pass ranks roughly, and the one that ends best is often
   well down its order.
3. Restarts: if every candidate has converged and time remains, the best are shaken (every
   joint moved by a random share of the drawing's chord, log-uniform in `SHAKE`) and refined
   again for at most `HOP_ITERATIONS`, keeping the shaken result only if it is better (a
   basin hop: the point-sampled chamfer has many local minima).

Refinements run in threads (the refinement kernels release the GIL), as many as the CPUs the
process was given (`engine.cpus.usable_cpus`). Every piece of work checks the deadline, so an
answer comes at most one damping trial past it. With `iterations` instead of a time budget
the passes count refinement iterations and run in lockstep rounds: a fixed amount of work,
whose answer is bit-equal for equal inputs whatever the time, the load and the threads.

What is measured. A result's `chamfer` is the bidirectional chamfer distance between the drawn
points and the path the result's `mechanism_joint` traces over a full crank turn at
`DEFAULT_STEPS` steps (for a partial stroke, over the run of steps that fits it best), divided
by the drawing's longest chord: for an unrefined retrieval result it equals retrieval's chamfer
between the normalized query and the normalized path. Every refined mechanism is valid as
`engine.refine` keeps it: it turns fully at `REFINE_CHECK_STEPS` steps, keeps its assembly
branches and its transmission margin.

`index` is anything with `retrieve(points, k, min_transmission) -> list[dict]` answering as
`links_ray.search.index.RetrievalIndex.retrieve` does (the engine imports no index). What
synthesis uses of refinement is `engine.refine`'s public interface (`as_target`,
`target_chamfer`, `refine_validated`, `check_mechanism`).

Pure numpy/numba and threads: no Ray, no files.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from links_ray.engine.constraints import KEPT, Violation, violation
from links_ray.engine.cpus import usable_cpus
from links_ray.engine.inputs import (
    DEFAULT_K,
    DEFAULT_MARGIN_DEG,
    DEFAULT_STEPS,
    Constraints,
    as_constraints,
    as_flag,
    as_max_joints,
    as_timing,
    as_transmission_deg,
    check_refine_size,
    link_pairs,
    validate_synthesis,
    validate_synthesis_work,
)
from links_ray.engine.mechanism import LockingError, Topology, analyze_topology
from links_ray.engine.refine import (
    DAMPING_START,
    IRLS_FLOOR,
    Refinement,
    Target,
    as_target,
    check_mechanism,
    refine_validated,
    target_chamfer,
    target_error,
)
from links_ray.engine.solver import simulate
from links_ray.engine.timing import best_start

__all__ = [
    "Retriever",
    "SynthesisResults",
    "fit",
    "pooled",
    "refine_retrieved",
    "retrievals",
    "synthesize",
]

#: Retrieved candidates the short pass refines.
CANDIDATES = 96
#: Iterations of the short pass, in rounds of FIRST_ROUND for every candidate, and the most
#: share of the budget it may take.
FIRST_ITERATIONS, FIRST_ROUND, FIRST_SHARE = 30, 10, 0.4
#: Candidates the long pass refines at a time (at least k), the best of the short pass first.
LONG_PASS_CANDIDATES = 3
#: Long-pass refinements run in rounds of LONG_ROUND iterations over the finalists.
LONG_ROUND = 50
#: Restarts move every joint by up to a share of the drawing's chord drawn log-uniformly
#: between these (the basin to leave may be narrow or wide), and refine for at most
#: HOP_ITERATIONS.
SHAKE = (0.003, 0.05)
HOP_ITERATIONS = 300
#: The short pass's IRLS floor (`refine_step.normal_equations`), a share of the drawing's chord:
#: its steps weigh every pair nearer than that alike, as least squares does, which pulls harder
#: on the parts of the drawing the path is far from; the long pass and restarts then weigh
#: pairs as the chamfer does (refine's default floor).
SHORT_IRLS_FLOOR = 0.15
#: Least seconds between two progress reports (the best so far) of one synthesis.
PROGRESS_INTERVAL_S = 0.2
#: A front also retrieves FRONT_CANDIDATES paths of at most each of these joint counts, so
#: that simple mechanisms are among the candidates even when complex ones match best.
FRONT_JOINTS, FRONT_CANDIDATES = (5, 6, 8), 24
#: With timing, the candidates the short pass leaves best go on, timed: choosing each one's
#: start costs a fine turn.
TIMED_CANDIDATES = 24


class SynthesisResults(list):
    """A synthesis's results (a list of result dicts, best first, or a front by joints), and
    `unmet`: when constraints were given and no candidate keeps them, {"constraint", "by"} of
    the candidate that came nearest (the most missed constraint, and by how much in its
    units), else None."""

    unmet: dict[str, Any] | None = None


class Retriever(Protocol):
    """What synthesis needs of a retrieval index."""

    def retrieve(
        self,
        points: object,
        k: int = DEFAULT_K,
        min_transmission: float = 0.0,
        max_joints: int | None = None,
    ) -> list[dict]:
        """The k best retrieval results for the drawn `points`, best first, among the paths
        keeping `min_transmission` degrees whose reduced mechanisms have at most `max_joints`
        joints, each with its mechanism in the drawing's frame."""
        ...


@dataclass(eq=False)  # candidates are the same only if they are one: `in` compares identities
class _Candidate:
    """One retrieved mechanism on its way through the passes."""

    result: dict  # the retrieval result it started from
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

    def rank(self) -> tuple[bool, float, float]:
        """Order of merit: keeping the constraints first, then missing them by less, then
        the error."""
        return (not self.missed.kept, self.missed.total, self.error)


def fit(
    points: object,
    positions: object,
    adjacency: object,
    node_types: object,
    joint: int,
    partial: bool = False,
) -> tuple[float, tuple[int, int] | None]:
    """(chamfer divided by the drawing's longest chord, interval) of the path `joint` traces
    at DEFAULT_STEPS steps against the drawn `points`; `interval` is (start step, count) of the
    run matched to a partial stroke, else None."""
    target = as_target(points, partial)
    path = simulate(adjacency, node_types, positions, DEFAULT_STEPS)[joint]
    value, interval = target_chamfer(target, path)
    return value / target.chord, interval


def _candidate(result: dict, target: Target, constraints: Constraints | None) -> _Candidate | None:
    """A retrieval result ready to refine, with the constraints it misses, or None if it
    cannot be (it locks between the simulation's steps, or is too large to refine)."""
    mechanism = result["mechanism"]
    try:
        topology = analyze_topology(mechanism["adjacency"], mechanism["node_types"])
        positions = np.ascontiguousarray(mechanism["positions"], dtype=np.float64)
        joint = int(result["mechanism_joint"])
        check_refine_size(topology.n_joints, DEFAULT_STEPS)
        check = check_mechanism(topology, positions)
        if check.lock[0] >= 0:
            return None
        path = _traced(topology, positions)
    except ValueError:
        return None
    if path is None:
        return None
    path = path[joint]
    value, interval = target_chamfer(target, path)
    chamfer = value / target.chord
    missed = violation(
        constraints,
        positions,
        topology.fixed_joints,
        link_pairs(topology.adjacency),
        check.bounds,
        target.chord,
    )
    return _Candidate(
        result, topology, joint, positions, positions, chamfer, chamfer, interval, missed
    )


def _refined(
    candidate: _Candidate,
    target: Target,
    start: np.ndarray,
    iterations: int,
    deadline: float | None,
    margin_deg: float,
    irls_floor: float,
    constraints: Constraints | None,
) -> Refinement | None:
    if deadline is not None and time.perf_counter() > deadline:
        return None  # not even its checks of the start: they are 2,000-step turns
    try:
        return refine_validated(
            candidate.topology,
            start,
            candidate.joint,
            target,
            DEFAULT_STEPS,
            iterations,
            margin_deg,
            deadline=deadline,
            origin=candidate.origin,
            damping=candidate.damping if start is candidate.positions else DAMPING_START,
            irls_floor=irls_floor,
            constraints=constraints,
        )
    except (LockingError, ValueError):  # a shaken start that locks or is degenerate
        return None


def _traced(topology: Topology, positions: np.ndarray) -> np.ndarray | None:
    """Every joint's path at DEFAULT_STEPS as `simulate` (and so a result) traces it, or None
    if it finds a lock there or cannot rule one out between those steps."""
    try:
        return simulate(topology.adjacency, topology.node_types, positions, DEFAULT_STEPS)
    except LockingError:
        return None


def _keep(candidate: _Candidate, refinement: Refinement | None, iterations: int) -> bool:
    """Take `refinement` if it ranks better (`_Candidate.rank`) and `simulate` traces it at
    DEFAULT_STEPS; True if it did. Refinement checks its steps at REFINE_CHECK_STEPS: a dyad
    it leaves within a hair of its dead centre (one retrieved so, whose margin is half its
    own) can turn there and still be beyond what the check between 200 steps can prove."""
    if refinement is None:
        return False
    missed = refinement.violation
    rank = (not missed.kept, missed.total, refinement.chamfer_after)
    if not rank < candidate.rank():
        return False
    if _traced(candidate.topology, refinement.positions) is None:
        return False
    candidate.positions = refinement.positions
    candidate.error = refinement.chamfer_after
    candidate.missed = missed
    candidate.interval = refinement.interval
    candidate.damping = refinement.damping
    candidate.converged = refinement.iterations < iterations
    return True


def refine_retrieved(
    points: object,
    retrieved: Sequence[dict],
    k: int = DEFAULT_K,
    seconds: float | None = None,
    partial: bool = False,
    *,
    started: float | None = None,
    seed: int = 0,
    margin_deg: float = DEFAULT_MARGIN_DEG,
    progress: Callable[[dict[str, Any]], None] | None = None,
    iterations: int | None = None,
    front: bool = False,
    constraints: object = None,
    timing: object = None,
) -> SynthesisResults:
    """The k best synthesis results (best first) refined from retrieval results of `points`
    (`RetrievalIndex.retrieve`'s, in the drawing's frame), keeping a transmission margin of
    at least DEFAULT_MARGIN_DEG and `margin_deg`. The module docstring says how.

    The work is bounded by time, or fixed. Timed: within `seconds` counted from `started` (a
    `time.perf_counter()` value; now if None); every piece of work checks the deadline, so the
    answer comes at most one damping trial past it (the first k retrieved are prepared
    whatever the time, so that there is an answer). Fixed (`iterations` given, `seconds`
    None): the passes stop after about `iterations` refinement iterations over all
    candidates, checked between rounds that run in lockstep, so the answer is the same bit
    for bit whatever the time, the machine's load and the threads. `seed` seeds the restarts.

    `progress`, if given, is called with the best so far whenever it has improved, at most
    every PROGRESS_INTERVAL_S (first with the best retrieved start): a result as the answer
    has them, with `trajectories` (every joint's path at DEFAULT_STEPS steps, to animate) and
    `elapsed_ms` besides. It runs in this thread, between rounds of refinement.

    `front`: the answer is, for each joint count among the candidates, the best result, and
    only those better than every simpler one, by joints ascending (k does not limit it).
    `constraints` (`inputs.as_constraints`): every result keeps them; if none can, the answer
    is empty and its `unmet` says which the nearest candidate misses, and by how much.
    `timing` (`inputs.as_timing`): the points are reached at those crank angles; the short
    pass fits the shape, then the start of each candidate is chosen (`timing.best_start`) and
    the rest refines and ranks by the timed error."""
    started = time.perf_counter() if started is None else started
    seconds, seed, iterations = validate_synthesis_work(seconds, seed, iterations)
    drawn, k, seconds, partial = validate_synthesis(points, k, seconds, partial)
    front = as_flag(front, "front")
    constraints = as_constraints(constraints)
    angles = as_timing(timing, len(drawn), partial)
    target = as_target(points, partial)
    timed = None if angles is None else target.timed(angles)
    measure = target  # the passes' target: the shape first, the timing from the long pass
    margin = max(DEFAULT_MARGIN_DEG, as_transmission_deg(margin_deg))
    fixed = iterations is not None
    # Fixed work has no deadline; its passes count iterations instead.
    deadline = math.inf if fixed else started + seconds
    spent = [0]  # refinement iterations so far (each attempt counts one at least)
    counting = threading.Lock()  # workers add to `spent` at once

    def until(end: float) -> float | None:
        return None if fixed else end

    def charge(refinement: Refinement | None) -> Refinement | None:
        with counting:
            spent[0] += max(1, refinement.iterations if refinement is not None else 0)
        return refinement

    def out_of(share: float, end: float) -> bool:
        """Whether this pass's work is done: its share of the iterations, or its time."""
        if fixed:
            return spent[0] >= share * iterations
        return time.perf_counter() >= end

    workers = max(1, min(usable_cpus(), len(retrieved)))
    with ThreadPoolExecutor(workers, thread_name_prefix="links-synthesize") as pool:

        def prepared(item: tuple[int, dict]) -> _Candidate | None:
            # Retrieval's first k, whatever the time: an answer needs them.
            place, result = item
            if place >= k and time.perf_counter() > deadline:
                return None
            return _candidate(result, target, constraints)

        found = pool.map(prepared, enumerate(retrieved))
        candidates = [c for c in found if c is not None]
        # The measure reported, when, and the best candidate's rank last looked at.
        reported_rank: tuple = (True, math.inf, math.inf)
        reported_at = -math.inf
        looked_at: tuple | None = None

        def report() -> None:
            nonlocal reported_rank, reported_at, looked_at
            now = time.perf_counter()
            if progress is None or not candidates or now - reported_at < PROGRESS_INTERVAL_S:
                return
            best = min(candidates, key=_Candidate.rank)
            best_rank = best.rank()
            if best_rank == looked_at:  # nothing kept since: no answer to measure
                return
            looked_at = best_rank
            # Measured from the positions read now (a worker may have moved them on since its
            # rank), by the answer's own measure (the timed error once timing ranks): the
            # reports must fall as the answer's measures do.
            answer = _as_result(best, target, timed, trajectories=True, elapsed=now - started)
            measured = answer["timed_error"] if timed is not None else answer["chamfer"]
            rank = (not best.missed.kept, best.missed.total, measured)
            if rank < reported_rank:
                reported_rank, reported_at = rank, now
                progress(answer)

        report()

        def short(c: _Candidate) -> None:
            refined = _refined(
                c,
                target,
                c.positions,
                FIRST_ROUND,
                until(first_end),
                margin,
                SHORT_IRLS_FLOOR,
                constraints,
            )
            if not _keep(c, charge(refined), FIRST_ROUND):  # no step helped: it will not move
                c.converged = True

        now = time.perf_counter()
        first_end = now + FIRST_SHARE * max(0.0, deadline - now) if not fixed else math.inf
        # In rounds, so that when time runs short every candidate has had as many iterations
        # (large mechanisms take many times as long per iteration as small ones).
        for _ in range(0, FIRST_ITERATIONS, FIRST_ROUND):
            moving = [c for c in candidates if not c.converged]
            if not moving or out_of(FIRST_SHARE, first_end):
                break
            list(pool.map(short, moving))
            report()
        if timed is not None:
            # The shape is near: the best TIMED_CANDIDATES (and a front's leaders) get their
            # start, and from here on the timing ranks them; the rest are dropped.
            candidates.sort(key=_Candidate.rank)
            leaders = _front(candidates) if front else []
            candidates = candidates[:TIMED_CANDIDATES] + [
                c for c in leaders if c not in candidates[:TIMED_CANDIDATES]
            ]
            list(pool.map(lambda c: _start_timed(c, timed), candidates))
            measure = timed
        candidates.sort(key=_Candidate.rank)
        # The long pass refines LONG_PASS_CANDIDATES at a time; one that converges makes room
        # for the next best after the short pass (whose ranking is rough: the one that ends
        # best is often well down it).
        waiting = list(candidates)
        quota = max(LONG_PASS_CANDIDATES, k)
        if front:
            # The front as the short pass leaves it goes first, all of it at once.
            leaders = _front(candidates)
            waiting = leaders + [c for c in candidates if c not in leaders]
            quota = max(quota, len(leaders))
        finalists: list[_Candidate] = []

        def long(c: _Candidate) -> None:
            refined = _refined(
                c,
                measure,
                c.positions,
                LONG_ROUND,
                until(deadline),
                margin,
                IRLS_FLOOR,
                constraints,
            )
            if not _keep(c, charge(refined), LONG_ROUND):
                c.converged = True

        def moving_finalists() -> list[_Candidate]:
            moving = [c for c in finalists if not c.converged]
            while len(moving) < quota and waiting:
                c = waiting.pop(0)
                c.converged = False  # a short round cut by its end is no sign of it
                finalists.append(c)
                moving.append(c)
            return moving

        if fixed:
            # Rounds in lockstep: every moving finalist refines once per round, whatever the
            # threads, so the same candidates get the same work.
            while not out_of(1.0, deadline):
                moving = moving_finalists()
                if not moving:
                    break
                list(pool.map(long, moving))
                for c in moving:
                    c.rounds += 1
                report()
        # In rounds too, the finalist with the fewest rounds next (one refined to the end would
        # leave the others none), and each worker takes the next round as it finishes one:
        # waiting for a round over all of them would idle a core, as a large finalist's round
        # takes many times a small one's.
        running: dict[Future[None], _Candidate] = {}
        while not fixed and time.perf_counter() < deadline:
            moving = moving_finalists()
            idle = [c for c in moving if c not in running.values()]
            idle.sort(key=lambda c: c.rounds)
            for c in idle[: workers - len(running)]:
                running[pool.submit(long, c)] = c
            if not running:
                break
            done, _ = wait(running, return_when=FIRST_COMPLETED)
            for future in done:
                future.result()
                running.pop(future).rounds += 1
            report()
        wait(running)  # rounds past the deadline stop within their damping trial under way
        rng = np.random.default_rng(seed)
        while not out_of(1.0, deadline) and finalists:
            # Each round shakes the current best ones: one per worker, or with fixed work as
            # many as the long pass refines (so the threads change nothing).
            finalists.sort(key=_Candidate.rank)
            chosen = finalists[: max(LONG_PASS_CANDIDATES if fixed else workers, k)]
            if front:
                chosen += [c for c in _front(finalists) if c not in chosen]
            shakes = np.exp(rng.uniform(*np.log(SHAKE), len(chosen))) * target.chord
            starts = [
                c.positions + rng.uniform(-1.0, 1.0, c.positions.shape) * shake
                for c, shake in zip(chosen, shakes, strict=True)
            ]

            def hop(c: _Candidate, start: np.ndarray) -> None:
                refined = _refined(
                    c,
                    measure,
                    start,
                    HOP_ITERATIONS,
                    until(deadline),
                    margin,
                    IRLS_FLOOR,
                    constraints,
                )
                _keep(c, charge(refined), 0)

            list(pool.map(hop, chosen, starts))
            report()
    candidates.sort(key=lambda c: (*c.rank(), c.result["path_id"]))
    kept = [c for c in candidates if c.missed.kept]
    answer = SynthesisResults(
        _as_result(c, target, timed) for c in (_front(kept) if front else kept[:k])
    )
    if candidates and not kept:
        nearest = candidates[0].missed
        answer.unmet = {"constraint": nearest.name, "by": nearest.by}
    return answer


def retrievals(k: int, max_joints: int | None, front: bool) -> list[tuple[int, int | None]]:
    """The retrievals a synthesis asks for, as (count, max_joints): CANDIDATES (at least k) of
    at most `max_joints` joints, and for a front FRONT_CANDIDATES more of each smaller count
    of FRONT_JOINTS; `pooled` joins their answers."""
    wanted: list[tuple[int, int | None]] = [(max(CANDIDATES, k), max_joints)]
    if front:
        wanted += [
            (FRONT_CANDIDATES, joints)
            for joints in FRONT_JOINTS
            if max_joints is None or joints < max_joints
        ]
    return wanted


def pooled(answers: Sequence[Sequence[dict]]) -> list[dict]:
    """The results of several retrievals (`retrievals`), each path once, in their order."""
    seen: set[int] = set()
    results = []
    for answer in answers:
        for result in answer:
            if result["path_id"] not in seen:
                seen.add(result["path_id"])
                results.append(result)
    return results


def _front(candidates: Sequence[_Candidate]) -> list[_Candidate]:
    """The best candidate of each joint count that ranks better than every simpler one's, by
    joints ascending."""
    best: dict[int, _Candidate] = {}
    for c in candidates:
        n = c.topology.n_joints
        if n not in best or c.rank() < best[n].rank():
            best[n] = c
    front: list[_Candidate] = []
    for n in sorted(best):
        if not front or best[n].rank() < front[-1].rank():
            front.append(best[n])
    return front


def _start_timed(candidate: _Candidate, timed: Target) -> None:
    """Move the candidate along its turn to the start that suits the timing best, and measure
    it by the timed error from now on."""
    topology, joint = candidate.topology, candidate.joint
    candidate.positions = best_start(topology, candidate.positions, joint, timed)
    path = simulate(topology.adjacency, topology.node_types, candidate.positions, DEFAULT_STEPS)
    value, _ = target_error(timed, topology, candidate.positions, joint, path[joint])
    candidate.error = value / timed.chord
    candidate.converged = False


def _as_result(
    candidate: _Candidate,
    target: Target,
    timed: Target | None = None,
    trajectories: bool = False,
    elapsed: float | None = None,
) -> dict[str, Any]:
    """A candidate as an answer (docs/reference/contract.md, HTTP API, describes it), with its
    `timed_error` against a `timed` target; a progress report adds every joint's
    `trajectories` and the `elapsed_ms` since the synthesis began."""
    topology = candidate.topology
    positions = candidate.positions
    path = simulate(topology.adjacency, topology.node_types, positions, DEFAULT_STEPS)
    value, interval = target_chamfer(target, path[candidate.joint])
    result = candidate.result
    answer: dict[str, Any] = {
        "path_id": result["path_id"],
        "mechanism_id": result["mechanism_id"],
        "chamfer": value / target.chord,
        "retrieved_chamfer": candidate.retrieved,
        "mechanism": {
            "adjacency": topology.adjacency.tolist(),
            "node_types": topology.node_types.tolist(),
            "positions": positions.tolist(),
        },
        "mechanism_joint": candidate.joint,
        "n_joints": topology.n_joints,
        "n_links": int(np.count_nonzero(np.triu(topology.adjacency, 1))),
        "path": path[candidate.joint].tolist(),
        "interval": None,
    }
    if timed is not None:
        error, _ = target_error(timed, topology, positions, candidate.joint, path[candidate.joint])
        answer["timed_error"] = error / timed.chord
    if interval is not None:
        start, count = interval
        answer["interval"] = {
            "start_step": start,
            "steps": count,
            "start_deg": 360.0 * start / DEFAULT_STEPS,
            "sweep_deg": 360.0 * (count - 1) / DEFAULT_STEPS,
        }
    if trajectories:
        answer["trajectories"] = path.tolist()
    if elapsed is not None:
        answer["elapsed_ms"] = round(elapsed * 1e3, 3)
    return answer


def synthesize(
    index: Retriever,
    points: object,
    k: int = DEFAULT_K,
    seconds: float | None = None,
    partial: bool = False,
    min_transmission: float = 0.0,
    progress: Callable[[dict[str, Any]], None] | None = None,
    *,
    max_joints: int | None = None,
    front: bool = False,
    constraints: object = None,
    timing: object = None,
    seed: int | None = None,
    iterations: int | None = None,
) -> SynthesisResults:
    """The k best mechanisms found for a drawn curve, best first, each refined so that its
    `mechanism_joint` traces `points` in the drawing's own frame, within `seconds` (default
    DEFAULT_SYNTHESIS_SECONDS, at most MAX_SYNTHESIS_SECONDS), retrieval included.
    `partial`: the points are an open stroke, matched to part of a turn. `min_transmission`
    (degrees): only paths keeping it are retrieved, and refinement keeps it as its margin (at
    least DEFAULT_MARGIN_DEG). `progress`: called with the best so far as it improves
    (`refine_retrieved` says how). `iterations` (instead of `seconds`): a fixed amount of
    work, about that many refinement iterations, whose answer is the same bit for bit for
    equal inputs whatever the time and the cores; `seed` (default 0) seeds the restarts.

    Design: `max_joints`, only mechanisms of at most that many joints (each result's
    `n_joints` counts its reduced mechanism's); `front`, the best of each joint count that
    beats every simpler one instead of the k best; `constraints` (pivots, footprint,
    max_link_ratio, min_link, max_link, in the drawing's units: `inputs.Constraints`), kept by
    every result, the answer's `unmet` saying so when no candidate can; `timing` (True: equal
    crank steps over a turn; or the crank angle of each point in degrees), the points reached
    at those angles from a free start, each result's `timed_error` measuring it.
    `refine_retrieved` says how. Raises ValueError naming bad input."""
    started = time.perf_counter()
    seconds, seed, iterations = validate_synthesis_work(seconds, seed, iterations)
    drawn, k, _, partial = validate_synthesis(points, k, seconds, partial)
    floor = as_transmission_deg(min_transmission, "min_transmission")
    max_joints = as_max_joints(max_joints)
    front = as_flag(front, "front")
    constraints = as_constraints(constraints)
    as_timing(timing, len(drawn), partial)  # refused before any retrieval
    retrieved = pooled(
        [
            index.retrieve(drawn, count, floor, most)
            for count, most in retrievals(k, max_joints, front)
        ]
    )
    return refine_retrieved(
        drawn,
        retrieved,
        k,
        seconds,
        partial,
        started=started,
        seed=seed,
        margin_deg=floor,
        progress=progress,
        iterations=iterations,
        front=front,
        constraints=constraints,
        timing=timing,
    )
