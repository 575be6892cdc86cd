"""The dyadic solution path and the dataset's structure rules, compiled.

`engine.kinematics.mechanism` states both in Python with a message for every failure; these kernels
give the same answers in a few microseconds, for the generator, which grows and checks one topology
per five mechanisms, and for every reader that simulates a root's mechanisms again, which checks
each topology it meets (`passes_graph_checks` is every check of `mechanism.as_graph` and
`analyze_topology` before the solution path). A topology they reject goes back to the Python
statements, which say why.

Pure numpy/numba: no Ray.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from links_ray.engine.buffers import check_buffer
from links_ray.engine.inputs import MAX_JOINTS, MIN_JOINTS
from links_ray.engine.node_kinds import ACTUATED, FIXED, SIMPLE

#: `_solution_order`'s answers when there is no solution path.
OVER_CONSTRAINED = -1
UNSOLVED = -2


@njit(cache=True, nogil=True)
def _solution_order(adjacency: np.ndarray, node_types: np.ndarray, order: np.ndarray) -> int:
    """Fill `order` (n, 3) with the solution path, lowest-index solvable joint first, and
    return its rows; OVER_CONSTRAINED if a joint has more than two known neighbours when it is
    solved, UNSOLVED if some joint is never solved."""
    n = node_types.shape[0]
    known = np.empty(n, dtype=np.bool_)
    count = np.zeros(n, dtype=np.int64)  # known neighbours of each joint
    for j in range(n):
        known[j] = node_types[j] != SIMPLE
    for j in range(n):
        for k in range(n):
            if adjacency[j, k] != 0 and known[k]:
                count[j] += 1
    rows = 0
    while True:
        joint = -1
        for j in range(n):
            if not known[j] and count[j] >= 2:
                joint = j
                break
        if joint < 0:
            break
        if count[joint] > 2:
            return OVER_CONSTRAINED
        first = -1
        for k in range(n):
            if adjacency[joint, k] != 0 and known[k]:
                if first < 0:
                    first = k
                else:
                    order[rows, 0] = joint
                    order[rows, 1] = first
                    order[rows, 2] = k
        rows += 1
        known[joint] = True
        for k in range(n):
            if adjacency[joint, k] != 0:
                count[k] += 1
    for j in range(n):
        if not known[j]:
            return UNSOLVED
    return rows


@njit(cache=True, nogil=True)
def _obeys_structure(adjacency: np.ndarray, node_types: np.ndarray, order: np.ndarray) -> bool:
    """Whether the last joint of the path depends on every joint and is linked to no fixed
    joint (`mechanism.structure_violations` is empty)."""
    n = node_types.shape[0]
    last = order[order.shape[0] - 1, 0] if order.shape[0] else 1
    for k in range(n):
        if adjacency[last, k] != 0 and node_types[k] == FIXED:
            return False
    needed = np.zeros(n, dtype=np.bool_)
    needed[last] = True
    for row in range(order.shape[0] - 1, -1, -1):  # parents are solved before their children
        if needed[order[row, 0]]:
            needed[order[row, 1]] = True
            needed[order[row, 2]] = True
    if needed[1]:
        needed[0] = True  # the crank tip turns about joint 0
    for j in range(n):
        if not needed[j]:
            return False
    return True


@njit(cache=True, nogil=True)
def _passes_graph_checks(adjacency: np.ndarray, node_types: np.ndarray) -> bool:
    """Whether an integer (n, n) adjacency and (n,) node types pass every check that
    `mechanism.analyze_topology` makes before its solution path: the form of the graph, the
    crank and the ground."""
    n = node_types.shape[0]
    if adjacency.shape[0] != n or adjacency.shape[1] != n or n < MIN_JOINTS or n > MAX_JOINTS:
        return False
    for j in range(n):
        if node_types[j] < FIXED or node_types[j] > ACTUATED:
            return False
        if adjacency[j, j] != 0:
            return False
        for k in range(n):
            value = adjacency[j, k]
            if (value != 0 and value != 1) or value != adjacency[k, j]:
                return False
    if node_types[0] != FIXED or node_types[1] != ACTUATED or adjacency[0, 1] == 0:
        return False
    for j in range(2, n):
        if node_types[j] == ACTUATED:
            return False
    for j in range(n):
        for k in range(n):
            if adjacency[j, k] != 0 and node_types[j] == FIXED and node_types[k] == FIXED:
                return False  # a link joins two fixed joints
    for k in range(2, n):
        if adjacency[1, k] != 0 and node_types[k] == FIXED:
            return False  # the crank joint is also linked to a fixed joint
    return True


def passes_graph_checks(adjacency: np.ndarray, node_types: np.ndarray) -> bool:
    """Whether a topology given as integer arrays, adjacency (n, n) and node_types (n,),
    passes the checks of `mechanism.analyze_topology` before its solution path (False also
    for arrays of another form, which those checks refuse or convert)."""
    if (
        not isinstance(adjacency, np.ndarray)
        or not isinstance(node_types, np.ndarray)
        or adjacency.ndim != 2
        or node_types.ndim != 1
        or adjacency.dtype.kind not in "iu"
        or node_types.dtype.kind not in "iu"
    ):
        return False
    return bool(_passes_graph_checks(adjacency, node_types))


def solution_order(adjacency: np.ndarray, node_types: np.ndarray) -> np.ndarray | None:
    """(m, 3) int64: the solution path `mechanism.analyze_topology` finds for a topology whose
    form it has checked (adjacency (n, n) uint8, node_types (n,) int8), or None when there is
    none."""
    check_buffer("node_types", node_types, (None,), np.int8)
    n = node_types.shape[0]
    check_buffer("adjacency", adjacency, (n, n), np.uint8)
    order = np.empty((n, 3), dtype=np.int64)
    rows = _solution_order(adjacency, node_types, order)
    return order[:rows].copy() if rows >= 0 else None


def obeys_structure(adjacency: np.ndarray, node_types: np.ndarray, order: np.ndarray) -> bool:
    """Whether a topology with solution path `order` obeys the dataset's structure rules."""
    check_buffer("node_types", node_types, (None,), np.int8)
    n = node_types.shape[0]
    if n < MIN_JOINTS:
        raise ValueError(f"node_types must hold at least the crank's {MIN_JOINTS} joints, got {n}")
    check_buffer("adjacency", adjacency, (n, n), np.uint8)
    check_buffer("order", order, (None, 3), np.int64)
    if order.size and (order.min() < 0 or order.max() >= n):
        raise ValueError(f"order must hold joints of the {n}-joint topology")
    return bool(_obeys_structure(adjacency, node_types, order))
