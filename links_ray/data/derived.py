"""Rows a lean root does not store, derived from its mechanisms, bit for bit.

A lean root keeps what cannot be recomputed: its mechanisms (`links generate --tables
mechanisms`) and its curated set as ids and flags without points (`links curate --store ids`).
Every trajectory and path is a pure function of its mechanism: simulated and cast as
generation casts it (`pathset.simulated_trajectories`), then normalized
(`pathset.path_batches`). Readers derive them here, one generation shard at a time, with the
code that writes them, so a derived row equals the stored one of a root curated with points.

Which tables a root derives (`derived_tables`): `simulations` and `paths` when no shard stored
them, `curated` when its files hold no points. A curated file of ids is checked against its
shard's derived paths: every id must be among them, in order, or the reader says so.

Memory is bounded by a shard's mechanisms file and `pathset.MECHANISMS_PER_BATCH` mechanisms'
trajectories at a time, whatever the root's size. Pure numpy/pyarrow: no Ray.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from links_ray.data.commit import SHARD_NAME, committed_files, committed_shards
from links_ray.data.curation import (
    JOINT_BITS,
    MECHANISMS_PER_BATCH,
    by_mechanism_id,
    path_batches,
    simulated_trajectories,
)
from links_ray.data.schemas import SCHEMAS, list_array
from links_ray.data.store import META, Store
from links_ray.engine.inputs import DEFAULT_STEPS

__all__ = [
    "DERIVABLE_TABLES",
    "PathFilter",
    "derived_batches",
    "derived_schema",
    "derived_shards",
    "derived_tables",
    "derives",
    "file_batches",
    "file_schema",
    "has_points",
    "rows_of_ids",
    "shard_batches",
]

#: Which of some path ids (N,) int64 a read keeps: a mask (N,) bool.
PathFilter = Callable[[np.ndarray], np.ndarray]

#: Tables a lean root may derive instead of storing.
DERIVABLE_TABLES = ("simulations", "paths", "curated")


def has_points(schema: pa.Schema) -> bool:
    """Whether a path table's files hold their points (a lean root's hold ids and flags)."""
    return "points" in schema.names


def file_schema(store: Store, relative: str) -> pa.Schema:
    """The columns of one Parquet file of the root."""
    with store.fs.open_input_file(store.path(relative)) as source:
        return pq.ParquetFile(source).schema_arrow


def derives(store: Store, table: str) -> bool:
    """Whether `store`'s root derives `table`: once it has generated mechanisms, `simulations`
    and `paths` when no shard stored them, and `paths` and `curated` when their files hold ids
    without points (the curated set is chosen by curation, never derived without it). Reads
    each stage's markers once."""
    if table not in DERIVABLE_TABLES:
        return False
    generated = committed_shards(store, "shards")
    if not committed_files(store, "mechanisms", generated):
        return False
    if table == "simulations":
        return not committed_files(store, "simulations", generated)
    files = committed_files(store, table)
    if not files:
        return table == "paths"
    return not has_points(file_schema(store, files[0]))


def derived_tables(store: Store) -> tuple[str, ...]:
    """The tables `store`'s root derives (`derives`)."""
    return tuple(table for table in DERIVABLE_TABLES if derives(store, table))


def _steps(store: Store) -> int:
    """The steps of the root's simulations, as its run record gives them."""
    run = store.read_json(f"{META}/run.json") or {}
    return int(run.get("steps", DEFAULT_STEPS))


def _shard_of(relative: str) -> int:
    found = SHARD_NAME.fullmatch(relative.rsplit("/", 1)[-1])
    if found is None:
        raise ValueError(f"{relative} is not a shard file")
    return int(found.group(2))


def _simulation_batches(mechanisms: pa.Table, n_joints: int, steps: int) -> Iterator[pa.Table]:
    """A shard's `simulations` rows, MECHANISMS_PER_BATCH mechanisms at a time."""
    mechanisms = by_mechanism_id(mechanisms)
    for start in range(0, len(mechanisms), MECHANISMS_PER_BATCH):
        part = mechanisms.slice(start, MECHANISMS_PER_BATCH)
        trajectories = simulated_trajectories(part, n_joints, steps)
        schema = SCHEMAS["simulations"]
        yield pa.table(
            {
                "mechanism_id": part.column("mechanism_id"),
                "steps": np.full(len(part), steps, dtype=np.int16),
                "trajectories": list_array(
                    trajectories.reshape(len(part), -1),
                    schema.field("trajectories").type.value_type,
                ),
            },
            schema=schema,
        )


def rows_of_ids(paths: Iterable[pa.Table], ids: np.ndarray, where: str) -> Iterator[pa.Table]:
    """The rows of `paths` (one shard's, in order) whose path ids are `ids`, checked to be all
    of them, in order; `where` names the ids' file in the error."""
    found = 0
    wanted = pa.array(ids)
    for batch in paths:
        kept = batch.filter(pc.is_in(batch.column("path_id"), value_set=wanted))
        got = kept.column("path_id").to_numpy()
        if not np.array_equal(got, ids[found : found + len(got)]):
            raise ValueError(f"{where}: its curated ids are not among its mechanisms' paths")
        found += len(got)
        yield kept
    if found != len(ids):
        raise ValueError(
            f"{where}: {len(ids) - found} of its curated ids are not among its mechanisms' paths"
        )


