"""`links bench synthesize --design`: buildable answers for the shipped target curves, each
placed in a random frame, at the default budget over the cached benchmark data set.

Per curve, four syntheses of `seconds` each:
- **plain**: the k best, as `links synthesize` answers (the unconstrained best);
- **front**: simplest first (`front=True`): the best chamfer at each joint count on the front,
  and the best at MAX_SIMPLE_JOINTS joints or fewer;
- **constrained**: a pivot region (the drawing's own box) and a footprint (that box grown by
  FOOTPRINT_MARGIN of its longest side on every side); whether the plain best keeps them, and
  whether every constrained answer does, checked over a 2,000-step turn;
- **timed**: `timing=True`, the points reached at equal crank steps; the timed error.

The targets: the mean best at MAX_SIMPLE_JOINTS or fewer within SIMPLE_GOAL times the plain
mean, every constraint kept by every answer, and the budget honoured (OVERRUN_GOAL_MS).
"""

from __future__ import annotations

import statistics
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from links_ray.bench.machine import machine_info
from links_ray.bench.synthesis import OVERRUN_GOAL_MS
from links_ray.bench.targets import TARGET_POINTS, placed, target_curves
from links_ray.engine.synthesis.constraints import as_constraints
from links_ray.engine.synthesis.limits import REFINE_CHECK_STEPS
from links_ray.engine.synthesis.options import DEFAULT_SYNTHESIS_SECONDS

if TYPE_CHECKING:
    from links_ray.engine.synthesis.plan import Retriever

#: "Simple": at most this many joints. The goal: the mean best so simple within SIMPLE_GOAL
#: times the unconstrained mean.
MAX_SIMPLE_JOINTS, SIMPLE_GOAL = 8, 1.5
#: The footprint is the drawing's box grown by this share of its longest side on each side.
FOOTPRINT_MARGIN = 0.5


def design_constraints(points: np.ndarray) -> dict[str, list[float]]:
    """The bench's constraints for a drawing: pivots inside its box, every joint inside the
    box grown by FOOTPRINT_MARGIN of its longest side."""
    low, high = points.min(axis=0), points.max(axis=0)
    grow = FOOTPRINT_MARGIN * float((high - low).max())
    return {
        "pivots": [*map(float, low), *map(float, high)],
        "footprint": [*map(float, low - grow), *map(float, high + grow)],
    }


def kept(result: dict, given: dict) -> bool:
    """Whether a result keeps `given`, measured afresh over a REFINE_CHECK_STEPS turn."""
    from links_ray.engine.inputs import link_pairs
    from links_ray.engine.kinematics.mechanism import analyze_topology
    from links_ray.engine.kinematics.solver import simulate
    from links_ray.engine.synthesis.constraints import extent, violation

    mechanism = result["mechanism"]
    topology = analyze_topology(mechanism["adjacency"], mechanism["node_types"])
    positions = np.array(mechanism["positions"])
    turn = simulate(topology.adjacency, topology.node_types, positions, REFINE_CHECK_STEPS)
    missed = violation(
        as_constraints(given),
        positions,
        topology.fixed_joints,
        link_pairs(topology.adjacency),
        extent(turn),
        1.0,
    )
    return missed.kept


def _timed(run: Any) -> tuple[Any, float]:
    start = time.perf_counter()
    answer = run()
    return answer, time.perf_counter() - start


def design_row(index: Retriever, name: str, points: np.ndarray, seconds: float) -> dict:
    """One curve's row of the design bench (the module docstring says what it holds)."""
    from links_ray.engine.synthesis.pipeline import synthesize

    def run(**design: Any) -> tuple[Any, float]:
        return _timed(lambda: synthesize(index, points, k=3, seconds=seconds, **design))

    plain, plain_s = run()
    front, front_s = run(front=True)
    given = design_constraints(points)
    constrained, constrained_s = run(constraints=given)
    timed, timed_s = run(timing=True)
    simple = [r["chamfer"] for r in front if r["n_joints"] <= MAX_SIMPLE_JOINTS]
    return {
        "curve": name,
        "plain": plain[0]["chamfer"],
        "plain_joints": plain[0]["n_joints"],
        "front": [(r["n_joints"], r["chamfer"]) for r in front],
        "simple": min(simple) if simple else None,
        "plain_keeps": kept(plain[0], given),
        "constrained": constrained[0]["chamfer"] if constrained else None,
        "constrained_kept": bool(constrained) and all(kept(r, given) for r in constrained),
        "unmet": constrained.unmet,
        "timed_error": timed[0]["timed_error"],
        "timed_chamfer": timed[0]["chamfer"],
        "seconds": [plain_s, front_s, constrained_s, timed_s],
    }


