"""`links bench kit`: random dataset mechanisms built as kits at the default sizes, scaled to
their cranks (`engine.fabrication.kit.kit_layers`, as a synthesis's `layers` are): how many have no
layer plan, how many layers the rest take and how often that is proven fewest, and how long a plan
takes; overall and by joint count.

The mechanisms are `engine.valid_mechanisms`' (random topologies of 8-20 joints, five valid
position sets each, from `seed`), as `links bench simulate-one` measures them. The counts
depend on the mechanisms alone; the times on the machine and its load. The paper reports
nothing on layers: these figures have nothing to stand beside.
"""

from __future__ import annotations

import statistics
import time
from collections import Counter

import numpy as np

from links_ray.bench.engine import valid_mechanisms
from links_ray.bench.machine import machine_info
from links_ray.engine.fabrication.kit import KitOptions, kit_layers
from links_ray.engine.fabrication.layers import LayeringError
from links_ray.engine.fabrication.limits import DEFAULT_CRANK_MM

__all__ = ["VARIANTS", "bench_kit", "format_kit", "kit_workload"]

#: Position sets per random topology, as `links bench simulate-one` draws them.
VARIANTS = 5

#: One mechanism: (adjacency, node_types, positions).
Mechanism = tuple[np.ndarray, np.ndarray, np.ndarray]


def kit_workload(mechanisms: int, seed: int) -> list[Mechanism]:
    """`mechanisms` valid random mechanisms drawn from `seed`, VARIANTS a topology."""
    topologies = -(-mechanisms // VARIANTS)
    return [
        (adjacency, node_types, pos)
        for adjacency, node_types, positions in valid_mechanisms(topologies, VARIANTS, seed)
        for pos in positions
    ][:mechanisms]


def _summary(rows: list[dict]) -> dict:
    """The figures of some planned mechanisms (`bench_kit`'s rows)."""
    planned = [row for row in rows if row["layers"] is not None]
    layers = [row["layers"] for row in planned]
    seconds = sorted(row["seconds"] for row in rows)
    return {
        "mechanisms": len(rows),
        "no_plan": sum(row["outcome"] == "no plan" for row in rows) / len(rows),
        "refused": sum(row["outcome"] == "refused" for row in rows) / len(rows),
        "layers": {
            "mean": statistics.fmean(layers) if layers else None,
            "median": statistics.median(layers) if layers else None,
            "max": max(layers, default=None),
            "histogram": {str(n): c for n, c in sorted(Counter(layers).items())},
        },
        "optimal": sum(row["optimal"] for row in planned) / len(planned) if planned else None,
        "statuses": dict(sorted(Counter(row["status"] for row in planned).items())),
        "seconds": {
            "median": statistics.median(seconds),
            "p90": float(np.quantile(seconds, 0.9)),
            "max": seconds[-1],
        },
    }


def bench_kit(mechanisms: int = 1000, seed: int = 0) -> dict:
    """Layer plans of `mechanisms` random dataset mechanisms at the kit's default sizes (the
    module's docstring), one at a time in this thread, each timed on the wall clock; `each`
    holds every mechanism's joints, layers and status, in the workload's order."""
    workload = kit_workload(mechanisms, seed)
    kit_layers(*workload[0])  # compiles the collision kernels outside the timing
    rows = []
    for adjacency, node_types, positions in workload:
        start = time.perf_counter()
        try:
            plan = kit_layers(adjacency, node_types, positions)
            row = {"outcome": "planned", "layers": plan.layers}
            row |= {"optimal": plan.optimal, "status": plan.status}
        except LayeringError:
            row = {"outcome": "no plan", "layers": None}
        except ValueError:  # the planner refuses it: none of a valid dataset's should be
            row = {"outcome": "refused", "layers": None}
        row["seconds"] = time.perf_counter() - start
        row["joints"] = len(node_types)
        rows.append(row)
    by_joints = {}
    for joints in sorted({row["joints"] for row in rows}):
        by_joints[str(joints)] = _summary([row for row in rows if row["joints"] == joints])
    return {
        "seed": seed,
        "sizes": {"crank": DEFAULT_CRANK_MM, **_sizes(KitOptions())},
        **_summary(rows),
        "by_joints": by_joints,
        "each": [{key: row.get(key) for key in ("joints", "layers", "status")} for row in rows],
        "machine": machine_info(),
    }


def _sizes(options: KitOptions) -> dict:
    """The sizes of a kit that the layers depend on, in mm."""
    return {
        "bar_width": options.bar_width_mm,
        "clearance": options.clearance_mm,
        "pin_diameter": options.spacer_diameter_mm,  # as the kit plans: a pin with its spacers
    }


def _share(value: float | None) -> str:
    return "-" if value is None else f"{100 * value:.1f}%"


def format_kit(result: dict) -> str:
    """No plan, layers and time to plan, overall and by joint count."""
    sizes = result["sizes"]
    lines = [
        f"{result['mechanisms']:,} random dataset mechanisms (seed {result['seed']}) as kits: "
        f"crank {sizes['crank']:g} mm, bars {sizes['bar_width']:g} mm, clearance "
        f"{sizes['clearance']:g} mm, pins (spacers) {sizes['pin_diameter']:g} mm",
        f"{'joints':<8}{'count':>7}{'no plan':>9}{'refused':>9}{'mean':>7}{'median':>8}"
        f"{'max':>5}{'optimal':>9}{'median s':>10}{'p90 s':>8}{'max s':>8}",
    ]
    rows = [*result["by_joints"].items(), ("all", result)]
    for name, row in rows:
        layers, seconds = row["layers"], row["seconds"]
        mean = "-" if layers["mean"] is None else f"{layers['mean']:.2f}"
        median = "-" if layers["median"] is None else f"{layers['median']:g}"
        most = "-" if layers["max"] is None else str(layers["max"])
        lines.append(
            f"{name:<8}{row['mechanisms']:>7}{_share(row['no_plan']):>9}"
            f"{_share(row['refused']):>9}{mean:>7}{median:>8}{most:>5}"
            f"{_share(row['optimal']):>9}{seconds['median']:>10.3f}{seconds['p90']:>8.3f}"
            f"{seconds['max']:>8.2f}"
        )
    histogram = ", ".join(f"{n}: {c}" for n, c in result["layers"]["histogram"].items())
    lines.append(f"layers (count of mechanisms): {histogram}")
    lines.append(f"statuses: {result['statuses']}")
    return "\n".join(lines)
