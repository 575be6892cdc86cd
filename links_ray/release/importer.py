"""Import of the LINKS release's own files into a links-ray root
(docs/guides/importing-the-release.md).

The release's files are read by `release.pickles`, one batch at a time, and one file's batch at
a time: a batch's mechanisms stay in memory while its simulations are checked and dropped
(`release.checked_batch`), then its curated (j, node) pairs are read. Each batch is
split by joint count into shards committed by the commit protocol (`data.commit`) under the
root's writer lease, so an interrupted import resumes where it stopped and every shard is
committed exactly once, under ids that say where each row came from (`release.ids`):

    shard_id = SHARDS_PER_BATCH * release_batch + n_joints
    mechanism_id = BATCH_STRIDE * release_batch + release_index
    topology_id = mechanism_id // 5, variant = mechanism_id % 5   (the release's groups of 5)
    a negative's id = NEGATIVE_ID_BASE + mechanism_id

so `release_location(mechanism_id)` is the row's (release_batch, release_index). Joints keep
their release order; node types map to links-ray's: True (fixed) to FIXED (0), joint 1 to
ACTUATED (2), any other joint to SIMPLE (1). Positions are the release's float32 values as
float64, exactly.

Every mechanism is checked with links-ray's own validators and solver: at the release's angles
(`release.format.release_trajectories`' solver), compared with the release's own trajectories
where it has them; and over links-ray's own turn (DEFAULT_STEPS steps from the initial angle),
where one that locks goes to `negatives`. `paths` are links-ray's curation of the rest
(`pathset.trajectory_paths`); `curated` are the paths the release curated when it has
`curated_dataset`, else curation's seeded choice (`pathset.curated_mask`).

Pure numpy/pyarrow: no Ray.
"""

from __future__ import annotations

import contextlib
import itertools
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pyarrow as pa

from links_ray.data.commit import ShardWriter, committed_shards, remove_uncommitted
from links_ray.data.lease import Lease
from links_ray.data.pathset import (
    KEEP_SHARE,
    MECHANISMS_PER_BATCH,
    arc_circle_counts,
    curated_mask,
    path_ids,
    path_shares,
    trajectory_paths,
)
from links_ray.data.schemas import SCHEMAS, TRAJECTORY_DTYPE, list_array
from links_ray.data.shards import NEGATIVE_ID_BASE, VARIANTS
from links_ray.data.store import IMPORTED_SOURCE, META, Store
from links_ray.engine.inputs import (
    DEFAULT_STEPS,
    InvalidMechanismError,
    as_positions,
    check_positions,
)
from links_ray.engine.solver import TopologySimulator
from links_ray.engine.transmission import mechanism_transmission_deg
from links_ray.release.checked_batch import (
    AGREEMENT_TOLERANCE,
    VERDICT_STATS,
    CheckedBatch,
    node_types_of,
)
from links_ray.release.ids import BATCH_STRIDE, SHARDS_PER_BATCH
from links_ray.release.pickles import ReleaseFileError, read_batches, release_files

__all__ = ["import_release", "summarize_import"]

#: Disagreeing mechanisms named in the import summary (every shard's marker names all of its).
SHOWN_DISAGREEING = 100
IMPORT_FORMAT = 1
#: Called with "batch <b> committed" after each release batch's shards are all committed:
#: the fault tests' way to stop an import between batches.
Failpoint = Callable[[str], None]


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


def _import_shard(
    store: Store,
    batch: CheckedBatch,
    shown: str,
    n: int,
    seed: int,
    shard_id: int,
    generated: dict[int, dict],
    fence: Callable[[], None],
) -> dict:
    """Import the mechanisms of `n` joints of `batch` as shard `shard_id`: its generation
    shard (unless `generated` holds it already), then its curation shard; returns the
    curation marker, after recording the generation marker in `generated`."""
    with contextlib.ExitStack() as aborts:  # whatever is raised aborts both attempts
        stages = ("curation",) if shard_id in generated else ("curation", "shards")
        writers = {
            stage: aborts.enter_context(ShardWriter(store, shard_id, n, stage=stage))
            for stage in stages
        }

        def write(table: str, record_batch: pa.RecordBatch) -> None:
            stage = "curation" if table in ("paths", "curated") else "shards"
            if stage in writers and record_batch.num_rows:
                writers[stage].write(table, record_batch)

        indices = np.flatnonzero(batch.n_joints == n).astype(np.int64)
        stats, curation = _group_rows(batch, shown, indices, n, seed, write)
        if "shards" in writers:
            fence()
            generated[shard_id] = writers["shards"].commit(stats)
        fence()
        return writers["curation"].commit(curation)


def _following(store: Store, relative: str | None) -> Iterator[tuple[int, int, Any]] | None:
    return None if relative is None else read_batches(store, relative)


def _next_batch(batches: Iterator[tuple[int, int, Any]], shown: str, batch: int) -> Any:
    found = next(batches, None)
    if found is None:
        raise ReleaseFileError(f"{shown} ends before batch {batch}, which dataset holds")
    return found[2]