def bench_design(
    seconds: float | None = None, paths: int = 1_000_000, seed: int = 0, root: str | None = None
) -> dict:
    """The design bench over the target curves in the frames of `seed` (those of `links bench
    synthesize`), `seconds` a synthesis (default the synthesis default), over the cached
    data set of `paths` curated paths or `root`."""
    from links_ray.bench.data import retrieval_dataset
    from links_ray.engine.synthesis.pipeline import synthesize
    from links_ray.search.index import RetrievalIndex

    seconds = DEFAULT_SYNTHESIS_SECONDS if seconds is None else seconds
    index = RetrievalIndex.open(root or retrieval_dataset(paths))
    index.warm()
    angle = np.linspace(0, 2 * np.pi, 60, endpoint=False)
    warm = np.column_stack([np.cos(angle), 0.4 * np.sin(angle)])
    synthesize(index, warm, seconds=0.5, timing=True, front=True)  # loads the kernels
    rng = np.random.default_rng(seed)
    rows = [
        design_row(index, name, placed(curve, rng), seconds)
        for name, curve in target_curves().items()
    ]
    plain_mean = statistics.fmean(row["plain"] for row in rows)
    simple = [row["simple"] for row in rows if row["simple"] is not None]
    simple_mean = statistics.fmean(simple) if len(simple) == len(rows) else None
    within = sum(
        row["simple"] is not None and row["simple"] <= SIMPLE_GOAL * row["plain"] for row in rows
    )
    worst_overrun = max(s - seconds for row in rows for s in row["seconds"]) * 1e3
    return {
        "paths": len(index),
        "points_per_curve": TARGET_POINTS,
        "budget_s": seconds,
        "seed": seed,
        "curves": rows,
        "plain_mean": plain_mean,
        "simple_mean": simple_mean,
        "simple_within": within,
        "constrained_mean": statistics.fmean(
            row["constrained"] for row in rows if row["constrained"] is not None
        )
        if any(row["constrained"] is not None for row in rows)
        else None,
        "timed_mean": statistics.fmean(row["timed_error"] for row in rows),
        "worst_overrun_ms": worst_overrun,
        "goals": {
            f"simple_mean_within_{SIMPLE_GOAL:g}x": simple_mean is not None
            and simple_mean <= SIMPLE_GOAL * plain_mean,
            "every_constraint_kept": all(
                row["constrained_kept"] or row["unmet"] is not None for row in rows
            ),
            "overrun_under_50_ms": worst_overrun < OVERRUN_GOAL_MS,
        },
        "machine": machine_info(),
    }


def format_design(result: dict) -> str:
    """The design bench as Markdown tables."""

    def number(value: float | None) -> str:
        return "-" if value is None else f"{value:.4f}"

    lines = [
        f"Buildable synthesis over {result['paths']:,} curated paths, {result['points_per_curve']}"
        f" points a curve, {result['budget_s']:g} s a synthesis, frames of seed {result['seed']} "
        "(chamfer / the drawing's longest chord)",
        "",
        f"| curve | plain (joints) | best at <= {MAX_SIMPLE_JOINTS} joints | front (joints: "
        "chamfer) | plain keeps the box | constrained | all kept | timed error | timed chamfer |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for row in result["curves"]:
        front = ", ".join(f"{n}: {c:.4f}" for n, c in row["front"])
        constrained = (
            number(row["constrained"])
            if row["unmet"] is None
            else f"unmet: {row['unmet']['constraint']} by {row['unmet']['by']:.3g}"
        )
        lines.append(
            f"| {row['curve']} | {row['plain']:.4f} ({row['plain_joints']}) | "
            f"{number(row['simple'])} | {front} | {'yes' if row['plain_keeps'] else 'no'} | "
            f"{constrained} | {'yes' if row['constrained_kept'] else 'no'} | "
            f"{row['timed_error']:.4f} | {row['timed_chamfer']:.4f} |"
        )
    lines.append(
        f"| **mean** | {result['plain_mean']:.4f} | {number(result['simple_mean'])} | | | "
        f"{number(result['constrained_mean'])} | | {result['timed_mean']:.4f} | |"
    )
    lines += [
        "",
        f"curves with an answer at <= {MAX_SIMPLE_JOINTS} joints within {SIMPLE_GOAL:g}x of "
        f"the plain best: {result['simple_within']} of {len(result['curves'])}",
        f"worst overrun past the budget: {result['worst_overrun_ms']:.0f} ms",
    ]
    lines += [f"{goal}: {'yes' if met else 'no'}" for goal, met in result["goals"].items()]
    return "\n".join(lines)
