"""Synthesis's passes over the retrieved candidates, within a budget (`engine.synthesis.budget`):

1. A short pass: every candidate gets up to `FIRST_ITERATIONS` refinement iterations, in
   rounds of `FIRST_ROUND` over them all, within `FIRST_SHARE` of the work left. Retrieval
   ranks by normalized shape alone; a few iterations show which candidates can really move
   onto the curve. Their steps weigh the point pairs nearer than SHORT_WEIGHT_FLOOR alike,
   pulling harder toward the parts of the drawing a path is far from than the chamfer would.
2. A middle pass: the best `MIDDLE_CANDIDATES` after it get up to `MIDDLE_ITERATIONS` more, in
   rounds of FIRST_ROUND, by the chamfer's own weights, until `MIDDLE_END` of the budget is
   spent: ten iterations rank roughly, and the long pass takes only a few at a time.
3. A long pass: the best `LONG_PASS_CANDIDATES` after the middle pass are refined on, in rounds
   of `LONG_ROUND` iterations, each continuing where the first pass left it (at the damping it
   ended with). One that converges gives its place to the next best of the first pass, until
   the budget is spent: the first pass ranks roughly, and the one that ends best is often
   well down its order.
4. Restarts: if every candidate has converged and work remains, the best are shaken (every
   joint moved by a random share of the drawing's chord, log-uniform in `SHAKE`) and refined
   again for at most `HOP_ITERATIONS`, keeping the shaken result only if it is better (a
   basin hop: the point-sampled chamfer has many local minima).

Refinements run in threads (the refinement kernels release the GIL). A `TimeBudget` gives
every piece of work the deadline, so an answer comes at most one damping trial past it; an
`IterationBudget` counts refinement iterations and runs rounds in lockstep, so that its answer
is bit-equal for equal inputs whatever the time, the load and the threads.

Pure numpy/numba and threads: no Ray.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from concurrent.futures import ALL_COMPLETED, FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from typing import Any

import numpy as np

from links_ray.engine.inputs import DEFAULT_MIN_TRANSMISSION_DEG
from links_ray.engine.synthesis.budget import Budget
from links_ray.engine.synthesis.candidates import WORST_RANK, Candidate, candidate
from links_ray.engine.synthesis.coupler_points import COUPLER_POINT_MAX_JOINTS
from links_ray.engine.synthesis.kit_layers import LayerCounts, layer_deadline, plans_layers
from links_ray.engine.synthesis.options import SynthesisOptions
from links_ray.engine.synthesis.pareto import pareto_front
from links_ray.engine.synthesis.plan import RetrievalResult
from links_ray.engine.synthesis.refinement.step import IRLS_WEIGHT_FLOOR
from links_ray.engine.synthesis.results import SynthesisResults, as_result
from links_ray.engine.synthesis.target import Target

__all__ = ["Progress", "SynthesisPasses"]

#: Iterations of the short pass, in rounds of FIRST_ROUND for every candidate, and the most
#: share of the budget it may take.
FIRST_ITERATIONS, FIRST_ROUND, FIRST_SHARE = 30, 10, 0.4
#: The middle pass: candidates, iterations each (in rounds of FIRST_ROUND), and the share of
#: the whole budget spent by which it ends.
MIDDLE_CANDIDATES, MIDDLE_ITERATIONS, MIDDLE_END = 24, 30, 0.7
#: Candidates the long pass refines at a time (at least k), the best after the middle pass
#: first.
LONG_PASS_CANDIDATES = 3
#: Long-pass refinements run in rounds of LONG_ROUND iterations over the finalists.
LONG_ROUND = 50
#: Restarts move every joint by up to a share of the drawing's chord drawn log-uniformly
#: between these (the basin to leave may be narrow or wide), and refine for at most
#: HOP_ITERATIONS.
SHAKE = (0.003, 0.05)
HOP_ITERATIONS = 300
#: The short pass's IRLS weight floor (`refine_step.normal_equations`), a share of the
#: drawing's chord: its steps weigh every pair nearer than that alike, as least squares does,
#: which pulls harder on the parts of the drawing the path is far from; the long pass and
#: restarts then weigh pairs as the chamfer does (IRLS_WEIGHT_FLOOR).
SHORT_WEIGHT_FLOOR = 0.15
#: The polish: once no more than POLISH_LEFT of the budget is left, the best candidate alone
#: goes on, and whenever it has converged it is given a coupler point on a link of its tracing
#: joint (`engine.synthesis.coupler_points`) COUPLER_POINT_OFFSET of the drawing's chord from
#: it, at most MAX_COUPLER_POINTS times along one line of descent.
POLISH_LEFT, COUPLER_POINT_OFFSET, MAX_COUPLER_POINTS = 0.2, 0.02, 3
#: Least seconds between two progress reports (the best so far) of one synthesis.
PROGRESS_INTERVAL_S = 0.2
#: With timing, the candidates the short pass leaves best go on, timed: choosing each one's
#: start costs a fine turn.
TIMED_CANDIDATES = 24

#: Called with the best so far, as a result with `trajectories` and `elapsed_ms`.
Progress = Callable[[dict[str, Any]], None]


class SynthesisPasses:
    """One synthesis's candidates and the passes that refine them (the module says how), run
    on `pool`'s `workers` threads within `budget`. Its state is explicit: `candidates` (all
    still in the running), `finalists` (those the long pass took), `measure` (the target the
    passes lower: the shape, then the timing once the candidates are timed)."""

    def __init__(
        self,
        options: SynthesisOptions,
        target: Target,
        budget: Budget,
        pool: ThreadPoolExecutor,
        workers: int,
        progress: Progress | None,
        started: float,
    ) -> None:
        self.options = options
        self.target = target
        angles = options.timing_angles(len(target.points))
        self.timed = None if angles is None else target.timed(angles)
        self.measure = target
        self.budget = budget
        self.pool = pool
        self.workers = workers
        # Refinement keeps at least DEFAULT_MIN_TRANSMISSION_DEG, whatever the request asked for.
        self.min_transmission_deg = max(DEFAULT_MIN_TRANSMISSION_DEG, options.min_transmission_deg)
        self.candidates: list[Candidate] = []
        self.finalists: list[Candidate] = []
        self.progress = progress
        self.started = started
        self.polishing = False  # whether the best alone goes on (`polish`)
        self.stopped: set[int] = set()  # ids of the finalists the polish stopped
        # The measure reported, when, and the best candidate's rank last looked at.
        self._reported_rank: tuple = WORST_RANK
        self._reported_at = -math.inf
        self._looked_at: tuple | None = None

    def run(self, retrieved: list[RetrievalResult]) -> SynthesisResults:
        """Every pass over the `retrieved` results, and the answer."""
        self.prepare(retrieved)
        self.report()
        self.short_pass()
        if self.timed is not None:
            self.time_candidates(self.timed)
        self.middle_pass()
        self.candidates.sort(key=Candidate.rank)
        self.long_pass()
        self.restarts()
        return self.answer()

    def prepare(self, retrieved: list[RetrievalResult]) -> None:
        """The retrieved results as candidates: retrieval's first k whatever the budget (an
        answer needs them), the rest while it lasts."""
        k, target, constraints = self.options.k, self.target, self.options.constraints

        def prepared(item: tuple[int, RetrievalResult]) -> Candidate | None:
            place, result = item
            if place >= k and self.budget.expired():
                return None
            return candidate(result, target, constraints, self.min_transmission_deg)

        found = self.pool.map(prepared, enumerate(retrieved))
        self.candidates = [c for c in found if c is not None]

    def _refine(
        self, c: Candidate, start: np.ndarray, iterations: int, end: float, weight_floor: float
    ) -> bool:
        """Refine `c` from `start` toward the pass's measure, charge the budget, keep it if
        better; True if kept. `end`: when the pass must end; `weight_floor`: the IRLS weight
        floor."""
        refined = c.refined(
            self.measure,
            start,
            iterations,
            self.budget.refine_deadline(end),
            self.min_transmission_deg,
            weight_floor,
            self.options.constraints,
            self.budget.stop,
        )
        if refined is None and self.budget.stopped():
            return False  # called off: nothing was done, and nothing is charged
        return c.keep(self.budget.charge(refined), iterations)

    def _refine_on(self, c: Candidate, iterations: int, end: float, weight_floor: float) -> None:
        """`_refine` from where `c` is; if no step helped, it has converged (it will not move)."""
        if not self._refine(c, c.positions, iterations, end, weight_floor):
            c.converged = True

    def _rounds(
        self,
        candidates: list[Candidate],
        iterations: int,
        share: float,
        end: float,
        weight_floor: float,
    ) -> None:
        """Rounds of FIRST_ROUND iterations over the `candidates` still moving, up to
        `iterations` each, until the pass of `share` ending at `end` is done (`Budget.done`).
        In rounds, so that when time runs short every candidate has had as many iterations
        (large mechanisms take many times as long per iteration as small ones)."""

        def round_of(c: Candidate) -> None:
            self._refine_on(c, FIRST_ROUND, end, weight_floor)

        for _ in range(0, iterations, FIRST_ROUND):
            moving = [c for c in candidates if not c.converged]
            if not moving or self.budget.done(share, end):
                break
            list(self.pool.map(round_of, moving))
            self.report()

    def short_pass(self) -> None:
        """Every candidate a few rounds of FIRST_ROUND iterations, within FIRST_SHARE."""
        first_end = self.budget.pass_end(FIRST_SHARE)
        self._rounds(self.candidates, FIRST_ITERATIONS, FIRST_SHARE, first_end, SHORT_WEIGHT_FLOOR)

    def middle_pass(self) -> None:
        """The best MIDDLE_CANDIDATES rounds of FIRST_ROUND iterations, up to MIDDLE_ITERATIONS,
        until MIDDLE_END of the budget is spent. Not for a front, whose long pass takes all its
        leaders, best or not."""
        if self.options.front:
            return
        best = sorted(self.candidates, key=Candidate.rank)[:MIDDLE_CANDIDATES]
        for c in best:  # a short step refused under the short pass's weights says little here
            c.converged = False
        end = self.budget.share_end(MIDDLE_END)
        self._rounds(best, MIDDLE_ITERATIONS, MIDDLE_END, end, IRLS_WEIGHT_FLOOR)

    def time_candidates(self, timed: Target) -> None:
        """The shape is near: the best TIMED_CANDIDATES (and a front's leaders) get their
        start, and from here on the timing ranks them; the rest are dropped."""
        candidates = sorted(self.candidates, key=Candidate.rank)
        leaders = pareto_front(candidates) if self.options.front else []
        best = candidates[:TIMED_CANDIDATES]
        self.candidates = best + [c for c in leaders if c not in best]
        list(self.pool.map(lambda c: c.start_timed(timed), self.candidates))
        self.measure = timed

    def long_pass(self) -> None:
        """LONG_PASS_CANDIDATES (at least k; with a front, all its leaders) refined at a time,
        in rounds of LONG_ROUND, the finalist with the fewest rounds next; one that converges
        makes room for the next best after the earlier passes (whose ranking is rough: the one
        that ends best is often well down it)."""
        budget, deadline = self.budget, self.budget.deadline
        waiting = list(self.candidates)
        quota = max(LONG_PASS_CANDIDATES, self.options.k)
        if self.options.front:
            # The front as the short pass leaves it goes first, all of it at once.
            leaders = pareto_front(self.candidates)
            waiting = leaders + [c for c in self.candidates if c not in leaders]
            quota = max(quota, len(leaders))

        def long(c: Candidate) -> None:
            self._refine_on(c, LONG_ROUND, deadline, IRLS_WEIGHT_FLOOR)

        def moving_finalists() -> list[Candidate]:
            moving = [c for c in self.finalists if not c.converged and id(c) not in self.stopped]
            while len(moving) < quota and waiting:
                c = waiting.pop(0)
                c.converged = False  # a short round cut by its end is no sign of it
                self.finalists.append(c)
                moving.append(c)
            return moving

        # In lockstep (counted work), every moving finalist refines once a round, whatever
        # the threads, so the same candidates get the same work. Else each worker takes the
        # next round as it finishes one: waiting for a round over all of them would idle a
        # core, as a large finalist's round takes many times a small one's.
        running: dict[Future[None], Candidate] = {}
        while not budget.done(1.0, deadline):
            moving = moving_finalists()
            idle = [c for c in moving if c not in running.values()]
            idle.sort(key=lambda c: c.rounds)
            free = len(idle) if budget.lockstep else self.workers - len(running)
            for c in idle[:free]:
                running[self.pool.submit(long, c)] = c
            if not running:
                break
            done, _ = wait(
                running, return_when=ALL_COMPLETED if budget.lockstep else FIRST_COMPLETED
            )
            for future in done:
                future.result()
                running.pop(future).rounds += 1
            waiting[:0] = self.polish(waiting)
            self.report()
        wait(running)  # rounds past the deadline stop within their damping trial under way

    def polish(self, waiting: list[Candidate]) -> list[Candidate]:
        """Once no more than POLISH_LEFT of the budget is left, the best candidate alone goes
        on: the other finalists stop and `waiting` is emptied. Then, and again whenever the best has
        converged, its children with a coupler point (`Candidate.coupler_point_children`), which
        join the candidates and are returned to wait for a finalist's place: the answer gets new
        freedom where it traces. Not for a front (which ranks by joints) or a timed target."""
        if self.options.front or self.timed is not None or not self.candidates:
            return []
        if self.budget.left() > POLISH_LEFT:
            return []
        best = min(self.candidates, key=Candidate.rank)
        if not self.polishing:  # it grows at once, and goes on beside its children
            self.polishing = True
            waiting.clear()
            # By name, not by `converged`: a round under way when the polish begins may
            # still keep a step, which would set it moving again.
            self.stopped = {id(c) for c in self.finalists if c is not best}
        elif not best.converged or best.branched or best.coupler_points >= MAX_COUPLER_POINTS:
            return []
        most = self.options.max_joints or COUPLER_POINT_MAX_JOINTS
        offset = COUPLER_POINT_OFFSET * self.target.chord
        children = best.coupler_point_children(
            self.target, self.options.constraints, self.min_transmission_deg, offset, most
        )
        self.candidates += children
        return children

    def restarts(self) -> None:
        """While work remains, the best finalists shaken and refined again, each kept only if
        better: one per worker, or with counted work as many as the long pass refines (so the
        threads change nothing)."""
        budget, deadline, k = self.budget, self.budget.deadline, self.options.k
        rng = np.random.default_rng(self.options.seed)

        def hop(c: Candidate, start: np.ndarray) -> None:
            self._refine(c, start, HOP_ITERATIONS, deadline, IRLS_WEIGHT_FLOOR)

        while not budget.done(1.0, deadline) and self.finalists:
            self.finalists.sort(key=Candidate.rank)
            chosen = self.finalists[: max(budget.at_once(self.workers, LONG_PASS_CANDIDATES), k)]
            if self.options.front:
                chosen += [c for c in pareto_front(self.finalists) if c not in chosen]
            shakes = np.exp(rng.uniform(*np.log(SHAKE), len(chosen))) * self.target.chord
            starts = [
                c.positions + rng.uniform(-1.0, 1.0, c.positions.shape) * shake
                for c, shake in zip(chosen, shakes, strict=True)
            ]
            list(self.pool.map(hop, chosen, starts))
            self.report()

    def answer(self) -> SynthesisResults:
        """The k best candidates that keep the constraints (or a front of them), as results;
        `unmet` says what the nearest missed when none keeps them. A front's results, and
        every result of one given `max_layers`, carry their `layers`
        (`engine.synthesis.kit_layers`)."""
        ranked = sorted(
            self.candidates, key=lambda c: (*c.rank(), c.result["path_id"], c.coupler_points)
        )
        # One answer for each retrieved mechanism: the best of it and what grew from it.
        seen: set[int] = set()
        candidates = []
        for c in ranked:
            if id(c.retrieved_as) not in seen:
                seen.add(id(c.retrieved_as))
                candidates.append(c)
        kept = [c for c in candidates if c.missed.kept]
        constraints, unmet = self.options.constraints, None
        counts = None
        if plans_layers(self.options):
            counts = LayerCounts(self.pool, layer_deadline(self.options, self.started))
        if counts is not None and constraints is not None and constraints.max_layers is not None:
            chosen, unmet = counts.keeping(kept, self.options, constraints.max_layers)
        else:
            chosen = pareto_front(kept) if self.options.front else kept[: self.options.k]
        if counts is not None:
            counts.plan(chosen, bounded=False)  # a front's, planned whatever the bounds
        stopped = self.budget.stopped()
        answer = SynthesisResults(
            as_result(c, self.target, self.timed, stopped=stopped) for c in chosen
        )
        if counts is not None:
            for result, c in zip(answer, chosen, strict=True):
                result["layers"] = counts.counts[c]
        if candidates and not kept:
            # A design constraint if one holds any candidate back; the floor only if that is all.
            nearest = next(
                (c.missed for c in candidates if c.missed.name != "min_transmission"),
                candidates[0].missed,
            )
            unmet = {"constraint": nearest.name, "by": nearest.by}
        answer.unmet = unmet
        return answer

    def report(self) -> None:
        """Call `progress` with the best so far if it has improved, at most every
        PROGRESS_INTERVAL_S."""
        now = time.perf_counter()
        if (
            self.progress is None
            or not self.candidates
            or now - self._reported_at < PROGRESS_INTERVAL_S
        ):
            return
        best = min(self.candidates, key=Candidate.rank)
        best_rank = best.rank()
        if best_rank == self._looked_at:  # nothing kept since: no answer to measure
            return
        self._looked_at = best_rank
        # Measured from the positions read now (a worker may have moved them on since its
        # rank), by the answer's own measure (the timed error once timing ranks): the
        # reports must fall as the answer's measures do.
        timed = self.timed
        answer = as_result(best, self.target, timed, trajectories=True, elapsed=now - self.started)
        measured = answer["timed_error"] if timed is not None else answer["chamfer"]
        rank = (not best.missed.kept, best.missed.total, measured)
        if rank < self._reported_rank:
            self._reported_rank, self._reported_at = rank, now
            self.progress(answer)
