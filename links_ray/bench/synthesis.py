"""`links bench synthesize`: the shipped target curves (`links_ray.bench.targets`), each
placed in a random frame, synthesized over the cached benchmark data set (`retrieval_dataset`).

Per curve: the retrieval-only chamfer (the best retrieved path's), the refined chamfer (the
best synthesis result's), the seconds `synthesize` took (retrieval included) and how far past
its budget that was (its overrun; the worst over the curves is the bench's), and a reference:
the chamfer between the curve's points and the curve itself at DEFAULT_STEPS points evenly
spaced along it, which is about what a mechanism tracing the curve exactly at an even speed
would score (the point-sampled chamfer is not 0 even then).

With `--set` (`use_set`) the curves are those of `links_ray.bench.curves.curve_set` instead, letter
strokes synthesized as partial strokes; each curve's frame is drawn from the seed and its name,
so a row does not depend on the curves before it. Besides the rows it reports, per half and per
family (and the smooth closed families together), the mean and median refined chamfer, the
mean retrieval-only chamfer, refined / retrieved, and the median and worst seconds; its goals
are the held-out half's, and its figure shows the held-out curves only. For a stroke the
retrieval-only chamfer is the best retrieved mechanism's fit over the run of its path that
matches the stroke best, as a refined one is measured.

Every row also states its answer's least transmission angle, and `min_transmission` asks the
synthesis for a floor, so the fit a floor costs is measured. With `front` each curve is
answered by the front (the best of each joint count that beats every simpler one), the row's
scores are its best answer's, and the row states each answer's joints, chamfer, transmission
and layers as a kit, and the seconds those layer plans took (planned again, one at a time):
what a buildable answer needs, and what planning it costs.
"""

from __future__ import annotations

import hashlib
import statistics
import time
from typing import TYPE_CHECKING

import numpy as np

from links_ray.bench.curves.curve_set import HALVES, curve_set
from links_ray.bench.machine import machine_info
from links_ray.bench.ordered import ordered_match
from links_ray.bench.synthesis_report import front_layers, quantiles, set_groups
from links_ray.bench.targets import TARGET_POINTS, placed, target_curves
from links_ray.cli.warm import WARM_ITERATIONS
from links_ray.engine.inputs import DEFAULT_STEPS
from links_ray.engine.kinematics.paths import chamfer, even_along, longest_chord
from links_ray.engine.kinematics.solver import simulate
from links_ray.engine.synthesis.limits import REFINE_CHECK_STEPS
from links_ray.engine.synthesis.options import (
    DEFAULT_SYNTHESIS_SECONDS,
    DEFAULT_SYNTHESIS_TRANSMISSION_DEG,
)

if TYPE_CHECKING:
    from links_ray.engine.synthesis.plan import Retriever

#: Seconds each curve is given: the most that keeps the median under MEDIAN_SECONDS_GOAL
#: (retrieval and the answer included).
BENCH_SECONDS = 4.5
#: What the bench is asked to show: refined mean at most this share of retrieval-only, and
#: below MEAN_GOAL; median seconds at most MEDIAN_SECONDS_GOAL.
RATIO_GOAL, MEAN_GOAL, MEDIAN_SECONDS_GOAL = 1 / 3, 0.010, 5.0
#: The time dial's budgets, in seconds a curve (`bench_dial`).
DIAL_SECONDS = (1.0, 3.0, 10.0, 30.0)
#: The most any curve's answer may come past its budget, in milliseconds.
OVERRUN_GOAL_MS = 50.0
#: The curve set's goals, each on the held-out half's mean refined chamfer: over all of it,
#: and over a group of its families.
SET_MEAN_GOAL = 0.012
SET_GROUP_GOALS = {
    "smooth_closed": 0.010,
    "letter_outline": 0.025,
    "letter_stroke": 0.015,
    "self_crossing": 0.012,
    "gcp_holo_test": 0.010,
}
#: Goals on a held-out family's median `dense_score`: a traced curve's mechanism exists, so
#: its best score is 0.
SET_DENSE_GOALS = {"traced": 0.001}


def chord_length(points: np.ndarray) -> float:
    """The drawing's longest chord, which every score here is divided by."""
    i, j = longest_chord(points)
    return float(np.hypot(*(points[j] - points[i])))


