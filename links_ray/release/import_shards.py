"""One shard of an import of the LINKS release: a release batch's mechanisms of one joint
count (`ShardPart`), checked, turned into rows and committed on its own (`import_part`).

A part holds what its shard reads and nothing of the rest of its batch: its mechanisms by
batch index (`CheckedBatch.part`), the release's trajectories of them and their curated
(j, node) pairs. So a part can be imported in the process that read the release or handed to
another one (`links import-release` on Ray), with the same rows: its rows depend only on the
part, the seed and the tables chosen (`ImportOptions`). Its shard is committed by the commit
protocol (`data.commit`), generation stage then curation stage, exactly once whoever tries.

Pure numpy/pyarrow: no Ray.
"""

from __future__ import annotations

import contextlib
import itertools
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np
import pyarrow as pa

from links_ray.data.commit import ShardWriter
from links_ray.data.curation import (
    MECHANISMS_PER_BATCH,
    arc_circle_counts,
    curated_mask,
    path_ids,
    trajectory_paths,
)
from links_ray.data.generation import NEGATIVE_ID_BASE, VARIANTS
from links_ray.data.schemas import (
    CURATION_TABLES,
    SCHEMAS,
    TRAJECTORY_DTYPE,
    check_path_store,
    choose_tables,
    list_array,
)
from links_ray.data.store import Store
from links_ray.engine.inputs import (
    DEFAULT_STEPS,
    InvalidMechanismError,
    as_positions,
    check_positions,
)
from links_ray.engine.kinematics.solver import TopologySimulator
from links_ray.engine.kinematics.transmission import mechanism_transmission_deg
from links_ray.release.checked_batch import VERDICT_STATS, CheckedBatch, Solution, node_types_of
from links_ray.release.ids import BATCH_STRIDE
from links_ray.release.pickles import ReleaseFileError

__all__ = ["IMPORT_TABLES", "ImportOptions", "ShardPart", "import_part"]

#: The tables an import may write: generation's but `simulations` (the release's trajectories
#: are checked, not stored), and curation's.
IMPORT_TABLES = ("mechanisms", "negatives", *CURATION_TABLES)
#: What `--store ids` writes unless told otherwise: the lean root of `links generate --tables
#: mechanisms` then `links curate --store ids`.
LEAN_TABLES = ("mechanisms", "curated")


@dataclass(frozen=True)
class ImportOptions:
    """What an import writes: `tables` (of IMPORT_TABLES), the path tables' `path_store`
    ("points", or "ids": ids and flags without points), and the `seed` of the curated choice
    when the release has no `curated_dataset`."""

    seed: int = 0
    tables: tuple[str, ...] = IMPORT_TABLES
    path_store: str = "points"

    @classmethod
    def checked(
        cls, seed: int = 0, tables: str | Iterable[str] | None = None, path_store: str = "points"
    ) -> ImportOptions:
        """The options, each checked; ValueError in one line for a bad one. `tables` is names
        or one comma-separated string, default all of IMPORT_TABLES (with `path_store` "ids",
        LEAN_TABLES); it must hold `mechanisms` and a path table."""
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
        check_path_store(path_store)
        if tables is None:
            tables = LEAN_TABLES if path_store == "ids" else IMPORT_TABLES
        chosen = choose_tables(tables, IMPORT_TABLES, required="mechanisms")
        if not set(chosen) & set(CURATION_TABLES):
            raise ValueError(f"tables must include paths or curated, got {', '.join(chosen)}")
        return cls(seed=seed, tables=chosen, path_store=path_store)

    def stage_tables(self, stage_tables: tuple[str, ...]) -> list[str]:
        """The chosen tables of one stage (GENERATION_TABLES or CURATION_TABLES)."""
        return [table for table in self.tables if table in stage_tables]


@dataclass
class ShardPart:
    """One shard of an import: the mechanisms of `n_joints` joints of a release batch (a
    `CheckedBatch.part`, read from `shown`), the release's trajectories of them (`solutions`,
    from `solutions_shown`; None once checked, or when the release has none), and the shard's
    generation marker if an earlier run committed that stage (`generated`)."""

    shard_id: int
    n_joints: int
    batch: CheckedBatch
    shown: str
    solutions: list[Solution] | None = None
    solutions_shown: str = ""
    generated: dict | None = None

    @property
    def mechanisms(self) -> int:
        """The release's mechanisms in this shard, valid or not."""
        return len(self.batch.x0)

    def check_solutions(self) -> None:
        """Check the part's mechanisms against the release's trajectories, then drop them."""
        if self.solutions is not None:
            self.batch.check_solutions(self.solutions_shown, self.solutions)
            self.solutions = None


