"""`links bench synthesize`: the shipped target curves (`links_ray.cli.targets`), each placed in
a random frame, synthesized over the cached benchmark data set (`retrieval_dataset`).

Per curve: the retrieval-only chamfer (the best retrieved path's), the refined chamfer (the
best synthesis result's), the seconds `synthesize` took (retrieval included) and how far past
its budget that was (its overrun; the worst over the curves is the bench's), and a reference:
the chamfer between the curve's points and the curve itself at DEFAULT_STEPS points evenly
spaced along it, which is about what a mechanism tracing the curve exactly at an even speed
would score (the point-sampled chamfer is not 0 even then).
"""

from __future__ import annotations

import statistics
import time

import numpy as np

from links_ray.cli.bench import machine_info
from links_ray.cli.targets import TARGET_POINTS, placed, target_curves
from links_ray.engine.inputs import DEFAULT_STEPS
from links_ray.engine.paths import chamfer, longest_chord
from links_ray.engine.solver import simulate

#: Seconds each curve is given: the most that keeps the median under MEDIAN_SECONDS_GOAL
#: (retrieval and the answer included).
BENCH_SECONDS = 4.5
#: What the bench is asked to show: refined mean at most this share of retrieval-only, and
#: below MEAN_GOAL; median seconds at most MEDIAN_SECONDS_GOAL.
RATIO_GOAL, MEAN_GOAL, MEDIAN_SECONDS_GOAL = 1 / 3, 0.010, 5.0
#: The most any curve's answer may come past its budget, in milliseconds.
OVERRUN_GOAL_MS = 50.0


def even_reference(points: np.ndarray, steps: int = DEFAULT_STEPS) -> float:
    """Chamfer, divided by the longest chord, between closed `points` and `steps` points
    evenly spaced along their own polyline."""
    loop = np.concatenate([points, points[:1]])
    lengths = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(loop, axis=0), axis=1))])
    at = np.linspace(0, lengths[-1], steps, endpoint=False)
    even = np.column_stack([np.interp(at, lengths, loop[:, 0]), np.interp(at, lengths, loop[:, 1])])
    i, j = longest_chord(points)
    return chamfer(points, even) / float(np.hypot(*(points[j] - points[i])))


