"""Train, validation and test splits by topology (docs/guides/training.md, Splits).

A topology's split is a pure function of its id: a splitmix64 draw of ``(SPLIT_SALT,
topology_id)`` (`pathset.keep_draw`) against the cumulative fractions. It depends on nothing
else, so a dataset grown with the same seed keeps every row where it was, and the five variants
of a topology, their simulations and their paths always share one split. Tables without a
`topology_id` column get it from `mechanism_id` (`shards.mechanism_topology`).

Pure numpy/pyarrow: no Ray.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import pyarrow as pa
from numpy.typing import ArrayLike

from links_ray.data.curation import keep_draw
from links_ray.data.generation import mechanism_topology

SPLITS = ("train", "validation", "test")
DEFAULT_FRACTIONS = (0.8, 0.1, 0.1)
#: The draw's seed: fixed, so a split never changes, and apart from curation's seeds.
SPLIT_SALT = 0x4C494E4B53  # "LINKS"


def check_fractions(fractions: Sequence[float] | None) -> tuple[float, float, float]:
    """The (train, validation, test) fractions: three non-negative numbers summing to 1
    (None: `DEFAULT_FRACTIONS`); ValueError otherwise."""
    if fractions is None:
        return DEFAULT_FRACTIONS
    try:
        values = tuple(float(f) for f in fractions)
    except (TypeError, ValueError):
        raise ValueError(f"split fractions must be three numbers, got {fractions!r}") from None
    if len(values) != 3 or not all(math.isfinite(f) and f >= 0 for f in values):
        raise ValueError(
            f"split fractions must be three non-negative numbers (train, validation, test), "
            f"got {fractions!r}"
        )
    if abs(sum(values) - 1.0) > 1e-9:
        raise ValueError(f"split fractions must sum to 1, got {fractions!r} (sum {sum(values)})")
    return values  # type: ignore[return-value]


def check_split(split: str) -> int:
    """The index of `split` in SPLITS; ValueError naming the choices otherwise."""
    if split not in SPLITS:
        raise ValueError(f"split must be one of {', '.join(SPLITS)}, got {split!r}")
    return SPLITS.index(split)


def split_codes(topology_ids: ArrayLike, fractions: Sequence[float] | None = None) -> np.ndarray:
    """The split of each topology id as an index into SPLITS (int8)."""
    train, validation, _ = check_fractions(fractions)
    ids = np.asarray(topology_ids)
    if ids.size and not np.issubdtype(ids.dtype, np.integer):
        raise ValueError(f"topology ids must be integers, got {ids.dtype}")
    if ids.size and ids.min() < 0:
        raise ValueError("topology ids must be non-negative")
    draw = keep_draw(ids.astype(np.int64), SPLIT_SALT)
    # Cumulative bounds: raising one fraction moves ids only across its own boundaries.
    codes = (draw >= train).astype(np.int8) + (draw >= train + validation).astype(np.int8)
    return codes


def split_of(topology_ids: ArrayLike, fractions: Sequence[float] | None = None) -> np.ndarray:
    """The split ("train", "validation" or "test") of each topology id, default 80/10/10.

    A pure function of the id: the same on any dataset, however large it has grown.
    """
    return np.asarray(SPLITS)[split_codes(topology_ids, fractions)]


def split_key(columns: Sequence[str]) -> str:
    """The column a table's split is read from: `topology_id`, else `mechanism_id`."""
    for key in ("topology_id", "mechanism_id"):
        if key in columns:
            return key
    raise ValueError("a split needs the topology_id or mechanism_id column")


def split_mask(
    rows: pa.Table | pa.RecordBatch, split: str, fractions: Sequence[float] | None = None
) -> np.ndarray:
    """Which `rows` (of any table) belong to `split`: by `topology_id`, or by the topology of
    `mechanism_id` where the table has no `topology_id`."""
    wanted = check_split(split)
    key = split_key(rows.schema.names)
    ids = rows.column(key).to_numpy()
    topologies = ids if key == "topology_id" else mechanism_topology(ids)
    return split_codes(topologies, fractions) == wanted


def with_split_key(columns: list[str] | None, available: Sequence[str]) -> list[str] | None:
    """`columns` plus the split's key column where it lacks it (None: every column)."""
    if columns is None:
        return None
    key = split_key(available)
    return columns if key in columns else [*columns, key]