def import_part(
    store: Store, part: ShardPart, fence: Callable[[], None], options: ImportOptions
) -> dict:
    """Check `part` against the release's trajectories, then write and commit its shard at
    `store`: its generation stage (unless `part.generated` holds it), then its curation stage,
    `fence` called before each commit (it raises if the run lost the root). Returns the two
    markers, {"shards": ..., "curation": ...}; ReleaseFileError in one line for a trajectory of
    the wrong shape or type."""
    part.check_solutions()
    with contextlib.ExitStack() as aborts:  # whatever is raised aborts both attempts
        stages = ("curation",) if part.generated is not None else ("curation", "shards")
        writers = {
            stage: aborts.enter_context(
                ShardWriter(store, part.shard_id, part.n_joints, stage=stage)
            )
            for stage in stages
        }
        ids_only = options.path_store == "ids"

        def write(table: str, record_batch: pa.RecordBatch) -> None:
            stage = "curation" if table in CURATION_TABLES else "shards"
            if stage in writers and table in options.tables and record_batch.num_rows:
                if ids_only and stage == "curation":
                    names = [name for name in record_batch.schema.names if name != "points"]
                    record_batch = record_batch.select(names)
                writers[stage].write(table, record_batch)

        batch = part.batch
        indices = np.array(sorted(batch.x0), dtype=np.int64)
        stats, curation = _group_rows(
            batch, part.shown, indices, part.n_joints, options.seed, write
        )
        generated = part.generated
        if "shards" in writers:
            fence()
            generated = writers["shards"].commit(stats)
        fence()
        return {"shards": generated, "curation": writers["curation"].commit(curation)}


def _rows(table: str, columns: dict[str, np.ndarray]) -> pa.RecordBatch:
    arrays = []
    for field in SCHEMAS[table]:
        values = columns[field.name]
        if pa.types.is_list(field.type):
            arrays.append(list_array(values.reshape(len(values), -1), field.type.value_type))
        else:
            arrays.append(pa.array(values, type=field.type))
    return pa.RecordBatch.from_arrays(arrays, schema=SCHEMAS[table])


