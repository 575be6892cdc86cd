"""From simulations to path rows (docs/CONTRACT.md, Dataset layout), for one shard at a time.

One path per moving joint (simple or actuated) of every mechanism, normalized; `is_arc` when
the joint is linked to a fixed joint (the engine's `arc_flags`), `is_circle` when the variance
of the normalized points' distances from (0.5, 0.5) is below 5e-4. Curation keeps every other
path and 0.5% of the arcs and circles, by a seeded draw per path: the same seed keeps the same
paths, wherever and however often it runs. `arc_circle_counts` and `path_shares` are the one
count and share of arcs and circles, for the curation summary and `links stats` alike.

``path_id = 32 * mechanism_id + joint`` (mechanisms have at most 20 joints).

Pure numpy/pyarrow: no Ray.
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa

from links_ray.data.schemas import SCHEMAS
from links_ray.engine.mechanism import FIXED, arc_flags
from links_ray.engine.paths import CIRCLE_VARIANCE_THRESHOLD, circle_variances, normalize_paths

JOINT_BITS = 5
#: Share of arcs and circles curation keeps (the paper's 0.5%).
KEEP_SHARE = 0.005


def path_ids(mechanism_ids: np.ndarray, joints: np.ndarray) -> np.ndarray:
    return (mechanism_ids.astype(np.int64) << JOINT_BITS) | joints.astype(np.int64)


def keep_draw(ids: np.ndarray, seed: int) -> np.ndarray:
    """A uniform number in [0, 1) per id, fixed by (seed, id): splitmix64 of the pair."""
    with np.errstate(over="ignore"):
        z = ids.astype(np.uint64) + np.uint64(seed) * np.uint64(0x9E3779B97F4A7C15)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        z = z ^ (z >> np.uint64(31))
    return (z >> np.uint64(11)).astype(np.float64) / float(1 << 53)


def _list_values(column: pa.ChunkedArray, width: int) -> np.ndarray:
    """A list column whose rows all hold `width` values, as a (rows, width) array."""
    flat = column.combine_chunks().flatten().to_numpy(zero_copy_only=False)
    return flat.reshape(-1, width)


def _by_id(table: pa.Table) -> pa.Table:
    """The table in mechanism_id order (generation already writes it so: skip the copy)."""
    ids = table.column("mechanism_id").to_numpy()
    return table if np.all(ids[1:] > ids[:-1]) else table.sort_by("mechanism_id")


def path_table(mechanisms: pa.Table, simulations: pa.Table, n_joints: int) -> pa.Table:
    """Every moving joint's normalized path of one shard's mechanisms (any row order)."""
    mechanisms, simulations = _by_id(mechanisms), _by_id(simulations)
    ids = mechanisms.column("mechanism_id").to_numpy()
    if not np.array_equal(ids, simulations.column("mechanism_id").to_numpy()):
        raise ValueError("the shard's mechanisms and simulations hold different mechanism ids")
    n = n_joints
    steps = int(simulations.column("steps")[0].as_py()) if len(simulations) else 200
    node_types = _list_values(mechanisms.column("node_types"), n)
    adjacency = _list_values(mechanisms.column("adjacency"), n * n).reshape(-1, n, n)
    trajectories = _list_values(simulations.column("trajectories"), n * steps * 2)
    trajectories = trajectories.reshape(-1, n, steps, 2)

    is_arc = arc_flags(adjacency, node_types)
    rows, joints = np.nonzero(node_types != FIXED)
    points = normalize_paths(trajectories[rows, joints]).astype(np.float32)
    # Classified from the points as stored, so a reader recomputing it gets the same answer.
    variance = circle_variances(points)
    return pa.table(
        {
            "path_id": path_ids(ids[rows], joints),
            "mechanism_id": ids[rows],
            "joint": joints.astype(np.int8),
            "points": pa.ListArray.from_arrays(
                pa.array(np.arange(0, (len(rows) + 1) * steps * 2, steps * 2, dtype=np.int32)),
                pa.array(points.ravel(), type=pa.float32()),
            ),
            "is_arc": is_arc[rows, joints],
            "is_circle": variance < CIRCLE_VARIANCE_THRESHOLD,
            "circle_variance": variance.astype(np.float32),
        },
        schema=SCHEMAS["paths"],
    )


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
