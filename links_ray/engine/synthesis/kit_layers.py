"""Synthesis's layers: how many layers each answer takes as a kit, and the `max_layers`
constraint, kept at the answer.

The sizes. A drawing has no unit, so a candidate is planned as `engine.fabrication.kit.kit_layers`
plans a kit of the default options (`KitOptions()`): its crank scaled to DEFAULT_CRANK_MM (20 mm),
then the default bar width, clearance and spacer diameter in millimetres. In the drawing's own units
that is each candidate's sizes relative to its own crank length c: bars 0.4 c wide (8 mm), 0.05 c of
clearance (1 mm), pins with their spacers 0.3 c across (6 mm).

Where it is checked. A layer plan costs about 0.03 to 0.5 s a mechanism, rarely seconds:
far too much for a refinement step. So refinement ignores `max_layers`, and the
answer keeps it: the candidates that keep every other constraint, in rank order, are planned
(a few at a time, on the synthesis's threads) until the answer is full (k that keep it, or a
front of them), at most MAX_LAYER_PLANS of them, and with a time budget not past the
synthesis's deadline (the first is planned whatever the time), for which the passes leave
LAYER_SHARE of it. A candidate past those bounds is not in the answer. With `front`, every
result carries `layers` (planned whatever the bounds: a front is a few results); with
`max_layers`, so does every result.

Unmet. A candidate misses `max_layers` by its layers over the most; one with no plan
(`LayeringError`, or a mechanism the planner refuses) by NO_PLAN_MISS, more than any plan
misses by. When none planned keeps it, `unmet` names the one that missed by least.

The planner does counted work (its shuffles seeded, its searches bounded by states and
branch-and-bound nodes, `engine.fabrication.layers`), so a synthesis of counted work stays bit-equal
with layers too. Only the planner's wall-clock guard (status "time limit") could make a plan depend
on the load, and the counted work stops long before it.

Pure numpy and threads: no Ray.
"""

from __future__ import annotations

import math
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from links_ray.engine.fabrication.kit import kit_layers
from links_ray.engine.synthesis.candidates import Candidate
from links_ray.engine.synthesis.constraints import MAX_LAYERS
from links_ray.engine.synthesis.options import SynthesisOptions
from links_ray.engine.synthesis.pareto import pareto_front

__all__ = [
    "LAYER_SHARE",
    "MAX_LAYER_PLANS",
    "NO_PLAN_MISS",
    "LayerCounts",
    "kit_layer_count",
    "layer_deadline",
    "plans_layers",
]

#: The most candidates one answer plans for `max_layers` (each 0.03-0.5 s, rarely more).
MAX_LAYER_PLANS = 12
#: The share of a time budget the passes leave for planning layers, when the answer plans.
LAYER_SHARE = 0.2
#: How much a candidate with no layer plan misses `max_layers` by: more than any plan does.
NO_PLAN_MISS = MAX_LAYERS


def plans_layers(options: SynthesisOptions) -> bool:
    """Whether the answer plans layers: for a front, or to keep `max_layers`."""
    constraints = options.constraints
    return options.front or (constraints is not None and constraints.max_layers is not None)


def kit_layer_count(
    adjacency: np.ndarray, node_types: np.ndarray, positions: np.ndarray
) -> int | None:
    """The layers of the mechanism as a kit at the default sizes (the module's docstring), or
    None when it has no plan (`LayeringError`) or the planner refuses it."""
    try:
        return kit_layers(adjacency, node_types, positions).layers
    except ValueError:  # LayeringError among them
        return None


class LayerCounts:
    """Each candidate's layer count (None: no plan), each planned once, on `pool`'s threads,
    at most MAX_LAYER_PLANS of them bounded, and none but the first of a bounded batch begun
    after `deadline` (`time.perf_counter()`; inf for counted work)."""

    def __init__(self, pool: ThreadPoolExecutor, deadline: float) -> None:
        self.pool = pool
        self.deadline = deadline
        self.counts: dict[Candidate, int | None] = {}
        self.bounded = 0  # plans counted against MAX_LAYER_PLANS

    def plan(self, chosen: list[Candidate], bounded: bool = True) -> int:
        """Plan those of `chosen` not yet planned, within the bounds if `bounded`; how many
        were planned."""
        todo = [c for c in chosen if c not in self.counts]
        if bounded:
            todo = todo[: MAX_LAYER_PLANS - self.bounded]
        first = bounded and self.bounded == 0

        def count(item: tuple[int, Candidate]) -> tuple[Candidate, int | None, bool]:
            place, c = item
            if bounded and not (first and place == 0) and time.perf_counter() > self.deadline:
                return c, None, False
            topology = c.topology
            return c, kit_layer_count(topology.adjacency, topology.node_types, c.positions), True

        planned = 0
        for c, layers, done in self.pool.map(count, enumerate(todo)):
            if done:
                self.counts[c] = layers
                planned += 1
        if bounded:
            self.bounded += planned
        return planned

    def keeping(
        self, candidates: list[Candidate], options: SynthesisOptions, most: int
    ) -> tuple[list[Candidate], dict[str, object] | None]:
        """The answer's candidates among `candidates` (ranked, each keeping the other
        constraints) that keep `most` layers: the k best, or a front of them; and `unmet`
        when none planned keeps it."""

        def chosen(among: list[Candidate]) -> list[Candidate]:
            return pareto_front(among) if options.front else among[: options.k]

        def keeps(c: Candidate) -> bool:
            layers = self.counts.get(c)
            return layers is not None and layers <= most

        # Plan the answer as it would be; drop what misses; again, until all of it is planned.
        while True:
            left = [c for c in candidates if c not in self.counts or keeps(c)]
            answer = chosen(left)
            if all(c in self.counts for c in answer) or not self.plan(answer):
                break
        answer = chosen([c for c in candidates if keeps(c)])
        if answer or not self.counts:
            return answer, None
        by = min(
            NO_PLAN_MISS if layers is None else layers - most for layers in self.counts.values()
        )
        return answer, {"constraint": "max_layers", "by": by}


def layer_deadline(options: SynthesisOptions, started: float) -> float:
    """When planning for the answer must stop: the synthesis's deadline, or never for counted
    work."""
    return math.inf if options.seconds is None else started + options.seconds
