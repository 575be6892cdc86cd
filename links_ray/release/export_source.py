"""What an export of a root to the LINKS release layout reads, checked before anything is
written: the root's committed generation and curation markers, the chunk size, the split, and
the folder written into. Shared by both formats (`release.exporter`, `release.pickled_export`).

Pure pyarrow: no Ray.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np

from links_ray.data.commit import committed_shards
from links_ray.data.splits import check_fractions, check_split
from links_ray.data.store import Store


def open_export(
    root: str | Store,
    out: str,
    chunk_size: int,
    split: str | None,
    split_fractions: Sequence[float] | None,
) -> tuple[Store, dict[int, dict], dict[int, dict], Sequence[float]]:
    """(store, generation markers, curation markers, split fractions) of the root an export
    reads, its arguments checked first; ValueError in one line for a bad one."""
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, int | np.integer):
        raise ValueError(f"chunk_size must be an integer, got {chunk_size!r}")
    if chunk_size < 1:
        raise ValueError(f"chunk_size must be at least 1, got {chunk_size}")
    if split is not None:
        check_split(split)
    fractions = check_fractions(split_fractions)
    check_out(out)
    store = root if isinstance(root, Store) else Store.open(root, writable=False)
    generated = committed_shards(store, "shards")
    if not generated:
        raise ValueError(f"{store.uri} holds no generated shards: run links generate first")
    return store, generated, committed_shards(store, "curation"), fractions


def check_out(out: str) -> None:
    """ValueError unless `out` names a local folder that is new or empty."""
    if not isinstance(out, str) or not out.strip():
        raise ValueError(f"out must be a local folder, got {out!r}")
    if "://" in out:
        raise ValueError(f"out must be a local folder, got {out}")
    if os.path.exists(out) and (not os.path.isdir(out) or os.listdir(out)):
        raise ValueError(f"{out} is not an empty folder: export into a new or empty one")