def _group_rows(
    batch: CheckedBatch,
    shown: str,
    indices: np.ndarray,
    n: int,
    seed: int,
    write: Callable[[str, pa.RecordBatch], None],
) -> tuple[dict, dict]:
    """Hand the rows of one joint count of a batch to `write(table, record_batch)`
    (`mechanisms`, `negatives`, `paths`, `curated`), MECHANISMS_PER_BATCH mechanisms at a time;
    returns the generation stats and the curation stats."""
    start = time.perf_counter()
    stats: dict[str, Any] = {
        "release_batch": batch.batch,
        "mechanisms": 0,
        "negatives": 0,
        "topologies": 0,
        "agreeing": 0,
        "disagreeing": 0,
        "locking_at_release_angles": 0,
        "unchecked": 0,
        "worst_error": 0.0,
        "disagreeing_ids": [],
    }
    curation = {
        "mechanisms": 0,
        "resimulated": 0,
        "paths": 0,
        "curated": 0,
        "arcs": 0,
        "circles": 0,
        "both": 0,
        "release_curated_unmatched": 0,
    }
    ids_all = BATCH_STRIDE * batch.batch + indices
    stats["topologies"] = len(np.unique(ids_all // VARIANTS))
    released_curated = None
    if batch.curated is not None:
        wanted = [(j, node) for j, node in batch.curated if batch.n_joints[j] == n]
        released_curated = path_ids(
            BATCH_STRIDE * batch.batch + np.array([j for j, _ in wanted], dtype=np.int64),
            np.array([node for _, node in wanted], dtype=np.int64),
        )
        matched = 0
    for lo in range(0, len(indices), MECHANISMS_PER_BATCH):
        part = indices[lo : lo + MECHANISMS_PER_BATCH]
        ids = ids_all[lo : lo + MECHANISMS_PER_BATCH]
        adjacency = np.stack([batch.adjacency[j] for j in part]).astype(np.uint8)
        node_types = np.stack([node_types_of(batch.fixed[j]) for j in part])
        positions = np.stack([batch.x0[j] for j in part]).astype(np.float64)
        trajectories = np.empty((len(part), n, DEFAULT_STEPS, 2), dtype=TRAJECTORY_DTYPE)
        lock_step = np.empty(len(part), dtype=np.int64)
        lock_node = np.empty(len(part), dtype=np.int64)
        min_deg = np.empty(len(part), dtype=np.float32)
        changes = np.any(adjacency[1:] != adjacency[:-1], axis=(1, 2))
        changes |= np.any(node_types[1:] != node_types[:-1], axis=1)
        starts = [0, *(np.flatnonzero(changes) + 1).tolist(), len(part)]
        for first, stop in itertools.pairwise(starts):
            where = f"{shown} batch {batch.batch} index {int(part[first])}"
            topology = batch.topology(int(part[first]))
            try:
                group = as_positions(positions[first:stop], n, batch=True)
                check_positions(topology.adjacency, group, topology.links)
            except InvalidMechanismError as exc:
                raise ReleaseFileError(f"{where}: {exc}") from None
            for k in range(first, stop):
                verdict, error = batch.verdict(int(part[k]))
                stats[VERDICT_STATS[verdict]] += 1
                if verdict in ("agree", "disagree"):
                    stats["worst_error"] = max(stats["worst_error"], error)
                if verdict == "disagree":
                    stats["disagreeing_ids"].append(int(ids[k]))
            simulator = TopologySimulator.from_topology(topology)
            turned, steps_locked, nodes_locked = simulator.run(positions[first:stop], DEFAULT_STEPS)
            trajectories[first:stop] = turned.astype(TRAJECTORY_DTYPE)
            lock_step[first:stop] = steps_locked
            lock_node[first:stop] = nodes_locked
            valid = steps_locked < 0
            min_deg[first:stop] = 0.0
            if valid.any():
                min_deg[first:stop][valid] = mechanism_transmission_deg(
                    topology.order, trajectories[first:stop][valid]
                )
        valid = lock_step < 0
        shared = {
            "topology_id": ids // VARIANTS,
            "variant": (ids % VARIANTS).astype(np.int8),
            "adjacency": adjacency.reshape(len(part), -1),
            "node_types": node_types,
            "positions": positions.reshape(len(part), -1),
        }
        if valid.any():
            chosen = {key: value[valid] for key, value in shared.items()}
            mechanisms = _rows(
                "mechanisms",
                {"mechanism_id": ids[valid], "min_transmission_deg": min_deg[valid], **chosen},
            )
            write("mechanisms", mechanisms)
            paths = trajectory_paths(pa.Table.from_batches([mechanisms]), trajectories[valid], n)
            if released_curated is None:
                keep = curated_mask(paths, seed)
            else:
                keep = np.isin(paths.column("path_id").to_numpy(), released_curated)
                matched += int(keep.sum())
            curated = paths.filter(keep)
            for table, rows in (("paths", paths), ("curated", curated)):
                for record_batch in rows.to_batches():
                    write(table, record_batch)
            curation["mechanisms"] += int(valid.sum())
            curation["paths"] += len(paths)
            curation["curated"] += len(curated)
            for key, count in arc_circle_counts(paths).items():
                curation[key] += count
        if not valid.all():
            locked = ~valid
            chosen = {key: value[locked] for key, value in shared.items()}
            write(
                "negatives",
                _rows(
                    "negatives",
                    {
                        "mechanism_id": NEGATIVE_ID_BASE + ids[locked],
                        "locked_step": lock_step[locked].astype(np.int16),
                        "locked_node": lock_node[locked].astype(np.int16),
                        **chosen,
                    },
                ),
            )
        stats["mechanisms"] += int(valid.sum())
        stats["negatives"] += int((~valid).sum())
    if released_curated is not None:
        curation["release_curated_unmatched"] = len(released_curated) - matched
    seconds = time.perf_counter() - start
    stats["seconds"] = seconds
    curation["seconds"] = 0.0  # the group's time is counted once, in the generation stats
    return stats, curation
