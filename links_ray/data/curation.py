"""From simulations to path rows (docs/reference/contract.md, Dataset layout), one shard at a time.

The trajectories come from the shard's `simulations` table or, when generation left it out,
from the engine: `simulated_trajectories` casts them to the stored type exactly as generation
does, so both give the same rows bit for bit. `trajectory_paths` is the one place rows are
made from trajectories.

One path per moving joint (simple or actuated) of every mechanism, normalized; `is_arc` when
the joint is linked to a fixed joint (the engine's `arc_flags`), `is_circle` when the variance
of the normalized points' distances from (0.5, 0.5) is below 5e-4. Curation keeps every other
path and 0.5% of the arcs and circles, by a seeded draw per path: the same seed keeps the same
paths, wherever and however often it runs. `arc_circle_counts` and `path_shares` are the one
count and share of arcs and circles, for the curation summary and `links stats` alike.
`curate_shard` is one generation shard's curation, committed: what a curator actor runs.

``path_id = 32 * mechanism_id + joint`` (mechanisms have at most 20 joints).

Pure numpy/pyarrow: no Ray.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable, Iterable, Iterator

import numpy as np
import pyarrow as pa

from links_ray.data.commit import ShardWriter
from links_ray.data.schemas import (
    MAX_LIST_VALUES,
    SCHEMAS,
    TRAJECTORY_DTYPE,
    check_path_store,
    list_array,
)
from links_ray.data.store import Store
from links_ray.engine.inputs import DEFAULT_STEPS
from links_ray.engine.kinematics.mechanism import FIXED, analyze_topology, arc_flags
from links_ray.engine.kinematics.paths import (
    CIRCLE_VARIANCE_THRESHOLD,
    circle_variances,
    normalize_paths,
)
from links_ray.engine.kinematics.solver import TopologySimulator
from links_ray.engine.kinematics.transmission import joint_transmission_deg

JOINT_BITS = 5
#: Mechanisms turned into paths at once (a default shard's 1,000 topologies): bounds a
#: curator's memory whatever the shard size.
MECHANISMS_PER_BATCH = 5000
#: Share of arcs and circles curation keeps (the paper's 0.5%).
KEEP_SHARE = 0.005


def path_ids(mechanism_ids: np.ndarray, joints: np.ndarray) -> np.ndarray:
    """int64 path ids: the mechanism id shifted left by JOINT_BITS, or'ed with the joint."""
    return (mechanism_ids.astype(np.int64) << JOINT_BITS) | joints.astype(np.int64)


def splitmix64(ids: np.ndarray, seed: int) -> np.ndarray:
    """A uint64 per id, fixed by (seed, id): splitmix64 of the pair. For one seed, distinct
    ids give distinct numbers (each step is a bijection of uint64)."""
    with np.errstate(over="ignore"):
        z = ids.astype(np.uint64) + np.uint64(seed) * np.uint64(0x9E3779B97F4A7C15)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        return z ^ (z >> np.uint64(31))


def keep_draw(ids: np.ndarray, seed: int) -> np.ndarray:
    """A uniform number in [0, 1) per id, fixed by (seed, id): `splitmix64` of the pair."""
    return (splitmix64(ids, seed) >> np.uint64(11)).astype(np.float64) / float(1 << 53)


def list_values(column: pa.ChunkedArray | pa.Array, width: int) -> np.ndarray:
    """A list column whose rows all hold `width` values, as a (rows, width) array."""
    if isinstance(column, pa.ChunkedArray):
        column = column.combine_chunks()
    return column.flatten().to_numpy(zero_copy_only=False).reshape(-1, width)


def by_mechanism_id(table: pa.Table) -> pa.Table:
    """The table in mechanism_id order (generation already writes it so: skip the copy)."""
    ids = table.column("mechanism_id").to_numpy()
    return table if np.all(ids[1:] > ids[:-1]) else table.sort_by("mechanism_id")


