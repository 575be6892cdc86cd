"""`links bench kit` on a few mechanisms, against `plan_layers` called directly on the same
mechanisms (`kit_workload`, the same seed), in millimetres at the kit's default sizes."""

from __future__ import annotations

import statistics

import pytest

from links_ray.bench.kit import bench_kit, format_kit, kit_workload
from links_ray.engine.fabrication.drawings import fabrication
from links_ray.engine.fabrication.kit import (
    DEFAULT_BAR_WIDTH_MM,
    DEFAULT_CLEARANCE_MM,
    DEFAULT_SPACER_DIAMETER_MM,
)
from links_ray.engine.fabrication.layers import LayeringError, plan_layers

MECHANISMS = 10


def direct(adjacency, node_types, positions) -> tuple[int | None, str | None]:
    """(layers, status) of `plan_layers` on the mechanism with its crank 20 mm long."""
    joints_mm = fabrication(adjacency, node_types, positions, crank_mm=20.0).joints_mm
    try:
        plan = plan_layers(
            adjacency,
            node_types,
            joints_mm,
            bar_width=DEFAULT_BAR_WIDTH_MM,
            clearance=DEFAULT_CLEARANCE_MM,
            pin_diameter=DEFAULT_SPACER_DIAMETER_MM,
        )
    except LayeringError:
        return None, None
    return plan.layers, plan.status


def test_bench_kit_counts_what_plan_layers_finds() -> None:
    result = bench_kit(mechanisms=MECHANISMS, seed=0)
    each = result["each"]
    assert len(each) == result["mechanisms"] == MECHANISMS
    workload = kit_workload(MECHANISMS, 0)
    for (adjacency, node_types, positions), row in zip(workload, each, strict=True):
        assert row["joints"] == len(node_types)
        layers, status = direct(adjacency, node_types, positions)
        assert (row["layers"] is None) == (layers is None)
        # The planner's work is counted, so the load changes nothing (but its wall-clock guard).
        if "time limit" not in (row["status"], status):
            assert (row["layers"], row["status"]) == (layers, status)
    # The summary is the per-mechanism rows'.
    planned = [row["layers"] for row in each if row["layers"] is not None]
    assert result["no_plan"] == pytest.approx(1 - len(planned) / MECHANISMS)
    assert result["layers"]["max"] == max(planned)
    assert result["layers"]["mean"] == pytest.approx(statistics.fmean(planned))
    assert result["layers"]["median"] == statistics.median(planned)
    assert sum(result["layers"]["histogram"].values()) == len(planned)
    optimal = sum(row["status"] == "optimal" for row in each) / len(planned)
    assert result["optimal"] == pytest.approx(optimal)
    assert sum(row["mechanisms"] for row in result["by_joints"].values()) == MECHANISMS
    seconds = result["seconds"]
    assert 0 < seconds["median"] <= seconds["p90"] <= seconds["max"]
    assert "layers (count of mechanisms)" in format_kit(result)
