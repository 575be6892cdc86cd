"""Synthesis: mechanisms whose joint traces a drawn curve, found by retrieval and then refined.

`synthesize(index, points)` checks the request once (`engine.synthesis.options`), asks a retrieval
index for the stored paths nearest the drawing (`engine.synthesis.plan`: their mechanisms already
placed in the drawing's frame), then refines them toward the drawing itself (`refine_retrieved`:
`engine.synthesis.passes` says how) within a budget (`engine.synthesis.budget`), and answers with
the best (`engine.synthesis.results`), or a Pareto front of them (`engine.synthesis.pareto`).

What is measured. A result's `chamfer` is the bidirectional chamfer distance between the drawn
points and the path the result's `mechanism_joint` traces over a full crank turn at `DEFAULT_STEPS`
steps (for a partial stroke, over the run of steps that fits it best), divided by the drawing's
longest chord: for an unrefined retrieval result it equals retrieval's chamfer between the
normalized query and the normalized path. Every refined mechanism is valid as
`engine.synthesis.refinement.loop` keeps it: it turns fully at `REFINE_CHECK_STEPS` steps, keeps its
assembly branches and its transmission floor.

`index` is anything with `retrieve(points, k, min_transmission, max_joints)` answering as
`links_ray.search.index.RetrievalIndex.retrieve` does (`engine.synthesis.plan.Retriever`: result
dicts whose mechanisms are numpy arrays, read without conversion; the engine imports no index).

Pure numpy/numba and threads: no Ray, no files.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor

from links_ray.engine.cpus import usable_cpus
from links_ray.engine.inputs import DEFAULT_K
from links_ray.engine.synthesis.budget import Budget, IterationBudget, TimeBudget
from links_ray.engine.synthesis.kit_layers import LAYER_SHARE, plans_layers
from links_ray.engine.synthesis.options import DEFAULT_SYNTHESIS_TRANSMISSION_DEG, SynthesisOptions
from links_ray.engine.synthesis.passes import Progress, SynthesisPasses
from links_ray.engine.synthesis.plan import RetrievalResult, Retriever, pooled, retrievals
from links_ray.engine.synthesis.results import SynthesisResults
from links_ray.engine.synthesis.target import as_target
from links_ray.engine.synthesis.warm import warm_synthesis

__all__ = ["refine_retrieved", "synthesize"]


def refine_retrieved(
    points: object,
    retrieved: Sequence[RetrievalResult],
    options: SynthesisOptions,
    *,
    started: float | None = None,
    progress: Progress | None = None,
    stop: threading.Event | None = None,
) -> SynthesisResults:
    """The `options.k` best synthesis results (best first) refined from retrieval results of
    `points` (`RetrievalIndex.retrieve`'s, in the drawing's frame), keeping a transmission
    floor of at least DEFAULT_MIN_TRANSMISSION_DEG and `options.min_transmission_deg`.

    The work is bounded by time, or counted. Timed: within `options.seconds` counted from
    `started` (a `time.perf_counter()` value; now if None), less the time this process first
    takes to compile or load the kernels (`engine.synthesis.warm`); every piece of work checks the
    deadline, so the answer comes at most one damping trial past it (the first k retrieved
    are prepared whatever the time, so that there is an answer). Counted
    (`options.iterations`): the passes stop after about that many refinement iterations over
    all candidates, checked between rounds that run in lockstep, so the answer is the same bit
    for bit whatever the time, the machine's load and the threads. `options.seed` seeds the
    restarts.

    `progress`, if given, is called with the best so far whenever it has improved, at most
    every PROGRESS_INTERVAL_S (first with the best retrieved start): a result as the answer
    has them, with `trajectories` (every joint's path at DEFAULT_STEPS steps, to animate) and
    `elapsed_ms` besides. It runs in this thread, between rounds of refinement.

    `options.front`: the answer is the Pareto front: for each joint count among the
    candidates, the best result, and only those better than every simpler one, by joints
    ascending (k does not limit it). `options.constraints`: every result keeps them; if none
    can, the answer is empty and its `unmet` says which the nearest candidate misses, and by
    how much; `max_layers` is kept at the answer, and a front's results (and those of a
    synthesis given `max_layers`) carry their `layers`, `engine.synthesis.kit_layers` says how
    (with a time budget, the passes take 1 - LAYER_SHARE of it, the plans the rest).
    `options.timing`: the points are reached at those crank angles; the short pass
    fits the shape, then the start of each candidate is chosen (`timing.best_start`) and the
    rest refines and ranks by the timed error.

    Counted work on more points than MAX_SYNTHESIS_WORK allows raises ValueError
    (`SynthesisOptions.check_work`). `stop`, once set (a server's client has gone), calls the
    rest of the work off: each refinement under way ends at its next iteration, and the
    answer is the best so far. The answer's `iterations` and `stopped` say what was done, and
    each result's `refined` and `why` whether refinement kept a step of it, and if not why."""
    target = as_target(points, options.partial)
    options.check_work(len(target.points))
    # The kernels compile (or load) before the clock starts: a first synthesis gets all its time.
    warming = warm_synthesis(target, options)
    started = time.perf_counter() if started is None else started + warming
    budget: Budget
    if options.iterations is not None:
        budget = IterationBudget(options.iterations, stop)
    else:
        seconds: float = options.seconds  # type: ignore[assignment]
        if plans_layers(options):
            seconds *= 1.0 - LAYER_SHARE  # the answer's layer plans take the rest
        budget = TimeBudget(started, seconds, stop)
    workers = max(1, min(usable_cpus(), len(retrieved)))
    with ThreadPoolExecutor(workers, thread_name_prefix="links-synthesize") as pool:
        passes = SynthesisPasses(options, target, budget, pool, workers, progress, started)
        results = passes.run(list(retrieved))
    results.iterations, results.stopped = budget.spent, budget.stopped()
    return results


def synthesize(
    index: Retriever,
    points: object,
    k: int = DEFAULT_K,
    seconds: float | None = None,
    partial: bool = False,
    min_transmission: float = DEFAULT_SYNTHESIS_TRANSMISSION_DEG,
    progress: Progress | None = None,
    *,
    max_joints: int | None = None,
    front: bool = False,
    constraints: object = None,
    timing: object = None,
    seed: int | None = None,
    iterations: int | None = None,
    options: SynthesisOptions | None = None,
) -> SynthesisResults:
    """The k best mechanisms found for a drawn curve, best first, each refined so that its
    `mechanism_joint` traces `points` in the drawing's own frame, within `seconds` (default
    DEFAULT_SYNTHESIS_SECONDS, at most MAX_SYNTHESIS_SECONDS), retrieval included.
    `partial`: the points are an open stroke, matched to part of a turn. `min_transmission`
    (degrees, default DEFAULT_SYNTHESIS_TRANSMISSION_DEG): every result keeps it (refinement's
    floor, at least DEFAULT_MIN_TRANSMISSION_DEG); most candidates are paths that keep it, and
    some are paths below it, which refinement raises to it first (`synthesis_plan`).
    `progress`: called with the best so far as it improves (`refine_retrieved` says how).
    `iterations` (instead of `seconds`): a counted amount of work, about that many refinement
    iterations, whose answer is the same bit for bit for equal inputs whatever the time and
    the cores; `seed` (default 0) seeds the restarts.

    Design: `max_joints`, only mechanisms of at most that many joints (each result's
    `n_joints` counts its reduced mechanism's); `front`, the Pareto front (the best of each
    joint count that beats every simpler one) instead of the k best, each result with its
    `layers` as a kit; `constraints` (pivots, footprint, max_link_ratio, min_link, max_link,
    in the drawing's units, and max_layers: `constraints.Constraints`), kept by every result,
    the answer's `unmet` saying so when no candidate can; `timing` (True: equal crank steps
    over a turn; or the crank angle of each point in degrees), the points reached at those
    angles from a free start, each result's `timed_error` measuring it.

    `options`: all of the above but `points` and `progress` as one `SynthesisOptions`, instead
    of the separate arguments. Raises ValueError naming bad input.

    The time counts from when the kernels are loaded: a process's first synthesis of a kind
    compiles (or loads from numba's cache) those of its retrievals (one result of each, asked of
    `index`) and of refinement first (`engine.synthesis.warm`)."""
    if options is None:
        options = SynthesisOptions(
            k=k,
            seconds=seconds,
            partial=partial,
            min_transmission_deg=min_transmission,
            max_joints=max_joints,
            front=front,
            constraints=constraints,  # type: ignore[arg-type]
            timing=timing,  # type: ignore[arg-type]
            seed=seed,  # type: ignore[arg-type]
            iterations=iterations,
        )
    elif (k, seconds, partial, min_transmission, max_joints, front) != (
        DEFAULT_K,
        None,
        False,
        DEFAULT_SYNTHESIS_TRANSMISSION_DEG,
        None,
        False,
    ) or (constraints, timing, seed, iterations) != (None, None, None, None):
        raise ValueError("give options or the separate synthesis arguments, not both")
    drawn = options.drawing(points)  # refused before any retrieval
    # The index's kernels and refinement's load before the clock starts (`refine_retrieved`
    # would warm refinement's within it, but not the retrieval's).
    warm_synthesis(as_target(drawn, options.partial), options, index)
    started = time.perf_counter()
    retrieved = pooled(
        [
            index.retrieve(drawn, count, floor, most)
            for count, most, floor in retrievals(
                options.k, options.max_joints, options.front, options.min_transmission_deg
            )
        ]
    )
    return refine_retrieved(drawn, retrieved, options, started=started, progress=progress)