def simulated_trajectories(mechanisms: pa.Table, n_joints: int, steps: int) -> np.ndarray:
    """The trajectories (rows, n, steps, 2) of mechanisms rows of `n_joints` joints, simulated
    by the engine and cast to the stored type as generation casts them: the paths made from
    them are bit for bit those made from the `simulations` table.

    Consecutive rows of one topology (a topology's variants) share one simulator. A mechanism
    that locks raises ValueError: the table holds valid mechanisms only.
    """
    n = n_joints
    adjacency = list_values(mechanisms.column("adjacency"), n * n)
    node_types = list_values(mechanisms.column("node_types"), n)
    positions = list_values(mechanisms.column("positions"), 2 * n).reshape(-1, n, 2)
    positions = np.ascontiguousarray(positions, dtype=np.float64)
    out = np.empty((len(positions), n, steps, 2), dtype=TRAJECTORY_DTYPE)
    changes = np.any(adjacency[1:] != adjacency[:-1], axis=1)
    changes |= np.any(node_types[1:] != node_types[:-1], axis=1)
    starts = [0, *(np.flatnonzero(changes) + 1).tolist(), len(positions)]
    scratch = np.empty((0, n, steps, 2))  # float64, reused: fresh pages cost more than solving
    for start, stop in itertools.pairwise(starts):
        if len(scratch) < stop - start:
            scratch = np.empty((stop - start, n, steps, 2))
        simulator = TopologySimulator(adjacency[start].reshape(n, n), node_types[start])
        # The checked path's position checks cost as much as the simulation: a bad position
        # shows up as a lock or, when not finite, in the normalization.
        trajectories, lock_step, _ = simulator.run(
            positions[start:stop], steps, out=scratch[: stop - start]
        )
        if np.any(lock_step >= 0):
            row = start + int(np.argmax(lock_step >= 0))
            mechanism_id = mechanisms.column("mechanism_id")[row].as_py()
            raise ValueError(f"mechanism {mechanism_id} locks: it is not a valid mechanism")
        out[start:stop] = trajectories.astype(TRAJECTORY_DTYPE)  # as generation casts them
    return out


