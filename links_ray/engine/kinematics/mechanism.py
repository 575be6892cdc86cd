"""Mechanism model: the crank and ground rules, the dyadic solution path, the dataset rules.

A mechanism is a graph (docs/reference/contract.md, Mechanisms): joints are nodes, links are edges.
Joint 0 is fixed, joint 1 is the only actuated joint, and link (0, 1) is the crank. A simple
joint is solved once exactly two of its neighbours are known; the order in which joints get
solved is the solution path, found once per topology and reused for every position set. The
checks of the input's form (shapes, types, limits) are in `links_ray.engine.inputs`.

Numpy, and the compiled path of `engine.kinematics.solution_path`: no Ray.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike

from links_ray.engine.inputs import (
    MAX_DATASET_JOINTS,
    MIN_DATASET_JOINTS,
    InvalidMechanismError,
    as_graph,
    as_positions,
    link_pairs,
)
from links_ray.engine.kinematics.solution_path import passes_graph_checks, solution_order
from links_ray.engine.node_kinds import ACTUATED, FIXED, SIMPLE

CRANK_CENTER = (0.5, 0.5)
CRANK_TIP = (0.55, 0.5)


class LockingError(ValueError):
    """The mechanism cannot be assembled at crank step `step`: joint `node` has no position."""

    def __init__(self, step: int, node: int) -> None:
        super().__init__(f"mechanism locks at step {step}: joint {node} cannot be assembled")
        self.step = int(step)
        self.node = int(node)


@dataclass(frozen=True, eq=False)
class Topology:
    """A validated topology and its solution path.

    `order[k] = (joint, parent_a, parent_b)` solves `joint` from its two known neighbours, with
    `parent_a < parent_b`; rows are in solving order. Fixed joints and the crank joint 1 are known
    from the start and do not appear in `order`.
    """

    adjacency: np.ndarray  # (n, n) uint8
    node_types: np.ndarray  # (n,) int8
    order: np.ndarray  # (m, 3) int64

    @property
    def n_joints(self) -> int:
        """The number of joints."""
        return int(self.node_types.shape[0])

    @cached_property
    def fixed_joints(self) -> np.ndarray:
        """(f,) int64: the fixed joints' indices, ascending."""
        return np.flatnonzero(self.node_types == FIXED).astype(np.int64)

    @cached_property
    def links(self) -> tuple[np.ndarray, np.ndarray]:
        """(i, j) of every link, i < j, in row order (`inputs.link_pairs`)."""
        return link_pairs(self.adjacency)

    @property
    def last_joint(self) -> int:
        """The last joint of the solution path (joint 1 when only the crank moves)."""
        return int(self.order[-1, 0]) if len(self.order) else 1

    def ancestors(self, joint: int) -> np.ndarray:
        """Sorted indices of the joints `joint`'s motion depends on, `joint` included."""
        parents = {int(j): (int(a), int(b)) for j, a, b in self.order}
        parents[1] = (0, 0)
        needed, stack = {joint}, [joint]
        while stack:
            for parent in parents.get(stack.pop(), ()):
                if parent not in needed:
                    needed.add(parent)
                    stack.append(parent)
        return np.array(sorted(needed), dtype=np.int64)


def mobility(adjacency: ArrayLike, node_types: ArrayLike) -> tuple[int, int, int]:
    """(moving joints, links, degrees of freedom = 2 x moving - links) of a mechanism graph."""
    moving = int(np.count_nonzero(np.asarray(node_types) != FIXED))
    links = int(np.count_nonzero(np.triu(np.asarray(adjacency), 1)))
    return moving, links, 2 * moving - links


def analyze_topology(adjacency: ArrayLike, node_types: ArrayLike) -> Topology:
    """Validate a topology and find its solution path.

    Raises `InvalidMechanismError` naming the first problem found.
    """
    if passes_graph_checks(adjacency, node_types):  # compiled: what readers of a root meet
        checked = adjacency.astype(np.uint8), node_types.astype(np.int8)
        order = solution_order(*checked)
        if order is not None:
            return Topology(adjacency=checked[0], node_types=checked[1], order=order)
    return checked_topology(adjacency, node_types)


def checked_topology(adjacency: ArrayLike, node_types: ArrayLike) -> Topology:
    """`analyze_topology` by Python statements alone, each failure named."""
    adj, types = as_graph(adjacency, node_types)
    if types[0] != FIXED:
        raise InvalidMechanismError(
            f"wrong crank joints: joint 0 must be fixed (0), got {types[0]}"
        )
    if types[1] != ACTUATED:
        raise InvalidMechanismError(
            f"wrong crank joints: joint 1 must be the actuated joint (2), got {types[1]}"
        )
    actuated = np.flatnonzero(types == ACTUATED)
    if len(actuated) > 1:
        raise InvalidMechanismError(
            f"wrong crank joints: only joint 1 may be actuated, also {actuated[1:].tolist()}"
        )
    if not adj[0, 1]:
        raise InvalidMechanismError("no crank: joints 0 and 1 are not linked")

    fixed = types == FIXED
    ground = np.flatnonzero(fixed)
    ground_links = np.argwhere(adj[np.ix_(ground, ground)])
    if len(ground_links):
        i, j = ground[ground_links[0]]
        raise InvalidMechanismError(f"link ({i}, {j}) joins two fixed joints")
    extra = [int(j) for j in np.flatnonzero(adj[1] & fixed) if j != 0]
    if extra:
        raise InvalidMechanismError(
            f"over-constrained: crank joint 1 is also linked to fixed joint {extra[0]}"
        )

    adjacency, node_types = adj.astype(np.uint8), types.astype(np.int8)
    order = solution_order(adjacency, node_types)
    if order is None:
        order = _solution_path(adj, types)  # raises, saying why there is no path
    return Topology(adjacency=adjacency, node_types=node_types, order=order)