def even_reference(points: np.ndarray, steps: int = DEFAULT_STEPS, closed: bool = True) -> float:
    """Chamfer, divided by the longest chord, between `points` and `steps` points evenly
    spaced along their own polyline (closed or open)."""
    return chamfer(points, even_along(points, steps, closed)) / chord_length(points)


def ordered_score(points: np.ndarray, path: np.ndarray) -> float:
    """The ordered distance (`bench.ordered`) from a closed drawing's `points`, evenly spaced,
    to a traced `path`, divided by the drawing's longest chord."""
    return ordered_match(points, path).distance / chord_length(points)


def dense_score(points: np.ndarray, result: dict, steps: int = REFINE_CHECK_STEPS) -> float:
    """How far a result's path is from a closed drawing as curves, not as samples: the mean
    distance from each point of either to the other's polyline, both ways, over the drawing
    and the mechanism simulated at `steps` steps, divided by the drawing's longest chord.
    Near 0 for a mechanism that traces the drawing, where the result's own chamfer (its 200
    steps against the drawn points) keeps a sampling floor of a few thousandths."""
    mechanism = result["mechanism"]
    traced = simulate(
        mechanism["adjacency"], mechanism["node_types"], mechanism["positions"], steps
    )[result["mechanism_joint"]]
    gap = _to_polyline(points, traced).mean() + _to_polyline(traced, points).mean()
    return float(gap) / chord_length(points)


def _to_polyline(points: np.ndarray, loop: np.ndarray, block: int = 256) -> np.ndarray:
    """Each point's distance to the closed polyline `loop`."""
    start, run = loop, np.roll(loop, -1, axis=0) - loop
    length2 = np.maximum(np.einsum("ij,ij->i", run, run), 1e-300)
    out = np.empty(len(points))
    for first in range(0, len(points), block):
        p = points[first : first + block, None, :]
        t = np.clip(np.einsum("pkj,kj->pk", p - start, run) / length2, 0.0, 1.0)
        nearest = start + t[..., None] * run
        out[first : first + block] = np.sqrt(((p - nearest) ** 2).sum(axis=-1)).min(axis=1)
    return out


def name_rng(seed: int, name: str) -> np.random.Generator:
    """The generator of a set curve's frame: from the bench's seed and the curve's name."""
    return np.random.default_rng([seed, int.from_bytes(hashlib.sha256(name.encode()).digest()[:8])])


def bench_row(
    index: Retriever,
    name: str,
    points: np.ndarray,
    partial: bool = False,
    seconds: float | None = None,
    iterations: int | None = None,
    seed: int = 0,
    labels: dict | None = None,
    draw: bool = False,
    min_transmission: float = DEFAULT_SYNTHESIS_TRANSMISSION_DEG,
    front: bool = False,
) -> tuple[dict, dict | None]:
    """One curve's row of the bench, synthesized from `points` (already in their frame) over
    `index`, and with `draw` what the figure draws of it (else None). With `iterations` the
    row is counted work, the same bit for bit whatever the time, the load, the threads and the
    rows run before it; its `seconds` alone vary. `seconds`: the budget (default the synthesis
    default). `min_transmission` and `front` as `synthesize` takes them (the module says what
    the row then holds)."""
    from links_ray.engine.synthesis.kit_layers import kit_layer_count
    from links_ray.engine.synthesis.pipeline import synthesize
    from links_ray.engine.synthesis.results import fit

    seconds = DEFAULT_SYNTHESIS_SECONDS if seconds is None else seconds
    asked = {"k": 3, "partial": partial, "min_transmission": min_transmission, "front": front}
    start = time.perf_counter()
    if iterations is None:
        results = synthesize(index, points, seconds=seconds, **asked)
    else:
        results = synthesize(index, points, seed=seed, iterations=iterations, **asked)
    took = time.perf_counter() - start
    best = min(results, key=lambda result: result["chamfer"])
    best_retrieved = index.retrieve(points, 1)[0]
    mechanism = best_retrieved["mechanism"]
    retrieved = best_retrieved["chamfer"]
    if partial:
        retrieved = fit(
            points,
            mechanism["positions"],
            mechanism["adjacency"],
            mechanism["node_types"],
            best_retrieved["mechanism_joint"],
            partial=True,
        )[0]
    row = {
        "curve": name,
        **(labels or {}),
        "partial": partial,
        "retrieved": retrieved,
        "refined": best["chamfer"],
        "seconds": took,
        "overrun_ms": None if iterations is not None else (took - seconds) * 1e3,
        "reference": even_reference(points, closed=not partial),
        "ordered": None if partial else ordered_score(points, np.array(best["path"])),
        "dense": None if partial else dense_score(points, best),
        "joints": len(best["mechanism"]["node_types"]),
        "coupler_points": best["coupler_points"],
        "transmission_deg": best["min_transmission_deg"],
        "path_id": best["path_id"],
    }
    if front:
        row["front"] = [
            {
                "joints": result["n_joints"],
                "chamfer": result["chamfer"],
                "transmission_deg": result["min_transmission_deg"],
                "layers": result["layers"],
            }
            for result in results
        ]
        planning = time.perf_counter()
        for result in results:
            mechanism = result["mechanism"]
            kit_layer_count(
                np.array(mechanism["adjacency"], dtype=np.uint8),
                np.array(mechanism["node_types"], dtype=np.int8),
                np.array(mechanism["positions"], dtype=np.float64),
            )
        row["layer_seconds"] = time.perf_counter() - planning
    if not draw:
        return row, None
    drawn = {
        "curve": name,
        "points": points,
        "partial": partial,
        "retrieved_path": simulate(
            mechanism["adjacency"], mechanism["node_types"], mechanism["positions"]
        )[best_retrieved["mechanism_joint"]],
        "retrieved": retrieved,
        "refined": best["chamfer"],
        "result": best,
    }
    return row, drawn


