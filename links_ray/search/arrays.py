"""The arrays a query reads: `IndexArrays`, the record `RetrievalIndex` passes into the query
pipeline (`search.query`) and brute force (`search.brute_force`), which never see the index.

Pure numpy: no Ray, no files.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from links_ray.search.build import Basis
from links_ray.search.mechanisms import MechanismBank
from links_ray.search.reduced import reduced_joints


@dataclass(frozen=True)
class IndexArrays:
    """An index's paths as arrays, one row a path (row order: grouped by coarse list).

    Frozen so that no query function can swap an array of the index for another; the arrays
    themselves are the index's own (not copies).
    """

    steps: int  # points per path
    mechanism_row: np.ndarray  # (N,) int32: each path's mechanism, a row of `bank`
    joint: np.ndarray  # (N,) int8: the path's joint in its mechanism
    sketches: np.ndarray  # (N, 2 * SKETCH_POINTS) uint8, see `search.kernels`
    transmission: np.ndarray  # (N,) float32: min_transmission_deg (NaN where not stored)
    # List l is rows list_start[l]:list_start[l + 1], its centroid centroids[l] (field codes).
    list_start: np.ndarray  # (L + 1,) int64
    centroids: np.ndarray  # (L, DIMENSIONS) float32
    file_row: np.ndarray  # (N,) int32 or int64: row r's place in the curated files
    basis: Basis  # places a query's variants among the lists
    bank: MechanismBank  # traces any path again

    def __len__(self) -> int:
        return len(self.joint)

    def path_ids(self, rows: np.ndarray) -> np.ndarray:
        """(len(rows),) int64: the path ids of these rows, 32 * mechanism_id + joint."""
        return (self.bank.ids[self.mechanism_row[rows]] << 5) | self.joint[rows].astype(np.int64)

    def paths(self, rows: np.ndarray) -> np.ndarray:
        """(len(rows), steps, 2) float32: the curated points of these rows, traced again."""
        rows = np.asarray(rows, dtype=np.int64)
        return self.bank.paths(self.mechanism_row[rows], self.joint[rows], self.steps)

    def count_joints(self) -> np.ndarray:
        """(N,) int16: the joints of each path's reduced mechanism (`reduce_mechanism`),
        counted from the packed mechanisms (a fraction of a second a million paths)."""
        counts = np.empty(len(self), dtype=np.int16)
        bank = self.bank
        reduced_joints(
            bank.orders, bank.order_start, bank.joint_start, self.mechanism_row, self.joint, counts
        )
        return counts
