"""The mechanisms behind an index's paths, packed so that any path can be traced again.

Retrieval keeps no path's points in memory: the finalists of a query are re-simulated from
their mechanisms (`MechanismBank.paths`), which gives exactly the curated points, bit for bit,
in microseconds a path. A mechanism is packed as its initial positions and its solution path
(joint, parent_a, parent_b rows): with one degree of freedom its links are exactly the crank
and the two of each solved joint, so the adjacency and the joint types follow from the
solution path and are not stored.

Pure numpy/numba: no Ray, no files.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, fields

import numpy as np
import pyarrow as pa

from links_ray.engine.kinematics.mechanism import ACTUATED, FIXED, SIMPLE, analyze_topology
from links_ray.engine.kinematics.paths import normalize_paths
from links_ray.engine.kinematics.solver import crank_table, trace_joints


@dataclass
class MechanismBank:
    """Mechanisms, sorted by id, packed (see the module's docstring)."""

    ids: np.ndarray  # (M,) int64, ascending
    joint_start: np.ndarray  # (M + 1,) int64: offsets of each mechanism in `positions`
    positions: np.ndarray  # (J, 2) float64, initial positions
    order_start: np.ndarray  # (M + 1,) int64: offsets of each solution path in `orders`
    orders: np.ndarray  # (R, 3) uint8, rows (joint, parent_a, parent_b)

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def nbytes(self) -> int:
        """Bytes the bank's arrays hold."""
        return sum(getattr(self, f.name).nbytes for f in fields(self))

    def arrays(self) -> dict[str, np.ndarray]:
        """The arrays to save; `MechanismBank(**arrays)` restores the bank."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @classmethod
    def from_table(cls, table: pa.Table) -> MechanismBank:
        """Pack mechanisms given as the `mechanisms` table's columns `mechanism_id`,
        `adjacency`, `node_types` and `positions`, in any row order (`from_tables` of one)."""
        return cls.from_tables([table])

    @classmethod
    def from_tables(cls, tables: Iterable[pa.Table]) -> MechanismBank:
        """Pack mechanisms given as tables like `from_table`'s, one table at a time: each is
        packed into NumPy arrays before the next is read, so the Arrow rows of only one table
        are held at once. Raises ValueError if a mechanism_id comes twice."""
        parts = [_pack(table) for table in tables]
        ids = np.concatenate([part.ids for part in parts] or [np.empty(0, np.int64)])
        joints = np.concatenate([part.joints for part in parts] or [np.empty(0, np.int64)])
        steps = np.concatenate([part.steps for part in parts] or [np.empty(0, np.int64)])
        positions = np.concatenate([part.positions for part in parts] or [np.empty((0, 2))])
        orders = np.concatenate([part.orders for part in parts] or [np.empty((0, 3), np.uint8)])
        del parts
        order = np.argsort(ids, kind="stable")
        if np.any(order[1:] < order[:-1]):  # tables given out of id order: reorder the rows
            positions = _take_runs(positions, joints, order)
            orders = _take_runs(orders, steps, order)
            ids, joints, steps = ids[order], joints[order], steps[order]
        if len(ids) and np.any(ids[1:] == ids[:-1]):
            raise ValueError("the mechanisms table holds a mechanism_id twice")
        return cls(
            ids=ids,
            joint_start=_offsets(joints),
            positions=positions,
            order_start=_offsets(steps),
            orders=orders,
        )

    def rows_of(self, mechanism_ids: np.ndarray) -> np.ndarray:
        """The bank's rows (int32) of these mechanism ids; ValueError if one is missing."""
        rows = np.searchsorted(self.ids, mechanism_ids)
        found = rows < len(self.ids)
        found[found] = self.ids[rows[found]] == np.asarray(mechanism_ids)[found]
        if not found.all():
            missing = np.asarray(mechanism_ids)[~found][0]
            raise ValueError(f"mechanism {int(missing)} is not in the mechanisms table")
        return rows.astype(np.int32)

    def trajectories(self, rows: np.ndarray, joints: np.ndarray, steps: int) -> np.ndarray:
        """(F, steps, 2) float64: joint joints[i] of mechanism row rows[i] over a crank turn."""
        out = np.empty((len(rows), steps, 2))
        trace_joints(
            self.orders,
            self.order_start,
            self.positions,
            self.joint_start,
            np.asarray(rows, dtype=np.int64),
            np.asarray(joints, dtype=np.int64),
            crank_table(steps),
            out,
        )
        return out

    def paths(self, rows: np.ndarray, joints: np.ndarray, steps: int) -> np.ndarray:
        """(F, steps, 2) float32: the curated points of these paths, made as curation makes
        them (float32 trajectories, normalized, stored as float32)."""
        if not len(rows):
            return np.empty((0, steps, 2), dtype=np.float32)
        traced = self.trajectories(rows, joints, steps).astype(np.float32)
        return normalize_paths(traced).astype(np.float32)

    def mechanism(self, row: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(adjacency (n, n) uint8, node_types (n,) int8, positions (n, 2)) of mechanism row
        `row`, as the `mechanisms` table holds it."""
        positions = self.positions[self.joint_start[row] : self.joint_start[row + 1]].copy()
        order = self.orders[self.order_start[row] : self.order_start[row + 1]].astype(np.int64)
        n = len(positions)
        adjacency = np.zeros((n, n), dtype=np.uint8)
        adjacency[0, 1] = adjacency[1, 0] = 1
        node_types = np.full(n, FIXED, dtype=np.int8)
        node_types[1] = ACTUATED
        for joint, a, b in order:
            adjacency[joint, a] = adjacency[a, joint] = 1
            adjacency[joint, b] = adjacency[b, joint] = 1
            node_types[joint] = SIMPLE
        return adjacency, node_types, positions


@dataclass
class _Packed:
    """One table's mechanisms, packed in its row order."""

    ids: np.ndarray  # (M,) int64
    joints: np.ndarray  # (M,) int64: joints of each mechanism
    steps: np.ndarray  # (M,) int64: rows of each solution path
    positions: np.ndarray  # (J, 2) float64
    orders: np.ndarray  # (R, 3) uint8


def _pack(table: pa.Table) -> _Packed:
    """Pack one table's mechanisms. A topology is analyzed once per table: the five position
    variants of a topology are rows of one generation shard."""
    ids = table.column("mechanism_id").to_numpy().astype(np.int64)
    node_types = table.column("node_types").combine_chunks()
    joint_start = node_types.offsets.to_numpy().astype(np.int64)
    types_flat = node_types.flatten().to_numpy()
    adjacency = table.column("adjacency").combine_chunks()
    adjacency_start = adjacency.offsets.to_numpy()
    adjacency_flat = adjacency.flatten().to_numpy()
    positions = table.column("positions").combine_chunks().flatten().to_numpy()
    orders: list[np.ndarray] = []
    known: dict[bytes, np.ndarray] = {}
    for m in range(len(ids)):
        types = types_flat[joint_start[m] : joint_start[m + 1]]
        graph = adjacency_flat[adjacency_start[m] : adjacency_start[m + 1]]
        key = types.tobytes() + graph.tobytes()
        order = known.get(key)
        if order is None:
            n = len(types)
            order = analyze_topology(graph.reshape(n, n), types).order.astype(np.uint8)
            known[key] = order
        orders.append(order)
    return _Packed(
        ids=ids,
        joints=np.diff(joint_start),
        steps=np.array([len(order) for order in orders], dtype=np.int64),
        positions=np.ascontiguousarray(positions, dtype=np.float64).reshape(-1, 2),
        orders=np.concatenate(orders) if orders else np.empty((0, 3), np.uint8),
    )


def _offsets(counts: np.ndarray) -> np.ndarray:
    """(M + 1,) int64 offsets of runs of these lengths."""
    out = np.zeros(len(counts) + 1, dtype=np.int64)
    np.cumsum(counts, out=out[1:])
    return out


def _take_runs(values: np.ndarray, counts: np.ndarray, order: np.ndarray) -> np.ndarray:
    """The runs of `values` (consecutive, of lengths `counts`) in the order `order`."""
    starts = _offsets(counts)[:-1]
    taken = counts[order]
    gather = np.repeat(starts[order] - _offsets(taken)[:-1], taken)
    gather += np.arange(len(gather), dtype=np.int64)
    return values[gather]
