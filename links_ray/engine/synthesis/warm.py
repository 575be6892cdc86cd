"""Synthesis's kernels compiled, or loaded from numba's cache, before a synthesis's clock starts.

numba compiles a kernel at its first call, for the types of that call, and only the kernels a
run reaches: a synthesis whose budget ran out in the first kernels never reached the next, which
the next run then compiled within its own budget, and so on (a fresh install's first few calls
answered as retrieved). `warm_synthesis` runs, once per process and kind of synthesis
(`variant`), a small synthesis of counted work on a mechanism of its own placed on the caller's
drawing, with the caller's options: the same code as the real one, with arrays of the same
types as a retrieval index answers (`engine.synthesis.plan.RetrievalResult`), so it compiles
the signatures the real one will call, every pass's (the short pass, restarts, the polish's
coupler points, timing, layer plans). Given the index, one result of each kind of retrieval
the synthesis asks for loads the index's kernels too, once an index. Nothing it does touches
what a synthesis computes: counted work stays bit-equal.

Pure numpy/numba and threads: no Ray, no files.
"""

from __future__ import annotations

import dataclasses
import threading
import time
import weakref
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from links_ray.engine.inputs import DEFAULT_STEPS
from links_ray.engine.kinematics.solver import simulate
from links_ray.engine.synthesis.budget import IterationBudget
from links_ray.engine.synthesis.constraints import MAX_LAYERS, Constraints
from links_ray.engine.synthesis.kit_layers import plans_layers
from links_ray.engine.synthesis.options import SynthesisOptions
from links_ray.engine.synthesis.passes import SynthesisPasses
from links_ray.engine.synthesis.plan import RetrievalResult, Retriever, retrievals
from links_ray.engine.synthesis.target import Target, as_target

__all__ = ["WARM_ITERATIONS", "variant", "warm_default", "warm_synthesis"]

#: Refinement iterations of a warming synthesis: a refinement's first iteration calls every
#: kernel of its loop, and these reach the long pass and the polish's coupler points too, in
#: milliseconds once the kernels are loaded (tests/engine/synthesis/test_warm.py checks that a
#: synthesis compiles nothing after it).
WARM_ITERATIONS = 60
#: The warming synthesis's mechanism: a crank-rocker four-bar whose coupler point (joint 4)
#: traces a loop, as a retrieval index answers one (uint8, int8, float64).
WARM_ADJACENCY = np.array(
    [[0, 1, 0, 0, 0], [1, 0, 1, 0, 1], [0, 1, 0, 1, 1], [0, 0, 1, 0, 0], [0, 1, 1, 0, 0]],
    dtype=np.uint8,
)
WARM_NODE_TYPES = np.array([0, 2, 1, 0, 1], dtype=np.int8)
WARM_POSITIONS = np.array(
    [[0.2, 0.1], [0.2765, 0.1644], [0.4320, 0.4780], [0.5821, 0.2182], [0.2357, 0.3521]]
)
WARM_JOINT = 4

_warming = threading.Lock()  # one warm at a time; the next caller finds it done
_warmed: set[tuple[bool, ...]] = set()
# The retrievals warmed, by the index's id (an index need not be hashable; a dead one's id may
# be reused) and their kind (with a transmission floor, with a joint limit).
_warm_retrievals_done: dict[tuple[int, bool, bool], weakref.ref[Retriever]] = {}


def variant(options: SynthesisOptions) -> tuple[bool, ...]:
    """What, of `options`, decides which kernels a synthesis runs: a stroke, timing, a front,
    constraints, layer plans."""
    return (
        options.partial,
        options.timing is not None,
        options.front,
        options.constraints is not None,
        plans_layers(options),
    )


