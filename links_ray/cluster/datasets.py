"""`ray_dataset`: one table's committed rows as a Ray Dataset, to stream into training.

The files are those commit markers name (`links_ray.data.commit`), as for `links_ray.load`, so
an interrupted shard shows no row; Ray Data reads them block by block, so a table far larger
than memory streams through `iter_batches` or `iter_torch_batches` without pandas in between.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Iterator, Sequence

import numpy as np
import pyarrow as pa
import pyarrow.dataset as pads
import ray
from ray.data.datasource import Partitioning

from links_ray.cluster.connect import connect
from links_ray.data.dataset import check_columns, derives_rows, joint_count_filter, open_table
from links_ray.data.derived import derived_schema, derived_shards, shard_batches
from links_ray.data.splits import check_fractions, check_split, split_mask, with_split_key
from links_ray.data.store import Store


def ray_dataset(
    root: str | Store,
    table: str,
    n_joints: int | Iterable[int] | None = None,
    columns: list[str] | None = None,
    filter: pads.Expression | None = None,
    split: str | None = None,
    split_fractions: Sequence[float] | None = None,
) -> ray.data.Dataset:
    """The committed rows of `table` at `root` (a folder, s3://bucket/prefix or a Store) as a
    `ray.data.Dataset`, with the partition column `n_joints`.

    `n_joints` keeps one joint count or several (only their files are read); `columns` keeps
    those columns; `filter` is a pyarrow expression on any column read, applied block by block
    as the files are read (`pyarrow.dataset.field("min_transmission_deg") >= 10`); `split`
    ("train", "validation" or "test") keeps the rows of that split's topologies
    (`links_ray.split_of`, `split_fractions` as there), block by block too. Joins the Ray
    cluster of `RAY_ADDRESS`, or starts a local Ray, unless one is running.

    On a lean root (`links curate --store ids`) the rows it does not store are derived from
    its mechanisms, a Ray task a generation shard (`links_ray.data.derived`): the rows of a
    root that stores them, bit for bit.
    """
    store = root if isinstance(root, Store) else Store.open(root, writable=False)
    sizes = None
    if n_joints is not None:
        sizes = [n_joints] if isinstance(n_joints, int | np.integer) else list(n_joints)
        if not all(isinstance(n, int | np.integer) and not isinstance(n, bool) for n in sizes):
            raise ValueError(f"n_joints must be an integer or integers, got {n_joints!r}")
    derived = derives_rows(store, table, columns)
    if derived:
        # A lean root: each generation shard's rows derived by a task (data.derived).
        parts: list = derived_shards(store, table, sizes)
        names = derived_schema(table).names
    else:
        dataset = open_table(store, table)
        # Only the files of the joint counts asked for, chosen by the table's own partitioning.
        parts = [f.path for f in dataset.get_fragments(filter=joint_count_filter(n_joints))]
        names = dataset.schema.names
    if sizes is not None and not parts:
        raise ValueError(f"{store.uri} has no {table} rows of {sorted(set(sizes))} joints")
    check_columns(names, table, columns)
    if filter is not None and not isinstance(filter, pads.Expression):
        raise ValueError(f"filter must be a pyarrow.dataset expression, got {filter!r}")
    read = columns
    if split is not None:
        check_split(split)
        check_fractions(split_fractions)
        read = with_split_key(columns, names)
    connect()
    if derived:
        rows = _derived_rows(store.uri, table, parts)
    else:
        rows = _read_files(parts, store.fs, store.path(table))
    if read is not None:
        # Ray 2.60 deprecates read_parquet's `columns=`; the selection is pushed into the scan.
        rows = rows.select_columns(read)
    if filter is None and split is None:
        return rows
    # Ray's read_parquet takes no pyarrow filter: each block is filtered as it is read.
    added = [] if read == columns else [read[-1]]  # the split's key, read for the split only
    keep = {"where": filter, "split": split, "fractions": split_fractions, "drop": added}
    return rows.map_batches(_keep, fn_kwargs=keep, batch_format="pyarrow")


def _derived_rows(uri: str, table: str, shards: list[dict]) -> ray.data.Dataset:
    """The rows of `table` that the generation shards `shards` (`derived_shards`) of the root
    at `uri` derive, a task a shard, each streaming its blocks as it derives them."""
    items = ray.data.from_items([{"shard": json.dumps(shard)} for shard in shards])
    return items.repartition(len(shards)).map_batches(
        _derive, fn_kwargs={"uri": uri, "table": table}, batch_size=1, batch_format="pyarrow"
    )


def _derive(batch: pa.Table, uri: str, table: str) -> Iterator[pa.Table]:
    store = Store.open(uri, writable=False)
    for shard in batch.column("shard").to_pylist():
        for rows in shard_batches(store, table, json.loads(shard)):
            # As Ray's Parquet reader types the partition column of a stored table.
            where = rows.schema.get_field_index("n_joints")
            yield rows.set_column(where, "n_joints", rows.column(where).cast(pa.int64()))


def _read_files(files: list[str], fs: object, base_dir: str) -> ray.data.Dataset:
    """The Parquet files `files` (already listed, by the commit markers) as a Dataset.

    Read through Ray Data's first Parquet reader (`use_datasource_v2` off for this call only),
    which takes the list as it is. Ray 2.60's default reader lists the files again in a task,
    in threads whose completion signaller can raise InterruptedError when the task finishes
    first (ray.data._internal.dynamic_work_queue: `_signal_completion` puts its sentinels after
    the consumer has set the pool's interrupt), and that thread's traceback reaches the
    driver's output. tests/cluster/test_ray_dataset.py holds the race and this way round it.
    """
    context = ray.data.DataContext.get_current()
    before = context.use_datasource_v2
    context.use_datasource_v2 = False
    try:
        return ray.data.read_parquet(
            files,
            filesystem=fs,
            partitioning=Partitioning("hive", base_dir=base_dir, field_types={"n_joints": int}),
        )
    finally:
        context.use_datasource_v2 = before


def _keep(
    block: pa.Table,
    where: pads.Expression | None,
    split: str | None,
    fractions: Sequence[float] | None,
    drop: list[str],
) -> pa.Table:
    if where is not None:
        block = block.filter(where)
    if split is not None:
        block = block.filter(pa.array(split_mask(block, split, fractions)))
    return block.drop_columns(drop) if drop else block