def bench_synthesize(
    seconds: float | None = None,
    paths: int = 1_000_000,
    seed: int = 0,
    figure: str | None = None,
    iterations: int | None = None,
    use_set: bool = False,
    only: tuple[str, ...] = (),
    root: str | None = None,
    min_transmission: float = DEFAULT_SYNTHESIS_TRANSMISSION_DEG,
    front: bool = False,
) -> dict:
    """Synthesize every target curve, placed in a random frame (`seed`), over the cached data
    set of `paths` curated paths; per curve and overall (means, median seconds, the worst
    overrun past the budget). `seconds`: the budget per curve (default BENCH_SECONDS for the
    targets, the synthesis default for the set). `iterations`: counted work per curve instead of
    `seconds`, its restarts seeded with `seed` (no overrun then: there is no budget). `figure`:
    a PNG path for a picture of every curve, its best retrieved path and its refined mechanism
    (needs the `plots` extra). `use_set`: the curve set instead of the targets (its fonts need
    the `bench` extra), reported by half and family too. `only`: the names of the curves to run
    (all if empty); ValueError names one that is not there. `root`: a dataset to use instead of
    the cached one of `paths`. `min_transmission` and `front`: `bench_row`'s."""
    from links_ray.bench.data import retrieval_dataset
    from links_ray.engine.synthesis.pipeline import synthesize
    from links_ray.search.index import RetrievalIndex

    if use_set:
        curves = [
            (c.name, c.points, c.partial, {"family": c.family, "half": c.half}) for c in curve_set()
        ]
    else:
        curves = [(name, curve, False, {}) for name, curve in target_curves().items()]
    names = [name for name, *_ in curves]
    unknown = sorted(set(only) - set(names))
    if unknown:
        raise ValueError(f"no curve named {', '.join(unknown)}; the curves: {', '.join(names)}")
    if seconds is None:
        seconds = DEFAULT_SYNTHESIS_SECONDS if use_set else BENCH_SECONDS
    root = root or retrieval_dataset(paths)
    start = time.perf_counter()
    index = RetrievalIndex.open(root)
    open_s = time.perf_counter() - start
    index.warm()
    angle = np.linspace(0, 2 * np.pi, 60, endpoint=False)
    # Loads (or compiles) the refinement kernels, a closed curve's and a stroke's, so that no
    # curve pays for them: counted work, which a compile cannot cut short as it would a budget.
    ellipse = np.column_stack([np.cos(angle), 0.4 * np.sin(angle)])
    synthesize(index, ellipse, iterations=WARM_ITERATIONS)
    synthesize(index, ellipse[:30], partial=True, iterations=WARM_ITERATIONS)
    rng = np.random.default_rng(seed)
    rows = []
    drawn = []
    for name, curve, partial, labels in curves:
        # The targets' frames come one after another from the seed; each set curve's from the
        # seed and its name alone.
        points = placed(curve, name_rng(seed, name) if use_set else rng)
        if only and name not in only:
            continue
        # The set's figure is of its held-out half; the targets' of all of them.
        draw = figure is not None and (not use_set or labels["half"] == HALVES[1])
        row, picture = bench_row(
            index,
            name,
            points,
            partial,
            seconds,
            iterations,
            seed,
            labels,
            draw,
            min_transmission,
            front,
        )
        rows.append(row)
        if picture is not None:
            drawn.append(picture)
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
    groups = set_groups(rows) if use_set else None
    if groups is not None:
        held_out = {group["family"]: group for group in groups if group["half"] == HALVES[1]}
        # Judged on the held-out groups run (all of them unless `only` picks curves).
        goals = {
            f"held_out_{family}_at_most_{goal:g}": held_out[family]["mean_refined"] <= goal
            for family, goal in {"all": SET_MEAN_GOAL, **SET_GROUP_GOALS}.items()
            if family in held_out
        }
        goals |= {
            f"held_out_{family}_dense_median_at_most_{goal:g}": held_out[family]["median_dense"]
            <= goal
            for family, goal in SET_DENSE_GOALS.items()
            if family in held_out
        }
        goals["median_at_most_5_s"] = median_s <= MEDIAN_SECONDS_GOAL
    if worst is not None:
        goals["overrun_under_50_ms"] = worst < OVERRUN_GOAL_MS
    return {
        "paths": len(index),
        "points_per_curve": TARGET_POINTS,
        "budget_s": None if iterations is not None else seconds,
        "iterations": iterations,
        "seed": seed,
        "index_open_s": open_s,
        "curve_set": use_set,
        "min_transmission": min_transmission,
        "front": front,
        "transmission_deg": quantiles([row["transmission_deg"] for row in rows]),
        "layers": front_layers(rows) if front else None,
        "curves": rows,
        "groups": groups,
        "mean_retrieved": mean_retrieved,
        "mean_refined": mean_refined,
        "mean_reference": statistics.fmean(row["reference"] for row in rows),
        "ratio": mean_refined / mean_retrieved,
        "median_seconds": median_s,
        "worst_overrun_ms": worst,
        "goals": goals,
        "machine": machine_info(),
    }


