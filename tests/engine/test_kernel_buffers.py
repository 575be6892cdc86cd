"""Every compiled kernel's entry point refuses a buffer of the wrong shape before the kernel
runs, with a ValueError naming it.

numba checks no bounds: a kernel given a buffer too small for what it writes writes past its
end, silently, and the process may crash much later. Each case below calls an entry point
with the buffers it needs (it must run), then with one of them a row short (or otherwise
misshapen): ValueError naming that buffer. tests/run runs these with numba's own bounds checks
on (tests/support/boundscheck.py), which would turn a write past an end into an IndexError.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np
import pytest

from links_ray.engine.kinematics import solver as engine_solver
from links_ray.engine.kinematics import transmission, turning
from links_ray.engine.kinematics.paths import chamfer_to_many, normalize_paths
from links_ray.engine.kinematics.sampling import PositionSampler
from links_ray.engine.kinematics.solver import TopologySimulator, crank_table
from links_ray.engine.kinematics.topology import grow_topology
from links_ray.engine.synthesis.refinement import kernels as refine_kernels
from links_ray.engine.synthesis.refinement import step_kernels
from links_ray.search import kernels, reduced

STEPS = 40


@dataclass(frozen=True)
class Case:
    """An entry point, the buffers of a good call, and the buffers to break one at a time."""

    call: Callable[..., Any]
    args: Callable[[], dict[str, Any]]
    broken: tuple[str, ...]


@cache
def mechanism(joints: int, seed: int) -> tuple[TopologySimulator, np.ndarray]:
    """A topology of `joints` joints and a valid position set of it."""
    rng = np.random.default_rng(seed)
    simulator = TopologySimulator.from_topology(grow_topology(rng, joints))
    return simulator, PositionSampler(simulator, STEPS).search(1, rng).positions[0]


def turn_args() -> dict[str, Any]:
    simulator, pos = mechanism(12, 1)
    topology = simulator.topology
    n, m = topology.n_joints, len(topology.order)
    return {
        "order": topology.order,
        "fixed": topology.fixed_joints,
        "pos": pos.copy(),
        "crank": crank_table(STEPS),
        "out": np.empty((n, STEPS, 2)),
        "geometry": np.empty((m, 3)),
    }


def simulated() -> tuple[dict[str, Any], np.ndarray]:
    args = turn_args()
    engine_solver.simulate_one(keep=True, **args)
    return args, args["out"]


def paths(count: int, points: int = 50) -> np.ndarray:
    angle = np.linspace(0, 2 * np.pi, points, endpoint=False)
    scale = np.linspace(0.3, 0.9, count)[:, None]
    raw = np.stack([np.cos(angle) * scale, np.sin(angle) + 0 * scale], axis=-1)
    return normalize_paths(raw)


def query() -> np.ndarray:
    return paths(1, 37)[0]


def owners_of(points: np.ndarray) -> np.ndarray:
    table = np.empty((kernels.TABLE_NODES,) * 2)
    owners = np.empty(table.shape, dtype=np.int32)
    kernels.distance_table(points, table, owners)
    return owners


def levels_of(points: np.ndarray) -> np.ndarray:
    levels = np.empty((kernels.LEVEL_SIDE,) * 2, dtype=np.float32)
    kernels.level_table(points, owners_of(points), levels)
    return levels


def tangent_args() -> dict[str, Any]:
    args = turn_args()
    n, m = len(args["pos"]), len(args["order"])
    del args["out"]
    return {
        **args,
        "traj": np.empty((n, STEPS, 2)),
        "dtraj": np.empty((n, STEPS, 2, 2 * n)),
        "trans": np.empty((m, STEPS)),
        "dtrans": np.empty((m, STEPS, 2 * n)),
    }


def trace_args() -> dict[str, Any]:
    args = turn_args()
    n, m = len(args["pos"]), len(args["order"])
    return {
        "orders": args["order"],
        "order_start": np.array([0, m]),
        "positions": args["pos"],
        "joint_start": np.array([0, n]),
        "mechanisms": np.array([0, 0]),
        "joints": np.array([n - 1, 1]),
        "crank": args["crank"],
        "out": np.empty((2, STEPS, 2)),
    }


def reduced_args() -> dict[str, Any]:
    args = trace_args()
    return {
        "orders": args["orders"],
        "order_start": args["order_start"],
        "joint_start": args["joint_start"],
        "mechanisms": args["mechanisms"],
        "joints": args["joints"],
        "out": np.empty(2, dtype=np.int16),
    }


def candidates_args() -> dict[str, Any]:
    args = turn_args()
    n = len(args["pos"])
    return {
        "order": args["order"],
        "fixed": args["fixed"],
        "positions": np.stack([args["pos"]] * 3),
        "crank": args["crank"],
        "keep": True,
        "out": np.empty((3, n, STEPS, 2)),
        "lock_step": np.empty(3, dtype=np.int64),
        "lock_node": np.empty(3, dtype=np.int64),
    }


def run_args() -> dict[str, Any]:
    simulator, pos = mechanism(12, 1)
    return {"positions": np.stack([pos] * 2), "out": np.empty((2, simulator.n_joints, STEPS, 2))}


def scan_args() -> dict[str, Any]:
    sketches = np.empty((300, kernels.SKETCH_BYTES), dtype=np.uint8)
    kernels.sketch_paths(paths(300), sketches)
    starts, ends, at = kernels.scan_pieces(np.array([0, 200]), np.array([100, 300]), piece=64)
    return {
        "sketches": sketches,
        "starts": starts,
        "ends": ends,
        "at": at,
        "levels": levels_of(query()),
        "slots": kernels.scan_slots(16),
        "margin": 0.01,
        "out": np.empty(200, dtype=np.float32),
        "likely": np.empty(200, dtype=np.int8),
    }


def chamfer_args() -> dict[str, Any]:
    sketches = np.empty((30, kernels.SKETCH_BYTES), dtype=np.uint8)
    kernels.sketch_paths(paths(30), sketches)
    points = query()
    return {
        "sample": np.rint(points[::3] * kernels.SKETCH_LEVELS).astype(np.int32),
        "levels": levels_of(points),
        "sketches": sketches,
        "rows": np.array([3, 29, 0, 7]),
        "variants": np.array([0, 1, 2, 3]),
        "used": kernels.SKETCH_POINTS,
        "midpoints": kernels.sketch_midpoints(50),
        "out": np.empty(4),
    }


def table_args() -> dict[str, Any]:
    table = np.empty((kernels.TABLE_NODES,) * 2)
    kernels.distance_table(query(), table, np.empty(table.shape, dtype=np.int32))
    return {"table": table, "points": paths(6), "out": np.empty((6, 4))}


def many_tables_args() -> dict[str, Any]:
    nodes = 33
    tables = np.empty((nodes, nodes, 2), dtype=np.float32)
    table = np.empty((nodes, nodes))
    for q, points in enumerate(paths(2, 20)):
        kernels.distance_table(points, table, np.empty((nodes, nodes), dtype=np.int32))
        tables[:, :, q] = table
    return {"tables": tables, "points": paths(5), "out": np.empty((5, 4, 2), dtype=np.float32)}


CASES: dict[str, Case] = {
    "dyad_geometry": Case(
        engine_solver.dyad_geometry,
        lambda: {k: v for k, v in turn_args().items() if k in ("order", "pos", "geometry")},
        ("geometry", "pos"),
    ),
    "simulate_one": Case(
        lambda **a: engine_solver.simulate_one(keep=True, **a),
        turn_args,
        ("out", "geometry", "pos"),
    ),
    "simulate_one scratch": Case(
        lambda **a: engine_solver.simulate_one(keep=False, **a),
        lambda: {**turn_args(), "out": np.empty((len(turn_args()["pos"]), 4, 2))},
        ("out", "geometry"),
    ),
    "simulate_turn": Case(engine_solver.simulate_turn, turn_args, ("out", "geometry", "pos")),
    "simulate_candidates": Case(
        engine_solver.simulate_candidates, candidates_args, ("out", "lock_step", "lock_node")
    ),
    "TopologySimulator.run": Case(
        lambda positions, out: mechanism(12, 1)[0].run(positions, STEPS, out=out),
        run_args,
        ("out",),
    ),
    "trace_joints": Case(
        engine_solver.trace_joints, trace_args, ("out", "joints", "joint_start", "positions")
    ),
    "reduced_joints": Case(
        reduced.reduced_joints, reduced_args, ("out", "joints", "joint_start", "orders")
    ),
    "turn_lock": Case(
        turning.turn_lock,
        lambda: {
            "order": (s := simulated())[0]["order"],
            "pos": s[0]["pos"],
            "geometry": s[0]["geometry"],
            "traj": s[1],
        },
        ("geometry", "traj", "pos"),
    ),
    "rigid_dyads": Case(
        turning.rigid_dyads,
        lambda: {"order": (s := simulated())[0]["order"], "traj": s[1]},
        ("traj",),
    ),
    "solve_tangents": Case(
        refine_kernels.solve_tangents,
        tangent_args,
        ("traj", "dtraj", "trans", "dtrans", "geometry", "pos"),
    ),
    "nearest_pairs": Case(
        refine_kernels.nearest_pairs,
        lambda: {
            "path": paths(1)[0],
            "target": query(),
            "path_nn": np.empty(50, dtype=np.int64),
            "path_d": np.empty(50),
            "target_nn": np.empty(37, dtype=np.int64),
            "target_d": np.empty(37),
        },
        ("path_nn", "path_d", "target_nn", "target_d"),
    ),
    "best_interval": Case(
        refine_kernels.best_interval,
        lambda: {"path": paths(1)[0], "stroke": query()[:10], "min_count": 3},
        ("path", "stroke"),
    ),
    "chamfer_system": Case(
        step_kernels.chamfer_system,
        lambda: {
            "path": paths(1)[0],
            "drawn": query(),
            "jac": np.ones((50, 2, 6)),
            "interval": (45, 10),
            "floor": 1e-4,
            "relative": 0.25,
        },
        ("path", "drawn", "jac"),
    ),
    "guard_minima": Case(
        step_kernels.guard_minima,
        lambda: {
            "trans": np.full((3, STEPS), 0.1),
            "dtrans": np.ones((3, STEPS, 6)),
            "floors": np.full(3, 0.2),
            "clearance": 0.01,
        },
        ("dtrans", "floors"),
    ),
    "guarded_minimum": Case(
        step_kernels.guarded_minimum,
        lambda: {
            "system": np.eye(4),
            "gradient": np.ones(4),
            "rows": np.eye(2, 4),
            "bounds": np.zeros(2),
        },
        ("system", "bounds"),
    ),
    "least_sines": Case(
        transmission.least_sines,
        lambda: {
            "order": (s := simulated())[0]["order"],
            "trajectories": s[1][None],
            "out": np.empty((1, len(s[0]["order"]))),
        },
        ("out", "trajectories"),
    ),
    "joint_transmission_deg": Case(
        transmission.joint_transmission_deg,
        lambda: {"order": (s := simulated())[0]["order"], "trajectories": s[1][None]},
        ("trajectories",),
    ),
    "chamfer_to_many": Case(
        chamfer_to_many,
        lambda: {"query": query(), "candidates": paths(4), "out": np.empty(4)},
        ("out",),
    ),
    "distance_fields": Case(
        kernels.distance_fields,
        lambda: {"paths": paths(6), "stride": 2, "fields": np.empty((6, kernels.GRID**2))},
        ("fields",),
    ),
    "distance_fields_serial": Case(
        kernels.distance_fields_serial,
        lambda: {"paths": paths(2), "stride": 1, "fields": np.empty((2, kernels.GRID**2))},
        ("fields",),
    ),
    "sketch_scan": Case(kernels.sketch_scan, scan_args, ("out", "likely", "sketches", "levels")),
    "distance_table": Case(
        kernels.distance_table,
        lambda: {
            "query": query(),
            "out": np.empty((kernels.TABLE_NODES,) * 2),
            "owners": np.empty((kernels.TABLE_NODES,) * 2, dtype=np.int32),
        },
        ("owners",),
    ),
    "sketch_paths": Case(
        kernels.sketch_paths,
        lambda: {"points": paths(5), "out": np.empty((5, kernels.SKETCH_BYTES), dtype=np.uint8)},
        ("out",),
    ),
    "level_table": Case(
        kernels.level_table,
        lambda: {
            "query": query(),
            "owners": owners_of(query()),
            "out": np.empty((kernels.LEVEL_SIDE,) * 2, dtype=np.float32),
        },
        ("out", "owners", "query"),
    ),
    "sketch_chamfer": Case(
        kernels.sketch_chamfer, chamfer_args, ("out", "variants", "sketches", "levels")
    ),
    "path_to_query_bounds": Case(kernels.path_to_query_bounds, table_args, ("out", "table")),
    "nearest_node_bounds": Case(kernels.nearest_node_bounds, many_tables_args, ("out",)),
    "sample_to_path_sums": Case(
        kernels.sample_to_path_sums,
        lambda: {
            "sample": query()[::4],
            "points": paths(6),
            "rows": np.array([5, 0, 2]),
            "variants": np.array([1, 0, 3]),
            "out": np.empty(3),
        },
        ("out", "variants", "points"),
    ),
}


def short(array: np.ndarray, name: str) -> np.ndarray:
    """`array` a row short: a joint short for trajectories (B, n, steps, 2), whose batch may be
    any size; a column short for a list of points (T, 2), whose length may be any."""
    if name in ("path", "stroke", "drawn"):
        return np.ascontiguousarray(array[:, :1])
    if name == "trajectories":
        return np.ascontiguousarray(array[:, :-1])
    return np.ascontiguousarray(array[:-1])


@pytest.mark.parametrize(
    ("entry", "buffer"), [(entry, name) for entry, case in CASES.items() for name in case.broken]
)
def test_a_misshapen_buffer_is_refused_by_name(entry: str, buffer: str) -> None:
    case = CASES[entry]
    case.call(**case.args())  # the right buffers: it runs
    args = case.args()
    args[buffer] = short(args[buffer], buffer)
    with pytest.raises(ValueError, match=rf"\b{buffer}\b"):
        case.call(**args)


@pytest.mark.parametrize(
    ("entry", "buffer", "index", "named"),
    [
        ("simulate_one", "order", (-1, 0), "order"),
        ("simulate_one", "fixed", (0,), "fixed"),
        ("trace_joints", "mechanisms", (1,), "mechanisms"),
        ("trace_joints", "joints", (0,), "joints"),
        ("reduced_joints", "mechanisms", (1,), "mechanisms"),
        ("reduced_joints", "joints", (0,), "joints"),
        ("reduced_joints", "orders", (0, 1), "orders"),
        ("sketch_scan", "slots", (0,), "slots"),
        ("sketch_scan", "ends", (-1,), "sketches"),
        ("sketch_chamfer", "rows", (1,), "rows"),
        ("level_table", "owners", (5, 7), "owners"),
        ("sample_to_path_sums", "rows", (2,), "rows"),
    ],
)
def test_an_index_past_a_buffer_is_refused(
    entry: str, buffer: str, index: tuple[int, ...], named: str
) -> None:
    """Indices in a buffer that point past another: ValueError naming them, before the
    kernel follows one."""
    case = CASES[entry]
    args = case.args()
    args[buffer] = args[buffer].copy()
    args[buffer][index] = 10**6
    with pytest.raises(ValueError, match=rf"\b{named}\b"):
        case.call(**args)


def test_every_entry_point_has_a_case() -> None:
    """The kernels' modules' public functions that take arrays are all above (those that
    take only sizes and make their own arrays are named here)."""
    import inspect

    making_their_own = {
        "crank_table",
        "crank_turn",
        "scan_pieces",
        "scan_slots",
        "sketch_midpoints",
        "mechanism_transmission_deg",
        "prefetch",
        "simulate",
        "simulate_batch",
        "simulate_until_lock",
        "checked_input",
    }
    covered = {entry.split()[0].split(".")[-1] for entry in CASES} | {"simulate_one"}
    modules = (engine_solver, turning, refine_kernels, step_kernels, transmission, kernels, reduced)
    for module in modules:
        for name, value in vars(module).items():
            if name.startswith("_") or name in making_their_own:
                continue
            if inspect.isfunction(value) and value.__module__ == module.__name__:
                assert name in covered, f"{module.__name__}.{name} has no case"


def test_the_turning_tests_first_mistake_is_refused() -> None:
    """A geometry sized for one topology's 9 dyads, reused for a larger topology: numba would
    write past its end (and did, in the test of the split budget); the entry point refuses it."""
    small, _ = mechanism(12, 1)
    geometry = np.empty((len(small.topology.order), 3))
    large, positions = mechanism(20, 2)
    topology = large.topology
    assert len(topology.order) > len(geometry)
    trajectory = np.empty((topology.n_joints, 2000, 2))
    with pytest.raises(ValueError, match=r"geometry must be a float64 array of shape \(\d+, 3\)"):
        engine_solver.simulate_one(
            topology.order,
            topology.fixed_joints,
            positions,
            crank_table(2000),
            True,
            trajectory,
            geometry,
        )
    with pytest.raises(ValueError, match="geometry"):
        turning.turn_lock(topology.order, positions, geometry, trajectory)