def bench_synthesize(
    seconds: float = BENCH_SECONDS,
    paths: int = 1_000_000,
    seed: int = 0,
    figure: str | None = None,
    iterations: int | None = None,
) -> dict:
    """Synthesize every target curve, placed in a random frame (`seed`), over the cached data
    set of `paths` curated paths; per curve and overall (means, median seconds, the worst
    overrun past the budget). `iterations`: fixed work per curve instead of `seconds`, its
    restarts seeded with `seed` (no overrun then: there is no budget). `figure`: a
    PNG path for a picture of every curve, its best retrieved path and its refined mechanism
    (needs the `plots` extra)."""
    from links_ray.cli.bench_data import retrieval_dataset
    from links_ray.engine.synthesis import synthesize
    from links_ray.search.index import RetrievalIndex

    root = retrieval_dataset(paths)
    start = time.perf_counter()
    index = RetrievalIndex.open(root)
    open_s = time.perf_counter() - start
    index.warm()
    angle = np.linspace(0, 2 * np.pi, 60, endpoint=False)
    # Loads the refinement kernels, so no curve pays for it.
    synthesize(index, np.column_stack([np.cos(angle), 0.4 * np.sin(angle)]), seconds=0.5)
    rng = np.random.default_rng(seed)
    rows = []
    drawn = []
    for name, curve in target_curves().items():
        points = placed(curve, rng)
        start = time.perf_counter()
        if iterations is None:
            results = synthesize(index, points, k=3, seconds=seconds)
        else:
            results = synthesize(index, points, k=3, seed=seed, iterations=iterations)
        took = time.perf_counter() - start
        best_retrieved = index.retrieve(points, 1)[0]
        retrieved = best_retrieved["chamfer"]
        if figure is not None:
            mechanism = best_retrieved["mechanism"]
            retrieved_path = simulate(
                mechanism["adjacency"], mechanism["node_types"], mechanism["positions"]
            )[best_retrieved["mechanism_joint"]]
            drawn.append(
                {
                    "curve": name,
                    "points": points,
                    "retrieved_path": retrieved_path,
                    "retrieved": retrieved,
                    "refined": results[0]["chamfer"],
                    "result": results[0],
                }
            )
        rows.append(
            {
                "curve": name,
                "retrieved": retrieved,
                "refined": results[0]["chamfer"],
                "seconds": took,
                "overrun_ms": None if iterations is not None else (took - seconds) * 1e3,
                "reference": even_reference(points),
                "joints": len(results[0]["mechanism"]["node_types"]),
            }
        )
    if figure is not None:
        from links_ray.cli.figures import write_synthesis_figure

        write_synthesis_figure(figure, drawn)
    mean_retrieved = statistics.fmean(row["retrieved"] for row in rows)
    mean_refined = statistics.fmean(row["refined"] for row in rows)
    median_s = statistics.median(row["seconds"] for row in rows)
    overruns = [row["overrun_ms"] for row in rows if row["overrun_ms"] is not None]
    worst = max(overruns) if overruns else None
    goals = {
        "ratio_at_most_a_third": mean_refined <= RATIO_GOAL * mean_retrieved,
        "mean_below_0.010": mean_refined < MEAN_GOAL,
        "median_at_most_5_s": median_s <= MEDIAN_SECONDS_GOAL,
    }
    if worst is not None:
        goals["overrun_under_50_ms"] = worst < OVERRUN_GOAL_MS
    return {
        "paths": len(index),
        "points_per_curve": TARGET_POINTS,
        "budget_s": None if iterations is not None else seconds,
        "iterations": iterations,
        "seed": seed,
        "index_open_s": open_s,
        "curves": rows,
        "mean_retrieved": mean_retrieved,
        "mean_refined": mean_refined,
        "mean_reference": statistics.fmean(row["reference"] for row in rows),
        "ratio": mean_refined / mean_retrieved,
        "median_seconds": median_s,
        "worst_overrun_ms": worst,
        "goals": goals,
        "machine": machine_info(),
    }


def format_synthesize(result: dict) -> str:
    """The bench as a Markdown table."""
    work = (
        f"budget {result['budget_s']:g} s"
        if result["budget_s"] is not None
        else f"{result['iterations']:,} iterations"
    )

    def overrun(value: float | None) -> str:
        return "" if value is None else f"{value:.0f}"

    lines = [
        f"Synthesis over {result['paths']:,} curated paths, {result['points_per_curve']} points "
        f"a curve, {work}, frames of seed {result['seed']} "
        "(chamfer / the drawing's longest chord)",
        "",
        "| curve | retrieval only | refined | reference (even) | joints | seconds | overrun ms |",
        "|---|---|---|---|---|---|---|",
    ]
    for row in result["curves"]:
        lines.append(
            f"| {row['curve']} | {row['retrieved']:.4f} | {row['refined']:.4f} | "
            f"{row['reference']:.4f} | {row['joints']} | {row['seconds']:.2f} | "
            f"{overrun(row['overrun_ms'])} |"
        )
    lines.append(
        f"| **mean** (median s, worst overrun) | {result['mean_retrieved']:.4f} | "
        f"{result['mean_refined']:.4f} | {result['mean_reference']:.4f} | | "
        f"{result['median_seconds']:.2f} | {overrun(result['worst_overrun_ms'])} |"
    )
    lines += ["", f"refined / retrieval-only: {result['ratio']:.3f}"]
    lines += [f"{goal}: {'yes' if met else 'no'}" for goal, met in result["goals"].items()]
    return "\n".join(lines)