def warm_synthesis(
    target: Target, options: SynthesisOptions, index: Retriever | None = None
) -> float:
    """Compile or load every kernel a synthesis of `options` onto `target` runs (and, given
    `index`, those of its retrievals), unless this process has already: the seconds it took
    (0 when warm)."""
    began = time.perf_counter()
    with _warming:
        if index is not None:
            _warm_retrievals(index, target, options)
        key = variant(options)
        if key not in _warmed:
            _warm_run(target, options)
            _warmed.add(key)
    return time.perf_counter() - began


def _warm_retrievals(index: Retriever, target: Target, options: SynthesisOptions) -> None:
    """One result of each retrieval a synthesis of `options` asks `index` for (`retrievals`),
    unless one alike (with or without a transmission floor, a joint limit) was asked of it."""
    for _, most, floor in retrievals(
        options.k, options.max_joints, options.front, options.min_transmission_deg
    ):
        key = (id(index), floor > 0.0, most is not None)
        known = _warm_retrievals_done.get(key)
        if known is None or known() is not index:
            index.retrieve(target.points, 1, floor, most)
            _warm_retrievals_done[key] = _reference(index)


def _reference(index: Retriever) -> weakref.ref[Retriever]:
    """A weak reference to `index`, or for one that takes none a strong one alike."""
    try:
        return weakref.ref(index)
    except TypeError:
        return lambda: index  # type: ignore[return-value]


def warm_default() -> float:
    """`warm_synthesis` of a default synthesis (a closed drawing, no design) on an ellipse, for
    a server to run before its first request: the seconds it took."""
    angle = np.linspace(0.0, 2.0 * np.pi, 60, endpoint=False)
    ellipse = np.column_stack([np.cos(angle), 0.5 * np.sin(angle)])
    return warm_synthesis(as_target(ellipse, False), SynthesisOptions())


def _warm_run(target: Target, options: SynthesisOptions) -> None:
    """A synthesis of WARM_ITERATIONS on the warming mechanism placed on `target`, its answer
    dropped. The design constraints are numpy alone: the warming keeps none but the loosest
    `max_layers` when layers are planned, and no floor but refinement's own, so that its
    mechanism keeps them and its answer plans its layers as a real one's would."""
    layers = Constraints(max_layers=MAX_LAYERS) if options.constraints is not None else None
    counted = dataclasses.replace(
        options,
        k=1,
        seconds=None,
        iterations=WARM_ITERATIONS,
        min_transmission_deg=0.0,
        constraints=layers if plans_layers(options) else None,
    )
    budget = IterationBudget(WARM_ITERATIONS)
    with ThreadPoolExecutor(1, thread_name_prefix="links-warm") as pool:
        passes = SynthesisPasses(counted, target, budget, pool, 1, None, time.perf_counter())
        passes.run([warm_retrieved(target)])


def warm_retrieved(target: Target) -> RetrievalResult:
    """The warming mechanism as a retrieval result, its path's box centred and scaled on
    `target`'s points."""
    path = simulate(WARM_ADJACENCY, WARM_NODE_TYPES, WARM_POSITIONS, DEFAULT_STEPS)[WARM_JOINT]
    low, high = path.min(axis=0), path.max(axis=0)
    drawn_low, drawn_high = target.points.min(axis=0), target.points.max(axis=0)
    scale = target.chord / max(float(np.hypot(*(high - low))), 1e-300)
    positions = (WARM_POSITIONS - (low + high) / 2.0) * scale + (drawn_low + drawn_high) / 2.0
    placed = (path - (low + high) / 2.0) * scale + (drawn_low + drawn_high) / 2.0
    return RetrievalResult(
        path_id=-1,
        mechanism_id=-1,
        joint=WARM_JOINT,
        chamfer=0.0,
        min_transmission_deg=None,
        n_joints=len(WARM_NODE_TYPES),
        points=placed,
        mechanism={
            "adjacency": WARM_ADJACENCY.copy(),
            "node_types": WARM_NODE_TYPES.copy(),
            "positions": np.ascontiguousarray(positions),
        },
        mechanism_joint=WARM_JOINT,
    )