def _shard_tables(
    store: Store,
    table: str,
    marker: dict,
    ids_file: str | None,
    steps: int,
    keeps: PathFilter | None = None,
) -> Iterator[pa.Table]:
    """One generation shard's rows of `table` over `steps` steps, derived; with `ids_file` (the
    shard's file of path ids, for `paths` or `curated`), those rows only, and of those only
    the ones `keeps` holds, when given: only their mechanisms are simulated."""
    n_joints = int(marker["n_joints"])
    mechanisms = store.read_parquet(marker["files"]["mechanisms"])
    if table == "simulations":
        yield from _simulation_batches(mechanisms, n_joints, steps)
        return
    if ids_file is None:
        yield from path_batches(mechanisms, None, n_joints, steps)
        return
    ids = store.read_parquet(ids_file, columns=["path_id"]).column("path_id").to_numpy()
    if keeps is not None:
        ids = ids[keeps(ids)]
        # A mechanism's paths are simulated and normalized row by row, the same in any
        # company, so the rows of a few of the shard's mechanisms equal their rows of all.
        needed = pa.array(np.unique(ids >> JOINT_BITS))
        mechanisms = mechanisms.filter(pc.is_in(mechanisms.column("mechanism_id"), needed))
    paths = path_batches(mechanisms, None, n_joints, steps)
    yield from rows_of_ids(paths, ids, f"{store.uri}/{ids_file}")


def derived_schema(table: str) -> pa.Schema:
    """The columns of `table`'s derived rows: the stored table's, and its `n_joints`."""
    return SCHEMAS[table].append(pa.field("n_joints", pa.int16()))


def derived_shards(store: Store, table: str, n_joints: Iterable[int] | None = None) -> list[dict]:
    """The generation shards whose rows of `table` a read derives, in order (only shards of
    `n_joints` joints, when given; for a table stored as ids, only the shards it holds): for
    each, its generation `marker`, its `ids_file` (None when the table is not stored) and the
    root's `steps`."""
    if table not in DERIVABLE_TABLES:
        raise ValueError(f"table must be one of {', '.join(DERIVABLE_TABLES)}, got {table!r}")
    wanted = None if n_joints is None else {int(n) for n in n_joints}
    stored = [] if table == "simulations" else committed_files(store, table)
    ids_files = {_shard_of(relative): relative for relative in stored}
    steps = _steps(store)
    return [
        {"marker": marker, "ids_file": ids_files.get(shard), "steps": steps}
        for shard, marker in sorted(committed_shards(store, "shards").items())
        if (wanted is None or int(marker["n_joints"]) in wanted)
        and (not ids_files or shard in ids_files)
    ]


def shard_batches(store: Store, table: str, shard: dict) -> Iterator[pa.Table]:
    """The derived rows of `table` of one shard of `derived_shards`, with `n_joints` typed as
    a read of the stored table gives it (`derived_schema`)."""
    marker = shard["marker"]
    count = int(marker["n_joints"])
    for rows in _shard_tables(store, table, marker, shard["ids_file"], shard["steps"]):
        n_joints = pa.array(np.full(len(rows), count, dtype=np.int16))
        yield rows.append_column("n_joints", n_joints)


def derived_batches(
    store: Store, table: str, n_joints: Iterable[int] | None = None
) -> Iterator[pa.Table]:
    """Every row of `table` at `store`'s root, derived shard by shard in shard order (only
    shards of `n_joints` joints, when given), with its `n_joints` as a stored table's read
    gives it; `table` one of `derived_tables(store)`."""
    for shard in derived_shards(store, table, n_joints):
        yield from shard_batches(store, table, shard)


def file_batches(
    store: Store,
    table: str,
    files: list[str],
    columns: list[str],
    block: int,
    keeps: PathFilter | None = None,
) -> Iterator[pa.RecordBatch]:
    """Record batches of up to `block` rows of these committed files of a path table, in
    order, with `columns`: read as stored, or, for a file without the points that `columns`
    name, derived from its shard's mechanisms. With `keeps`, only the rows whose path ids it
    holds (`keeps(path_ids)` is a mask)."""
    generated: dict[int, dict] | None = None
    read = columns if keeps is None or "path_id" in columns else [*columns, "path_id"]
    for relative in files:
        with store.fs.open_input_file(store.path(relative)) as source:
            stored = pq.ParquetFile(source)
            if "points" not in columns or has_points(stored.schema_arrow):
                for batch in stored.iter_batches(batch_size=block, columns=read):
                    yield _kept(batch, keeps).select(columns)
                continue
        if generated is None:  # once, at the first file to derive
            generated, steps = committed_shards(store, "shards"), _steps(store)
        marker = generated.get(_shard_of(relative))
        if marker is None:
            raise ValueError(f"{store.uri}/{relative}: its generation shard is not committed")
        for rows in _shard_tables(store, table, marker, relative, steps, keeps):
            yield from rows.select(columns).to_batches(max_chunksize=block)


def _kept(batch: pa.RecordBatch, keeps: PathFilter | None) -> pa.RecordBatch:
    if keeps is None:
        return batch
    return batch.filter(pa.array(keeps(batch.column("path_id").to_numpy())))