def _solution_path(adj: np.ndarray, types: np.ndarray) -> np.ndarray:
    """Solve the lowest-index solvable joint first, each from exactly two known neighbours."""
    n = len(types)
    rows, cols = np.nonzero(adj)
    ends = np.cumsum(np.bincount(rows, minlength=n)).tolist()
    cols = cols.tolist()
    neighbours = [cols[start:end] for start, end in zip([0, *ends[:-1]], ends, strict=True)]
    known = (types != SIMPLE).tolist()
    known_count = [sum(known[k] for k in neighbours[j]) for j in range(n)]
    solvable = [j for j in range(n) if not known[j] and known_count[j] >= 2]
    heapq.heapify(solvable)
    order: list[tuple[int, int, int]] = []
    while solvable:
        j = heapq.heappop(solvable)
        parents = [k for k in neighbours[j] if known[k]]
        if len(parents) > 2:
            raise InvalidMechanismError(
                f"over-constrained: joint {j} is linked to {len(parents)} joints whose "
                f"positions are already determined ({', '.join(map(str, parents))})"
            )
        order.append((j, parents[0], parents[1]))
        known[j] = True
        for k in neighbours[j]:
            known_count[k] += 1
            if not known[k] and known_count[k] == 2:
                heapq.heappush(solvable, k)
    if not all(known):
        unsolved = [j for j in range(n) if not known[j]]
        moving, links, dof = mobility(adj, types)
        if dof > 1:
            raise InvalidMechanismError(
                f"more than one degree of freedom: 2 x {moving} moving joints - {links} links "
                f"= {dof}; joints {unsolved} are not determined by the crank"
            )
        if dof < 1:
            raise InvalidMechanismError(
                f"over-constrained: 2 x {moving} moving joints - {links} links = {dof}; "
                f"joints {unsolved} cannot be solved"
            )
        raise InvalidMechanismError(
            f"not dyadic-solvable: joints {unsolved} never have two known neighbours "
            "(a complex kinematic loop)"
        )
    return np.array(order, dtype=np.int64).reshape(-1, 3)


def structure_violations(topology: Topology) -> list[str]:
    """The topology rules of the dataset this topology breaks: reducibility and the last joint."""
    problems = []
    last = topology.last_joint
    if len(topology.ancestors(last)) != topology.n_joints:
        problems.append(f"reducible: the last joint {last} does not depend on every joint")
    if np.any(topology.adjacency[last] & (topology.node_types == FIXED)):
        problems.append(f"the last joint {last} is linked to a fixed joint")
    return problems


def dataset_rule_violations(
    topology: Topology, positions: np.ndarray | None = None, *, atol: float = 1e-12
) -> list[str]:
    """The dataset rules this mechanism breaks (empty when it obeys them all).

    The rules are those of docs/reference/contract.md, Mechanisms. Locking is not checked here;
    simulate for that.
    """
    problems = structure_violations(topology)
    n = topology.n_joints
    if not MIN_DATASET_JOINTS <= n <= MAX_DATASET_JOINTS:
        problems.append(f"{n} joints, outside {MIN_DATASET_JOINTS}-{MAX_DATASET_JOINTS}")
    if positions is not None:
        if not np.allclose(positions[0], CRANK_CENTER, rtol=0, atol=atol):
            problems.append(f"joint 0 at {positions[0].tolist()}, not {CRANK_CENTER}")
        if not np.allclose(positions[1], CRANK_TIP, rtol=0, atol=atol):
            problems.append(f"joint 1 at {positions[1].tolist()}, not {CRANK_TIP}")
        if np.any((positions < 0) | (positions > 1)):
            problems.append("initial positions outside [0, 1]^2")
    return problems


def reduce_mechanism(
    adjacency: ArrayLike, node_types: ArrayLike, positions: ArrayLike, joint: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """The sub-mechanism of only the joints `joint`'s motion needs.

    Returns (adjacency, node_types, positions, index of `joint` in it). Joints keep their
    relative order, so joints 0 and 1 stay the crank; the links kept are exactly those used to
    solve the kept joints.
    """
    topology = analyze_topology(adjacency, node_types)
    n = topology.n_joints
    pos = as_positions(positions, n)
    if isinstance(joint, bool) or not isinstance(joint, int | np.integer):
        raise InvalidMechanismError(f"joint must be an integer, got {joint!r}")
    if not 0 <= joint < n:
        raise InvalidMechanismError(f"joint {joint} does not exist in a {n}-joint mechanism")
    if topology.node_types[joint] == FIXED:
        raise InvalidMechanismError(f"joint {joint} is fixed: it has no motion to reduce to")
    keep = topology.ancestors(int(joint))
    return (
        topology.adjacency[np.ix_(keep, keep)].copy(),
        topology.node_types[keep].copy(),
        pos[keep].copy(),
        int(np.searchsorted(keep, joint)),
    )


def arc_flags(adjacency: np.ndarray, node_types: np.ndarray) -> np.ndarray:
    """Which joints trace arcs: the moving joints linked to a fixed joint (they turn about it).

    adjacency (..., n, n) and node_types (..., n) -> (..., n) bool; a batch of mechanisms of
    one size works as one mechanism does. docs/reference/contract.md, Dataset layout, `is_arc`.
    """
    fixed = np.asarray(node_types) == FIXED
    on_ground = ((np.asarray(adjacency) != 0) & fixed[..., None, :]).any(axis=-1)
    return on_ground & ~fixed


def arc_joints(topology: Topology) -> np.ndarray:
    """(n,) bool: `arc_flags` of a validated topology."""
    return arc_flags(topology.adjacency, topology.node_types)