def bench_dial(
    budgets: tuple[float, ...] = DIAL_SECONDS,
    paths: int = 1_000_000,
    seed: int = 0,
    use_set: bool = False,
    only: tuple[str, ...] = (),
    root: str | None = None,
) -> dict:
    """The time dial: `bench_synthesize` at each of `budgets` seconds a curve, and per half
    and family (the set's groups; the targets as one group) the mean and median refined
    chamfer at each budget."""
    runs = [
        bench_synthesize(seconds, paths, seed, use_set=use_set, only=only, root=root)
        for seconds in budgets
    ]
    dial: dict[tuple[str, str], dict] = {}
    for seconds, run in zip(budgets, runs, strict=True):
        groups = run["groups"] or [
            {
                "half": "all",
                "family": "all",
                "curves": len(run["curves"]),
                "mean_refined": run["mean_refined"],
                "median_refined": statistics.median(row["refined"] for row in run["curves"]),
                "median_seconds": run["median_seconds"],
            }
        ]
        for group in groups:
            key = (group["half"], group["family"])
            entry = dial.setdefault(
                key, {"half": key[0], "family": key[1], "curves": group["curves"], "by_budget": {}}
            )
            entry["by_budget"][f"{seconds:g}"] = {
                "mean_refined": group["mean_refined"],
                "median_refined": group["median_refined"],
                "median_seconds": group["median_seconds"],
            }
    return {
        "paths": runs[0]["paths"],
        "budgets_s": list(budgets),
        "seed": seed,
        "curve_set": use_set,
        "dial": list(dial.values()),
        "runs": runs,
        "machine": machine_info(),
    }
