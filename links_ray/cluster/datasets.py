"""`ray_dataset`: one table's committed rows as a Ray Dataset, to stream into training.

The files are those commit markers name (`links_ray.data.commit`), as for `links_ray.load`, so
an interrupted shard shows no row; Ray Data reads them block by block, so a table far larger
than memory streams through `iter_batches` or `iter_torch_batches` without pandas in between.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np
import pyarrow as pa
import pyarrow.dataset as pads
import ray
from ray.data.datasource import Partitioning

from links_ray.cluster.connect import connect
from links_ray.data.dataset import check_columns, joint_count_filter, open_table
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
    """
    store = root if isinstance(root, Store) else Store.open(root, writable=False)
    dataset = open_table(store, table)
    if n_joints is not None:
        sizes = [n_joints] if isinstance(n_joints, int | np.integer) else list(n_joints)
        if not all(isinstance(n, int | np.integer) and not isinstance(n, bool) for n in sizes):
            raise ValueError(f"n_joints must be an integer or integers, got {n_joints!r}")
    # Only the files of the joint counts asked for, chosen by the table's own partitioning.
    files = [f.path for f in dataset.get_fragments(filter=joint_count_filter(n_joints))]
    if n_joints is not None and not files:
        wanted = sorted({int(n) for n in sizes})
        raise ValueError(f"{store.uri} has no {table} rows of {wanted} joints")
    check_columns(dataset, table, columns)
    if filter is not None and not isinstance(filter, pads.Expression):
        raise ValueError(f"filter must be a pyarrow.dataset expression, got {filter!r}")
    read = columns
    if split is not None:
        check_split(split)
        check_fractions(split_fractions)
        read = with_split_key(columns, dataset.schema.names)
    connect()
    rows = _read_files(files, store.fs, store.path(table))
    if read is not None:
        # Ray 2.60 deprecates read_parquet's `columns=`; the selection is pushed into the scan.
        rows = rows.select_columns(read)
    if filter is None and split is None:
        return rows
    # Ray's read_parquet takes no pyarrow filter: each block is filtered as it is read.
    added = [] if read == columns else [read[-1]]  # the split's key, read for the split only
    keep = {"where": filter, "split": split, "fractions": split_fractions, "drop": added}
    return rows.map_batches(_keep, fn_kwargs=keep, batch_format="pyarrow")


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
