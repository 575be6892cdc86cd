"""The dataset's tables: their names, their columns as written, and how they are written.

Each table is Hive-partitioned Parquet under the root (docs/reference/contract.md, Dataset layout)::

    ROOT/<table>/n_joints=12/shard-000042-<attempt>.parquet
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import pyarrow as pa

GENERATION_TABLES = ("mechanisms", "simulations", "negatives")
CURATION_TABLES = ("paths", "curated")
#: Trajectories are simulated in float64 and stored in this type. Curation casts the
#: trajectories it simulates itself the same way, so its paths are those of stored ones.
TRAJECTORY_DTYPE = np.float32
#: Values one list array may hold: its offsets are 32-bit.
MAX_LIST_VALUES = 2**31 - 1

_MECHANISM_FIELDS = [
    pa.field("mechanism_id", pa.int64(), nullable=False),
    pa.field("topology_id", pa.int64(), nullable=False),
    pa.field("variant", pa.int8(), nullable=False),
    pa.field("adjacency", pa.list_(pa.uint8()), nullable=False),
    pa.field("node_types", pa.list_(pa.int8()), nullable=False),
    pa.field("positions", pa.list_(pa.float64()), nullable=False),
]
_PATH_SCHEMA = pa.schema(
    [
        pa.field("path_id", pa.int64(), nullable=False),
        pa.field("mechanism_id", pa.int64(), nullable=False),
        pa.field("joint", pa.int8(), nullable=False),
        pa.field("points", pa.list_(pa.float32()), nullable=False),
        pa.field("is_arc", pa.bool_(), nullable=False),
        pa.field("is_circle", pa.bool_(), nullable=False),
        pa.field("circle_variance", pa.float32(), nullable=False),
        # The path's joint's least transmission angle: over the dyads its motion needs.
        pa.field("min_transmission_deg", pa.float32(), nullable=False),
    ]
)
#: Columns of each table as written; `n_joints` is the Hive partition (the folder name).
SCHEMAS: dict[str, pa.Schema] = {
    "mechanisms": pa.schema(
        [
            *_MECHANISM_FIELDS,
            # The least transmission angle over the turn, in degrees
            # (engine.kinematics.transmission).
            pa.field("min_transmission_deg", pa.float32(), nullable=False),
        ]
    ),
    "simulations": pa.schema(
        [
            pa.field("mechanism_id", pa.int64(), nullable=False),
            pa.field("steps", pa.int16(), nullable=False),
            pa.field(
                "trajectories", pa.list_(pa.from_numpy_dtype(TRAJECTORY_DTYPE)), nullable=False
            ),
        ]
    ),
    "negatives": pa.schema(
        [
            *_MECHANISM_FIELDS,
            pa.field("locked_step", pa.int16(), nullable=False),
            pa.field("locked_node", pa.int16(), nullable=False),
        ]
    ),
    "paths": _PATH_SCHEMA,
    "curated": _PATH_SCHEMA,
}
#: How curation stores a path table: with its points, or as ids and flags only (a lean root:
#: readers derive the points from the mechanisms, `links_ray.data.derived`).
PATH_STORES = ("points", "ids")
#: The path tables' columns when stored as ids: all but `points`.
ID_SCHEMAS: dict[str, pa.Schema] = {
    table: SCHEMAS[table].remove(SCHEMAS[table].get_field_index("points"))
    for table in ("paths", "curated")
}
#: zstd, and a dictionary only for the 0/1 and joint-kind values of the graph columns: there
#: it turns each (n, n) adjacency into a run-length bit stream that zstd folds over a topology's
#: five variants (docs/benchmarks.md, Sizes on disk); floats do not repeat, and a dictionary
#: page only costs them time and space.
PARQUET_OPTIONS = {
    "compression": "zstd",
    "use_dictionary": ["adjacency.list.element", "node_types.list.element"],
    "write_statistics": True,
}
TABLE_NAMES = GENERATION_TABLES + CURATION_TABLES


def check_path_store(path_store: str) -> str:
    """`path_store` if it is one of PATH_STORES; ValueError naming them otherwise."""
    if path_store not in PATH_STORES:
        raise ValueError(f"store must be one of {', '.join(PATH_STORES)}, got {path_store!r}")
    return path_store


def choose_tables(
    tables: str | Iterable[str], stage_tables: tuple[str, ...], required: str | None = None
) -> tuple[str, ...]:
    """The tables a run writes, in `stage_tables` order, from names or a comma-separated string.

    Raises ValueError for an unknown name, for none at all, or without `required`.
    """
    names = tables.split(",") if isinstance(tables, str) else list(tables)
    names = [name.strip() if isinstance(name, str) else name for name in names]
    unknown = [name for name in names if name not in stage_tables]
    if unknown:
        raise ValueError(
            f"tables must be among {', '.join(stage_tables)}, got {', '.join(map(repr, unknown))}"
        )
    if not names:
        raise ValueError(f"tables must name at least one of {', '.join(stage_tables)}")
    if required is not None and required not in names:
        raise ValueError(f"tables must include {required}, got {', '.join(names)}")
    return tuple(table for table in stage_tables if table in names)


def list_array(rows: np.ndarray, value_type: pa.DataType) -> pa.ListArray:
    """A list array of the rows of a (rows, width) array, every row of `width` values.

    Its offsets are 32-bit: more than MAX_LIST_VALUES values in all is refused, never wrapped.
    """
    count, width = rows.shape
    if count * width > MAX_LIST_VALUES:
        raise ValueError(
            f"{count} lists of {width} values exceed the {MAX_LIST_VALUES} values a list array "
            "can hold: split the rows"
        )
    offsets = (np.arange(count + 1, dtype=np.int64) * width).astype(np.int32)
    return pa.ListArray.from_arrays(pa.array(offsets), pa.array(rows.ravel(), type=value_type))
