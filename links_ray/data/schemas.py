"""The dataset's tables: their names, their columns as written, and how they are written.

Each table is Hive-partitioned Parquet under the root (docs/CONTRACT.md, Dataset layout)::

    ROOT/<table>/n_joints=12/shard-000042.parquet
"""

from __future__ import annotations

import pyarrow as pa

GENERATION_TABLES = ("mechanisms", "simulations", "negatives")
CURATION_TABLES = ("paths", "curated")

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
    ]
)
#: Columns of each table as written; `n_joints` is the Hive partition (the folder name).
SCHEMAS: dict[str, pa.Schema] = {
    "mechanisms": pa.schema(_MECHANISM_FIELDS),
    "simulations": pa.schema(
        [
            pa.field("mechanism_id", pa.int64(), nullable=False),
            pa.field("steps", pa.int16(), nullable=False),
            pa.field("trajectories", pa.list_(pa.float32()), nullable=False),
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
#: zstd, no dictionary: floats do not repeat, and dictionary pages only cost time and space.
PARQUET_OPTIONS = {"compression": "zstd", "use_dictionary": False, "write_statistics": True}
TABLE_NAMES = GENERATION_TABLES + CURATION_TABLES
