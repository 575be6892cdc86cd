"""A seeded draw of a root's curated paths: exactly `paths` of them, the same ones on every
machine, for an index over part of a large curated set (the paper's case study searched a
reduced set of ten million curated paths).

Each path id gets a key, `splitmix64(path_id, DRAW_SALT + seed)`; the draw is the `paths`
paths of smallest key. Keys of distinct ids are distinct, so the draw holds exactly
`min(paths, curated)` paths with no tie to break, and which paths it holds depends on the
seed and the ids alone: not on files, shards or partitions. A draw of an extended root keeps
every earlier path whose key is still among the smallest. The salt keeps the draw's keys
apart from curation's own seeded choice (`pathset.keep_draw` with the curation seed), which
they would otherwise favour.

`DrawnPaths.of` reads only the `path_id` column of the curated files (ids, a few bytes a
path), twice: to find the largest key kept, in memory of about twice the draw's keys, then to
count each file's share. Pure numpy/pyarrow: no Ray.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from links_ray.data.curation import splitmix64
from links_ray.data.store import Store

__all__ = ["DRAW_SALT", "MAX_DRAW_PATHS", "MAX_DRAW_SEED", "DrawnPaths", "PathDraw"]

#: Added to the seed: the draw's keys are their own stream, apart from curation's.
DRAW_SALT = 0x6C696E6B7364726177  # "linksdraw"
MAX_DRAW_SEED = 2**32 - 1
#: More paths than any root holds (LINKS has about 1.1e9 paths): a draw's name stays short.
MAX_DRAW_PATHS = 2**40


@dataclass(frozen=True)
class PathDraw:
    """`paths` curated paths drawn with `seed`: those of the smallest `keys`."""

    paths: int
    seed: int = 0

    def __post_init__(self) -> None:
        for name, value in (("paths", self.paths), ("seed", self.seed)):
            if isinstance(value, bool) or not isinstance(value, int | np.integer):
                raise ValueError(f"the draw's {name} must be an integer, got {value!r}")
        if not 1 <= self.paths <= MAX_DRAW_PATHS:
            raise ValueError(f"the draw's paths must be in 1..{MAX_DRAW_PATHS}, got {self.paths}")
        if not 0 <= self.seed <= MAX_DRAW_SEED:
            raise ValueError(f"the draw's seed must be in 0..{MAX_DRAW_SEED}, got {self.seed}")

    @property
    def name(self) -> str:
        """The draw as a folder name: `draw-PATHS-seed-SEED`."""
        return f"draw-{self.paths}-seed-{self.seed}"

    def keys(self, path_ids: np.ndarray) -> np.ndarray:
        """(N,) uint64: each path id's key, distinct for distinct ids."""
        return splitmix64(np.asarray(path_ids), (DRAW_SALT + self.seed) % 2**64)


@dataclass(frozen=True)
class DrawnPaths:
    """A `PathDraw` on one root's curated files: the largest key it keeps (`last_key`) and how
    many paths each file gives it."""

    draw: PathDraw
    last_key: int
    rows_by_file: dict[str, int]

    @classmethod
    def of(cls, store: Store, files: list[str], draw: PathDraw) -> DrawnPaths:
        """The draw over the curated `files` (every file of the root: a draw is of the whole
        curated set, whatever part of it one index holds)."""
        smallest = _smallest_keys(draw, (_path_ids(store, relative) for relative in files))
        if len(smallest) == 0:
            raise ValueError(f"{store.uri}: no curated paths to draw from")
        last_key = np.uint64(smallest.max())
        del smallest
        counts = {
            relative: int(np.count_nonzero(draw.keys(_path_ids(store, relative)) <= last_key))
            for relative in files
        }
        return cls(draw, int(last_key), counts)

    @property
    def rows(self) -> int:
        """The paths drawn."""
        return sum(self.rows_by_file.values())

    def keeps(self, path_ids: np.ndarray) -> np.ndarray:
        """(N,) bool: which of these path ids the draw holds."""
        return self.draw.keys(path_ids) <= np.uint64(self.last_key)


def _smallest_keys(draw: PathDraw, path_ids: Iterable[np.ndarray]) -> np.ndarray:
    """The `draw.paths` smallest keys of these ids (all, if fewer), in no order. Memory holds
    at most about twice the draw's keys and one file's: keys gather until they outnumber it
    twice, then only the smallest are kept."""
    wanted = draw.paths
    kept: list[np.ndarray] = []
    held = 0
    for ids in path_ids:
        kept.append(draw.keys(ids))
        held += len(ids)
        if held >= 2 * wanted:
            every = np.concatenate(kept)
            kept, held = [np.partition(every, wanted - 1)[:wanted]], wanted
    every = np.concatenate(kept) if kept else np.empty(0, dtype=np.uint64)
    return np.partition(every, wanted - 1)[:wanted] if len(every) > wanted else every


def _path_ids(store: Store, relative: str) -> np.ndarray:
    return store.read_parquet(relative, columns=["path_id"]).column("path_id").to_numpy()