def trajectory_paths(mechanisms: pa.Table, trajectories: np.ndarray, n_joints: int) -> pa.Table:
    """Every moving joint's normalized path of `mechanisms` rows (in mechanism_id order), from
    their trajectories (rows, n, steps, 2) in the stored type."""
    n = n_joints
    ids = mechanisms.column("mechanism_id").to_numpy()
    steps = trajectories.shape[2]
    node_types = list_values(mechanisms.column("node_types"), n)
    adjacency = list_values(mechanisms.column("adjacency"), n * n).reshape(-1, n, n)
    is_arc = arc_flags(adjacency, node_types)
    rows, joints = np.nonzero(node_types != FIXED)
    points = normalize_paths(trajectories[rows, joints]).astype(np.float32)
    # Classified from the points as stored, so a reader recomputing it gets the same answer.
    variance = circle_variances(points)
    # One list array holds at most MAX_LIST_VALUES values (32-bit offsets): split if need be.
    per_chunk = max(1, MAX_LIST_VALUES // (steps * 2))
    flat = points.reshape(len(points), -1)
    chunks = [
        list_array(flat[start : start + per_chunk], pa.float32())
        for start in range(0, len(flat), per_chunk)
    ]
    return pa.table(
        {
            "path_id": path_ids(ids[rows], joints),
            "mechanism_id": ids[rows],
            "joint": joints.astype(np.int8),
            "points": pa.chunked_array(chunks, type=pa.list_(pa.float32())),
            "is_arc": is_arc[rows, joints],
            "is_circle": variance < CIRCLE_VARIANCE_THRESHOLD,
            "circle_variance": variance.astype(np.float32),
            "min_transmission_deg": _joint_transmission(adjacency, node_types, trajectories)[
                rows, joints
            ],
        },
        schema=SCHEMAS["paths"],
    )


def _joint_transmission(
    adjacency: np.ndarray, node_types: np.ndarray, trajectories: np.ndarray
) -> np.ndarray:
    """(rows, n) each joint's least transmission angle (`engine.kinematics.transmission`), topology
    by topology (consecutive rows of one topology share its solution path)."""
    out = np.empty(trajectories.shape[:2], dtype=np.float32)
    changes = np.any(adjacency[1:] != adjacency[:-1], axis=(1, 2))
    changes |= np.any(node_types[1:] != node_types[:-1], axis=1)
    starts = [0, *(np.flatnonzero(changes) + 1).tolist(), len(out)]
    for start, stop in itertools.pairwise(starts):
        order = analyze_topology(adjacency[start], node_types[start]).order
        out[start:stop] = joint_transmission_deg(order, trajectories[start:stop])
    return out


def path_batches(
    mechanisms: pa.Table, simulations: pa.Table | None, n_joints: int, steps: int = DEFAULT_STEPS
) -> Iterator[pa.Table]:
    """One shard's path rows in mechanism_id order, MECHANISMS_PER_BATCH mechanisms at a time
    (any row order in). Trajectories come from `simulations` (of the same mechanisms), or,
    when it is None, are simulated over `steps` steps: the rows are the same either way."""
    mechanisms = by_mechanism_id(mechanisms)
    ids = mechanisms.column("mechanism_id").to_numpy()
    if simulations is not None:
        simulations = by_mechanism_id(simulations)
        if not np.array_equal(ids, simulations.column("mechanism_id").to_numpy()):
            raise ValueError("the shard's mechanisms and simulations hold different mechanism ids")
        if len(simulations):
            steps = int(simulations.column("steps")[0].as_py())
    for start in range(0, len(ids), MECHANISMS_PER_BATCH):
        part = mechanisms.slice(start, MECHANISMS_PER_BATCH)
        if simulations is None:
            trajectories = simulated_trajectories(part, n_joints, steps)
        else:
            stored = simulations.column("trajectories").slice(start, MECHANISMS_PER_BATCH)
            trajectories = list_values(stored, n_joints * steps * 2)
            trajectories = trajectories.reshape(-1, n_joints, steps, 2)
        yield trajectory_paths(part, trajectories, n_joints)


def path_table(
    mechanisms: pa.Table, simulations: pa.Table | None, n_joints: int, steps: int = DEFAULT_STEPS
) -> pa.Table:
    """Every moving joint's normalized path of one shard's mechanisms (`path_batches` as one
    table)."""
    batches = list(path_batches(mechanisms, simulations, n_joints, steps))
    return pa.concat_tables(batches) if batches else SCHEMAS["paths"].empty_table()


def curated_mask(paths: pa.Table, seed: int) -> np.ndarray:
    """Which paths curation keeps: all that are neither arc nor circle, 0.5% of the rest."""
    common = paths.column("is_arc").to_numpy() | paths.column("is_circle").to_numpy()
    lucky = keep_draw(paths.column("path_id").to_numpy(), seed) < KEEP_SHARE
    return ~common | lucky


def arc_circle_counts(paths: pa.Table) -> dict[str, int]:
    """How many of `paths` are arcs, circles, and both."""
    is_arc = paths.column("is_arc").to_numpy(zero_copy_only=False)
    is_circle = paths.column("is_circle").to_numpy(zero_copy_only=False)
    return {
        "arcs": int(is_arc.sum()),
        "circles": int(is_circle.sum()),
        "both": int((is_arc & is_circle).sum()),
    }


def path_shares(paths: int, arcs: int, circles: int, both: int) -> dict[str, float]:
    """The shares of `paths` paths that are circles, arcs, either and both (0 with no paths),
    from the counts of `arc_circle_counts`."""
    total = paths or 1
    return {
        "circle": circles / total,
        "arc": arcs / total,
        "arc_or_circle": (arcs + circles - both) / total,
        "both": both / total,
    }


def curate_shard(
    store: Store,
    shard_id: int,
    n_joints: int,
    mechanisms_file: str,
    simulations_file: str | None,
    seed: int,
    tables: Iterable[str],
    steps: int = DEFAULT_STEPS,
    before_commit: Callable[[], None] | None = None,
    path_store: str = "points",
) -> dict:
    """Curate one committed generation shard: its `paths` and `curated` rows (those named in
    `tables`; with `path_store` "ids", without their points) written by a curation-stage
    `ShardWriter`, then its marker; returns the marker.

    With no `simulations_file` (generation left the table out) the shard's mechanisms are
    simulated again, which gives the same rows. `before_commit` runs just before the marker is
    written (a curator checks there that its run still holds the root); whatever it or the
    writing raises aborts the shard's files."""
    check_path_store(path_store)
    start = time.perf_counter()
    mechanisms = store.read_parquet(mechanisms_file)
    simulations = store.read_parquet(simulations_file) if simulations_file else None
    with ShardWriter(store, shard_id, n_joints, stage="curation") as writer:
        counts = {"paths": 0, "curated": 0, "arcs": 0, "circles": 0, "both": 0}
        for paths in path_batches(mechanisms, simulations, n_joints, steps):
            curated = paths.filter(curated_mask(paths, seed))
            for table, rows in (("paths", paths), ("curated", curated)):
                if table in tables:
                    if path_store == "ids":
                        rows = rows.drop_columns(["points"])
                    for batch in rows.to_batches(max_chunksize=50_000):
                        writer.write(table, batch)
            counts["paths"] += len(paths)
            counts["curated"] += len(curated)
            for key, count in arc_circle_counts(paths).items():
                counts[key] += count
        stats = {
            "mechanisms": len(mechanisms),
            "resimulated": 0 if simulations is not None else len(mechanisms),
            **counts,
            "seconds": time.perf_counter() - start,
        }
        if before_commit is not None:
            before_commit()
        return writer.commit(stats)
