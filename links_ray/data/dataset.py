"""Reading the dataset: `load` a table as pandas or pyarrow, optionally one joint count.

Only committed rows are read: the files that commit markers name (`links_ray.data.commit`), so
a shard interrupted anywhere in its commit shows no row, in no table.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Literal

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.dataset as pads
from numpy.typing import ArrayLike

from links_ray.data.commit import committed_files
from links_ray.data.derived import derived_batches, derived_schema, derives
from links_ray.data.schemas import TABLE_NAMES
from links_ray.data.splits import check_fractions, check_split, split_mask, with_split_key
from links_ray.data.store import Store

#: The partition column, typed (Hive folders carry no types).
PARTITIONING = pads.partitioning(pa.schema([("n_joints", pa.int16())]), flavor="hive")


def open_table(
    root: str | Store, table: str, markers: dict[int, dict] | None = None
) -> pads.Dataset:
    """The pyarrow dataset of one table's committed files at `root` (a folder,
    s3://bucket/prefix or a Store); `markers` as in `committed_files`."""
    if table not in TABLE_NAMES:
        raise ValueError(f"table must be one of {', '.join(TABLE_NAMES)}, got {table!r}")
    store = root if isinstance(root, Store) else Store.open(root, writable=False)
    files = committed_files(store, table, markers)
    if not files:
        raise ValueError(f"{store.uri} has no {table} table yet")
    return pads.dataset(
        [store.path(relative) for relative in files],
        filesystem=store.fs,
        format="parquet",
        partitioning=PARTITIONING,
        partition_base_dir=store.path(table),
    )


def isin(column: str, values: ArrayLike) -> pads.Expression:
    """A scan filter: `column` is one of `values`, held as their distinct values in Arrow's own
    memory.

    Never NumPy's: `pa.array` of a NumPy array borrows its memory, and a scan may drop its
    filter on one of Arrow's threads after `to_table` has returned (its asynchronous scanner's
    last callback). Letting go of borrowed NumPy memory takes the GIL; if Python is finalizing
    by then (a command that ends right after a scan), the thread is stopped inside a C++
    destructor and the process aborts: "terminate called without an active exception", exit
    status 134. `pc.unique` allocates its result from Arrow's memory pool, and the borrowing
    `pa.array` it reads from is let go here, on the caller's thread.
    """
    return pads.field(column).isin(value_set(values))


def value_set(values: ArrayLike) -> pa.Array:
    """The distinct `values`, in Arrow's own memory (see `isin`)."""
    return pc.unique(pa.array(values))


def joint_count_filter(n_joints: int | Iterable[int] | None) -> pads.Expression | None:
    """A scan filter keeping one joint count or several (None: every row)."""
    if n_joints is None:
        return None
    sizes = [n_joints] if isinstance(n_joints, int | np.integer) else list(n_joints)
    return pads.field("n_joints").isin([int(n) for n in sizes])


def check_columns(
    dataset: pads.Dataset | pa.Table | list[str], table: str, columns: list[str] | None
) -> None:
    """ValueError naming the `columns` that `table` (its rows, or its column names) lacks."""
    names = dataset if isinstance(dataset, list) else dataset.schema.names
    unknown = sorted(set(columns or ()) - set(names))
    if unknown:
        raise ValueError(f"{table} has no column {', '.join(unknown)}")


def load(
    root: str | Store,
    table: str,
    n_joints: int | Iterable[int] | None = None,
    columns: list[str] | None = None,
    format: Literal["pandas", "arrow"] = "pandas",
    reshape: bool = False,
    split: str | None = None,
    split_fractions: Sequence[float] | None = None,
) -> pd.DataFrame | pa.Table:
    """Rows of `table`, filtered by `n_joints`, as a pandas DataFrame or a pyarrow Table.

    With `reshape` (pandas only) the flattened lists become arrays: `adjacency` (n, n),
    `positions` (n, 2), `trajectories` (n, steps, 2), `points` (steps, 2). With `split`
    ("train", "validation" or "test") only the rows of that split's topologies
    (`links_ray.split_of`, `split_fractions` as there).
    """
    if format not in ("pandas", "arrow"):
        raise ValueError(f"format must be 'pandas' or 'arrow', got {format!r}")
    if reshape and format != "pandas":
        raise ValueError("reshape applies to format='pandas'")
    if split is not None:
        check_split(split)
        check_fractions(split_fractions)
    store = root if isinstance(root, Store) else Store.open(root, writable=False)
    if derives_rows(store, table, columns):
        check_columns(derived_schema(table).names, table, columns)  # before the work
        rows = _derived_table(store, table, n_joints)
        read = columns if split is None else with_split_key(columns, rows.schema.names)
        rows = rows if read is None else rows.select(read)
    else:
        dataset = open_table(store, table)
        check_columns(dataset, table, columns)
        read = columns if split is None else with_split_key(columns, dataset.schema.names)
        rows = dataset.to_table(columns=read, filter=joint_count_filter(n_joints))
    if split is not None:
        rows = rows.filter(pa.array(split_mask(rows, split, split_fractions)))
        if columns is not None:
            rows = rows.select(columns)
    if format == "arrow":
        return rows
    frame = rows.to_pandas()
    if reshape:
        _reshape(frame)
    return frame


def derives_rows(store: Store, table: str, columns: list[str] | None) -> bool:
    """Whether a read of `columns` of `table` derives rows: the root stores no such rows, or
    stores them as ids and the read wants their points (`data.derived`)."""
    if not derives(store, table):
        return False
    if columns is None or "points" in columns:
        return True
    # Columns without points: a table stored as ids reads them as stored.
    return table == "simulations" or not committed_files(store, table)


def _derived_table(store: Store, table: str, n_joints: int | Iterable[int] | None) -> pa.Table:
    """Every derived row of `table` (of `n_joints` joints, when given), as one table."""
    sizes = None
    if n_joints is not None:
        sizes = [n_joints] if isinstance(n_joints, int | np.integer) else list(n_joints)
    parts = list(derived_batches(store, table, sizes))
    if not parts:
        raise ValueError(f"{store.uri} has no {table} rows to derive")
    return pa.concat_tables(parts)


def _reshape(frame: pd.DataFrame) -> None:
    n = frame["n_joints"].to_numpy() if "n_joints" in frame else None
    shapes = {
        "adjacency": lambda k: (n[k], n[k]),
        "positions": lambda k: (n[k], 2),
        "trajectories": lambda k: (n[k], -1, 2),
        "points": lambda k: (-1, 2),
    }
    for column, shape in shapes.items():
        if column in frame and (n is not None or column == "points"):
            frame[column] = [np.asarray(v).reshape(shape(k)) for k, v in enumerate(frame[column])]