def import_release(
    src: str,
    out: str,
    seed: int = 0,
    failpoint: Failpoint | None = None,
) -> dict:
    """Import the LINKS release's files at `src` (a folder or s3://) into the root `out`;
    returns the import summary (also saved as `_links/import_summary.json`).

    `seed` draws the curated set when the release has no `curated_dataset`. Resumable: the
    shards an earlier import of the same release committed are kept. Raises ValueError
    (ReleaseFileError, StoreError) in one line for a file that cannot be read as the release
    writes it; the batches before the one at fault are committed.
    """
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    source = Store.open(src, writable=False)
    files = release_files(source)
    data_file = files["dataset"]
    if data_file is None:  # release_files refuses a folder without one
        raise ReleaseFileError(f"{source.uri} holds no release dataset")
    sims_file = files["simulation_dataset"]
    curated_file = files["curated_dataset"]
    curated_from = "release" if curated_file is not None else "seed"
    store = Store.open(out)
    start = time.perf_counter()
    with Lease.acquire(store, "writer", "links import-release") as lease:
        store.claim(
            f"{META}/run.json",
            {
                "source": IMPORTED_SOURCE,
                "release": source.uri,
                "format": IMPORT_FORMAT,
                "steps": DEFAULT_STEPS,
                "tables": ["mechanisms", "negatives"],
            },
        )
        store.claim(
            f"{META}/curation.json",
            {
                "seed": seed,
                "keep_share": KEEP_SHARE,
                "tables": ["paths", "curated"],
                "curated_from": curated_from,
            },
        )
        generated = committed_shards(store, "shards")
        curated = committed_shards(store, "curation")
        remove_uncommitted(store, "shards", generated)
        remove_uncommitted(store, "curation", curated)

        def fence() -> None:
            lease.confirm()

        sims = _following(source, sims_file)
        chosen = _following(source, curated_file)
        shown = f"{source.uri}/{data_file}"
        imported_now = 0  # valid mechanisms whose shards this run committed
        for number, _, value in read_batches(source, data_file):
            batch = CheckedBatch(shown, number, value)
            del value
            shards = [
                (n, SHARDS_PER_BATCH * number + n) for n in np.unique(batch.n_joints).tolist()
            ]
            pending = [(n, i) for n, i in shards if i not in generated or i not in curated]
            # One file's batch in memory at a time: each is reduced to what the import keeps
            # (verdicts, curated pairs) before the next is read. A batch an earlier run
            # committed is read only to reach the next.
            if sims is not None:
                solutions = _next_batch(sims, f"{source.uri}/{sims_file}", number)
                if pending:
                    batch.check_solutions(f"{source.uri}/{sims_file}", solutions)
                del solutions
            if chosen is not None:
                batch.add_curated(
                    f"{source.uri}/{curated_file}",
                    _next_batch(chosen, f"{source.uri}/{curated_file}", number),
                )
            for n, shard_id in pending:
                curated[shard_id] = _import_shard(
                    store, batch, shown, n, seed, shard_id, generated, fence
                )
                imported_now += curated[shard_id]["stats"]["mechanisms"]
            del batch
            if failpoint is not None:
                failpoint(f"batch {number} committed")
        lease.confirm()
        remove_uncommitted(store, "shards", generated)
        remove_uncommitted(store, "curation", curated)
        seconds = time.perf_counter() - start
        summary = summarize_import(store, source.uri, curated_from, seconds, imported_now)
        store.write_json(f"{META}/import_summary.json", summary)
        store.write_json(
            f"{META}/curation_summary.json",
            {
                "out": store.uri,
                "tables": ["paths", "curated"],
                "shards": summary["shards"],
                "seconds": summary["seconds"],
                "mechanisms_per_core_second": summary["mechanisms_per_second"],  # one process
                **{key: summary[key] for key in ("paths", "curated", "arcs", "circles", "both")},
                "shares": path_shares(
                    summary["paths"], summary["arcs"], summary["circles"], summary["both"]
                ),
            },
        )
    return summary


def summarize_import(
    store: Store, release: str, curated_from: str, seconds: float, imported_now: int
) -> dict:
    """The import summary, from the committed shards' markers: rows, the check against the
    release's trajectories, negatives, paths, and where the curated set came from; `seconds`
    and `mechanisms_per_second` are this run's, over the `imported_now` valid mechanisms it
    committed."""
    generated = committed_shards(store, "shards")
    curated = committed_shards(store, "curation")
    counts = (
        "mechanisms",
        "negatives",
        "topologies",
        "agreeing",
        "disagreeing",
        "locking_at_release_angles",
        "unchecked",
    )
    totals = {key: sum(m["stats"].get(key, 0) for m in generated.values()) for key in counts}
    path_counts = ("paths", "curated", "arcs", "circles", "both", "release_curated_unmatched")
    paths = {key: sum(m["stats"].get(key, 0) for m in curated.values()) for key in path_counts}
    disagreeing = sorted(i for m in generated.values() for i in m["stats"]["disagreeing_ids"])
    batches = {m["stats"]["release_batch"] for m in generated.values()}
    imported = totals["mechanisms"] + totals["negatives"]
    return {
        "out": store.uri,
        "release": release,
        "release_batches": len(batches),
        "shards": len(generated),
        **totals,
        "imported": imported,
        "worst_error": max((m["stats"]["worst_error"] for m in generated.values()), default=0.0),
        "agreement_tolerance": AGREEMENT_TOLERANCE,
        "disagreeing_ids": disagreeing[:SHOWN_DISAGREEING],
        **paths,
        "curated_from": curated_from,
        "seconds": seconds,
        "imported_this_run": imported_now,
        "mechanisms_per_second": imported_now / seconds if imported_now and seconds else None,
    }
