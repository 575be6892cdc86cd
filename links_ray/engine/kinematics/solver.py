"""The compiled dyadic solver (docs/reference/contract.md, Simulation).

One numba kernel serves every topology: the topology enters as data (its solution path), so nothing
is compiled per topology. A candidate is simulated step by step and stops at its first lock, so
rejecting a locking candidate costs only the steps it survived. A turn that assembles at every
sampled step is then checked between them (`engine.kinematics.turning`): valid means it turns.

Pure numpy/numba: no Ray.
"""

from __future__ import annotations

import functools
import threading
from collections import OrderedDict

import numpy as np
from numba import njit
from numpy.typing import ArrayLike

from links_ray.engine.buffers import (
    check_buffer,
    check_indices,
    check_packed_paths,
    check_solution_path,
)
from links_ray.engine.inputs import (
    DEFAULT_STEPS,
    MAX_COORDINATE,
    MIN_LINK_LENGTH,
    as_positions,
    as_steps,
    check_positions,
)
from links_ray.engine.kinematics.mechanism import LockingError, Topology, analyze_topology
from links_ray.engine.kinematics.turning import _turn_lock

#: Steps solved together per joint when trajectories are kept (see `simulate_one`).
BLOCK = 16
#: Steps per block of a lock check: small, so a rejected candidate costs little past its lock.
CHECK_BLOCK = 4
#: Topologies `simulate`, `simulate_batch` and `simulate_until_lock` keep analysed (validated,
#: solution path found), the least recently used dropped first.
TOPOLOGY_CACHE_SIZE = 256
#: Larger topologies are analysed at every call: their keys would be large (n x n entries),
#: and the analysis is small beside their simulation.
CACHE_MAX_JOINTS = 100


@njit(cache=True, nogil=True, error_model="numpy")
def crank_table(steps: int) -> np.ndarray:
    """cos and sin of the crank turn at each step, (steps, 2)."""
    table = np.empty((steps, 2))
    for t in range(steps):
        angle = 2.0 * np.pi * t / steps
        table[t, 0] = np.cos(angle)
        table[t, 1] = np.sin(angle)
    return table


@njit(cache=True, nogil=True, error_model="numpy")
def _dyad_geometry(order: np.ndarray, pos: np.ndarray, geometry: np.ndarray) -> None:
    """Per solved joint: radius to each parent and the frozen branch sign, from the initial pose.

    The branch sign is the side of the line parent_a -> parent_b the joint starts on (+1 left,
    -1 right; a joint exactly on the line counts as left).
    """
    for k in range(order.shape[0]):
        j, a, b = order[k, 0], order[k, 1], order[k, 2]
        geometry[k, 0] = np.hypot(pos[j, 0] - pos[a, 0], pos[j, 1] - pos[a, 1])
        geometry[k, 1] = np.hypot(pos[j, 0] - pos[b, 0], pos[j, 1] - pos[b, 1])
        cross = (pos[b, 0] - pos[a, 0]) * (pos[j, 1] - pos[a, 1]) - (pos[b, 1] - pos[a, 1]) * (
            pos[j, 0] - pos[a, 0]
        )
        geometry[k, 2] = 1.0 if cross >= 0.0 else -1.0


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def dyad_fails(d_sq: float, r1: float, r2: float) -> bool:
    """Whether circles of radii r1 and r2 whose centres are sqrt(d_sq) apart fail to meet.

    Compared in squares, which saves a square root per joint and step.
    """
    outer = r1 + r2
    inner = r1 - r2
    # Bitwise, not short-circuit: no branches in the solver's inner loop.
    return (d_sq > outer * outer) | (d_sq < inner * inner) | (d_sq == 0.0)


@njit(cache=True, nogil=True, error_model="numpy")
def _solve_span(
    traj: np.ndarray, j: int, a: int, b: int, r1: float, r2: float, side: float, lo: int, hi: int
) -> int:
    """Place joint j at rows lo:hi of `traj` (n, rows, 2) from parents a and b.

    The joint sits at distance r1 from a and r2 from b, on `side` of the line a -> b (+1 left).
    Returns how many rows lock; their values are meaningless. Branch-free, so the rows' work
    overlaps in the CPU.
    """
    r1_sq = r1 * r1
    lever = r1_sq - r2 * r2
    failures = 0
    # error_model="numpy": a zero d_sq (a lock) gives inf/NaN here instead of raising.
    for s in range(lo, hi):
        ax = traj[a, s, 0]
        ay = traj[a, s, 1]
        dx = traj[b, s, 0] - ax
        dy = traj[b, s, 1] - ay
        d_sq = dx * dx + dy * dy
        failures += dyad_fails(d_sq, r1, r2)
        # Along a -> b by `along` d, then sideways by `height` d: one division, one root.
        inv_d_sq = 1.0 / d_sq
        along = 0.5 * (d_sq + lever) * inv_d_sq
        # Rounding can push this just below zero at tangency, where the circles do touch.
        height = side * np.sqrt(max(r1_sq * inv_d_sq - along * along, 0.0))
        traj[j, s, 0] = ax + along * dx - height * dy
        traj[j, s, 1] = ay + along * dy + height * dx
    return failures


@njit(cache=True, nogil=True, error_model="numpy")
def _first_failure(traj: np.ndarray, a: int, b: int, r1: float, r2: float, lo: int, hi: int) -> int:
    """The first row in lo:hi where a dyad on parents a and b cannot be assembled, else -1."""
    for s in range(lo, hi):
        dx = traj[b, s, 0] - traj[a, s, 0]
        dy = traj[b, s, 1] - traj[a, s, 1]
        if dyad_fails(dx * dx + dy * dy, r1, r2):
            return s
    return -1


@njit(cache=True, nogil=True, error_model="numpy")
def _place_crank(
    pos: np.ndarray, crank: np.ndarray, traj: np.ndarray, start: int, stop: int, row: int
) -> None:
    """Joint 1 at crank steps start:stop, the initial crank turned, into `traj` from `row` on."""
    cx, cy = pos[0, 0], pos[0, 1]
    vx, vy = pos[1, 0] - cx, pos[1, 1] - cy
    for t in range(start, stop):
        c, s = crank[t, 0], crank[t, 1]
        traj[1, row + t - start, 0] = cx + c * vx - s * vy
        traj[1, row + t - start, 1] = cy + s * vx + c * vy


@njit(cache=True, nogil=True, error_model="numpy")
def _place_fixed(fixed: np.ndarray, pos: np.ndarray, traj: np.ndarray, rows: int) -> None:
    """Fixed joints at their initial positions in the first `rows` rows of `traj`."""
    for i in range(fixed.shape[0]):
        f = fixed[i]
        for s in range(rows):
            traj[f, s, 0] = pos[f, 0]
            traj[f, s, 1] = pos[f, 1]


@njit(cache=True, nogil=True, error_model="numpy")
def _simulate_one(
    order: np.ndarray,
    fixed: np.ndarray,
    pos: np.ndarray,
    crank: np.ndarray,
    keep: bool,
    out: np.ndarray,
    geometry: np.ndarray,
) -> tuple[int, int]:
    """Simulate one position set over `crank` steps into `out`.

    Steps go in blocks; inside a block each joint is solved for every step before the next
    joint, so independent steps overlap in the CPU instead of waiting on one long chain. With
    `keep`, `out` is (n, steps, 2) and keeps every step (blocks of `BLOCK`); without, it is
    (n, block, 2) scratch, all a lock check needs. Returns (-1, -1) when valid, else (first
    locking step, joint): the earliest step at which some joint cannot be assembled, and the
    first such joint in solution order. Rows of a locking candidate are left partly written.
    """
    steps = crank.shape[0]
    block = BLOCK if keep else out.shape[1]
    _dyad_geometry(order, pos, geometry)
    _place_fixed(fixed, pos, out, steps if keep else block)
    for start in range(0, steps, block):
        stop = min(start + block, steps)
        # Rows of `out` for this block: absolute steps with `keep`, block-relative without.
        lo = start if keep else 0
        hi = lo + stop - start
        _place_crank(pos, crank, out, start, stop, lo)
        lock_step, lock_node = -1, -1
        for k in range(order.shape[0]):
            j, a, b = order[k, 0], order[k, 1], order[k, 2]
            r1, r2 = geometry[k, 0], geometry[k, 1]
            if _solve_span(out, j, a, b, r1, r2, geometry[k, 2], lo, hi):
                # Later joints need only the rows before this joint's first lock.
                hi = _first_failure(out, a, b, r1, r2, lo, hi)
                lock_step, lock_node = start + hi - lo, j
        if lock_step >= 0:
            return lock_step, lock_node
    return -1, -1


@njit(cache=True, nogil=True, error_model="numpy")
def _positions_suspect(
    pos: np.ndarray, link_i: np.ndarray, link_j: np.ndarray, max_coordinate: float, min_link: float
) -> bool:
    """Whether `inputs.as_positions` or `inputs.check_positions` might refuse position sets
    (B, n, 2) of links (link_i, link_j): a coordinate that is not finite or beyond
    `max_coordinate`, or a link shorter than twice `min_link`. Never False where they would
    refuse, so a caller that runs them only when this is True refuses exactly what they do."""
    bound = (2.0 * min_link) * (2.0 * min_link)
    for b in range(pos.shape[0]):
        for i in range(pos.shape[1]):
            # Written so that NaN fails too.
            if not (abs(pos[b, i, 0]) <= max_coordinate and abs(pos[b, i, 1]) <= max_coordinate):
                return True
        for k in range(link_i.shape[0]):
            dx = pos[b, link_i[k], 0] - pos[b, link_j[k], 0]
            dy = pos[b, link_i[k], 1] - pos[b, link_j[k], 1]
            if dx * dx + dy * dy < bound:
                return True
    return False


@njit(cache=True, nogil=True, error_model="numpy")
def _simulate_turn(
    order: np.ndarray,
    fixed: np.ndarray,
    pos: np.ndarray,
    crank: np.ndarray,
    out: np.ndarray,
    geometry: np.ndarray,
) -> tuple[int, int]:
    """`simulate_one` keeping every step in `out` (n, steps, 2), then the check between the
    steps (`turning.turn_lock`): (-1, -1) only if the crank certainly turns fully."""
    step, node = _simulate_one(order, fixed, pos, crank, True, out, geometry)
    if step < 0:
        step, node = _turn_lock(order, pos, geometry, out)
    return step, node


@njit(cache=True, nogil=True, error_model="numpy")
def _simulate_candidates(
    order: np.ndarray,
    fixed: np.ndarray,
    positions: np.ndarray,
    crank: np.ndarray,
    keep: bool,
    out: np.ndarray,
    lock_step: np.ndarray,
    lock_node: np.ndarray,
) -> None:
    """Simulate position sets (B, n, 2) of one topology, one thread, each checked between its
    steps too (`simulate_turn`).

    With `keep`, `out` is (B, n, steps, 2) and a locking candidate's rows become NaN; without,
    `out` is scratch of shape (1, n, block, 2) and only the lock results are produced.
    """
    geometry = np.empty((order.shape[0], 3))
    turn = np.empty((0, 0, 2))  # a whole turn, for candidates a blockwise check passes
    for b in range(positions.shape[0]):
        if keep:
            step, node = _simulate_turn(order, fixed, positions[b], crank, out[b], geometry)
        else:
            step, node = _simulate_one(order, fixed, positions[b], crank, False, out[0], geometry)
            if step < 0:
                if turn.shape[0] == 0:
                    turn = np.empty((positions.shape[1], crank.shape[0], 2))
                step, node = _simulate_turn(order, fixed, positions[b], crank, turn, geometry)
        lock_step[b] = step
        lock_node[b] = node
        if keep and step >= 0:
            out[b] = np.nan


@njit(cache=True, nogil=True, error_model="numpy")
def _trace_joints(
    orders: np.ndarray,
    order_start: np.ndarray,
    positions: np.ndarray,
    joint_start: np.ndarray,
    mechanisms: np.ndarray,
    joints: np.ndarray,
    crank: np.ndarray,
    out: np.ndarray,
) -> None:
    """out[i] = the trajectory (steps, 2) of joint joints[i] of mechanism mechanisms[i], for
    many mechanisms of any topologies held packed: mechanism m's solution path is
    orders[order_start[m]:order_start[m + 1]] (rows joint, parent_a, parent_b) and its initial
    positions positions[joint_start[m]:joint_start[m + 1]]. The joints that are neither joint 1
    nor in its solution path are fixed. Mechanisms that lock give NaN rows.

    The arithmetic is `simulate_one`'s, so a trajectory equals the one `TopologySimulator`
    gives for the whole mechanism, bit for bit.
    """
    steps = crank.shape[0]
    for i in range(mechanisms.shape[0]):
        m = mechanisms[i]
        pos = positions[joint_start[m] : joint_start[m + 1]]
        n = pos.shape[0]
        order = orders[order_start[m] : order_start[m + 1]].astype(np.int64)
        solved = np.zeros(n, dtype=np.bool_)
        solved[1] = True
        for k in range(order.shape[0]):
            solved[order[k, 0]] = True
        fixed = np.flatnonzero(~solved).astype(np.int64)
        traj = np.empty((n, steps, 2))
        geometry = np.empty((order.shape[0], 3))
        step, _ = _simulate_one(order, fixed, pos, crank, True, traj, geometry)
        if step >= 0:
            out[i] = np.nan
        else:
            out[i] = traj[joints[i]]


# -- entry points: the kernels above, called from Python with the caller's buffers --------------
# numba checks no bounds, so each checks its buffers' shapes against the positions and the
# solution path first (`buffers.check_buffer`). This module's own callers, which make their
# buffers from the topology they hold, call the kernels directly.


def _check_turn_buffers(
    order: np.ndarray, fixed: np.ndarray | None, pos: np.ndarray, crank: np.ndarray
) -> tuple[int, int, int]:
    """(n, m, steps) of a mechanism's positions `pos` (n, 2), its solution path and `crank`."""
    check_buffer("pos", pos, (None, 2))
    n = pos.shape[0]
    check_solution_path(order, n, fixed)
    check_buffer("crank", crank, (None, 2))
    return n, order.shape[0], crank.shape[0]


def dyad_geometry(order: np.ndarray, pos: np.ndarray, geometry: np.ndarray) -> None:
    """Per solved joint k of `order`, into geometry[k] (m, 3): its radius to each parent and
    its frozen branch sign (+1 left of the line parent_a -> parent_b, -1 right), from the
    positions `pos` (n, 2)."""
    check_buffer("pos", pos, (None, 2))
    check_solution_path(order, pos.shape[0])
    check_buffer("geometry", geometry, (order.shape[0], 3))
    _dyad_geometry(order, pos, geometry)


def simulate_one(
    order: np.ndarray,
    fixed: np.ndarray,
    pos: np.ndarray,
    crank: np.ndarray,
    keep: bool,
    out: np.ndarray,
    geometry: np.ndarray,
) -> tuple[int, int]:
    """Simulate the positions `pos` (n, 2) over the `crank` (steps, 2) steps, checking only
    the steps themselves: (-1, -1) when every step assembles, else (first locking step,
    joint). With `keep`, `out` (n, steps, 2) receives the trajectories; without, it is
    scratch (n, block, 2). `geometry` (m, 3) receives `dyad_geometry`'s."""
    n, m, steps = _check_turn_buffers(order, fixed, pos, crank)
    check_buffer("out", out, (n, steps, 2) if keep else (n, None, 2))
    if not keep and out.shape[1] == 0:
        raise ValueError("out must have at least one step of scratch, got shape (n, 0, 2)")
    check_buffer("geometry", geometry, (m, 3))
    return _simulate_one(order, fixed, pos, crank, keep, out, geometry)


def simulate_turn(
    order: np.ndarray,
    fixed: np.ndarray,
    pos: np.ndarray,
    crank: np.ndarray,
    out: np.ndarray,
    geometry: np.ndarray,
) -> tuple[int, int]:
    """`simulate_one` keeping every step in `out` (n, steps, 2), then the check between the
    steps: (-1, -1) only if the crank certainly turns fully."""
    n, m, steps = _check_turn_buffers(order, fixed, pos, crank)
    check_buffer("out", out, (n, steps, 2))
    check_buffer("geometry", geometry, (m, 3))
    return _simulate_turn(order, fixed, pos, crank, out, geometry)


def simulate_candidates(
    order: np.ndarray,
    fixed: np.ndarray,
    positions: np.ndarray,
    crank: np.ndarray,
    keep: bool,
    out: np.ndarray,
    lock_step: np.ndarray,
    lock_node: np.ndarray,
) -> None:
    """Position sets (B, n, 2) of one topology, each checked between its steps too: with
    `keep`, trajectories into `out` (B, n, steps, 2), NaN where a set locks; without, `out`
    is scratch (1, n, block, 2). lock_step and lock_node (B,) int64 receive each set's lock
    (-1 where valid)."""
    check_buffer("positions", positions, (None, None, 2))
    batch, n = positions.shape[:2]
    check_solution_path(order, n, fixed, positions="positions")
    check_buffer("crank", crank, (None, 2))
    steps = crank.shape[0]
    check_buffer("out", out, (batch, n, steps, 2) if keep else (1, n, None, 2))
    if not keep and out.shape[2] == 0:
        raise ValueError("out must have at least one step of scratch, got shape (1, n, 0, 2)")
    check_buffer("lock_step", lock_step, (batch,), np.int64)
    check_buffer("lock_node", lock_node, (batch,), np.int64)
    _simulate_candidates(order, fixed, positions, crank, keep, out, lock_step, lock_node)


def trace_joints(
    orders: np.ndarray,
    order_start: np.ndarray,
    positions: np.ndarray,
    joint_start: np.ndarray,
    mechanisms: np.ndarray,
    joints: np.ndarray,
    crank: np.ndarray,
    out: np.ndarray,
) -> None:
    """out[i] (F, steps, 2) = the trajectory of joint joints[i] of mechanism mechanisms[i],
    of mechanisms held packed (`_trace_joints` says how); NaN rows where a mechanism locks.
    The packed solution paths are the holder's (`search.mechanisms.MechanismBank`), checked
    when it was made; the rest is checked here."""
    check_packed_paths(orders, order_start, joint_start, mechanisms, joints)
    check_buffer("positions", positions, (None, 2))
    check_buffer("crank", crank, (None, 2))
    check_buffer("out", out, (mechanisms.shape[0], crank.shape[0], 2))
    check_indices("joint_start", joint_start, positions.shape[0] + 1, "the rows of positions")
    _trace_joints(orders, order_start, positions, joint_start, mechanisms, joints, crank, out)


@functools.lru_cache(maxsize=16)
def crank_turn(steps: int) -> np.ndarray:
    """`crank_table(steps)`, made once per step count: callers share it, and never write to it."""
    return crank_table(steps)


class TopologySimulator:
    """Simulates many position sets of one topology; its solution path is found once."""

    def __init__(self, adjacency: ArrayLike, node_types: ArrayLike) -> None:
        self.topology: Topology = analyze_topology(adjacency, node_types)

    @classmethod
    def from_topology(cls, topology: Topology) -> TopologySimulator:
        """Wrap an already validated topology."""
        simulator = cls.__new__(cls)
        simulator.topology = topology
        return simulator

    @property
    def n_joints(self) -> int:
        """The topology's number of joints."""
        return self.topology.n_joints

    def crank(self, steps: int) -> np.ndarray:
        """The crank's turn at `steps` steps (`crank_turn`)."""
        return crank_turn(steps)

    def _prepare(self, positions: ArrayLike, steps: int) -> tuple[np.ndarray, int]:
        return checked_input(self.topology, positions, steps, batch=True)

    def simulate(
        self, positions: ArrayLike, steps: int = DEFAULT_STEPS
    ) -> tuple[np.ndarray, np.ndarray]:
        """Trajectories (B, n, steps, 2), NaN where invalid, and the valid mask (B,)."""
        positions, steps = self._prepare(positions, steps)
        trajectories, lock_step, _ = self.run(positions, steps)
        return trajectories, lock_step < 0

    def run(
        self,
        positions: np.ndarray,
        steps: int,
        *,
        out: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Fast path: (trajectories, lock_step, lock_node), -1 where valid.

        `positions` must already be a valid float64 (B, n, 2) array: its shape and an `out`'s
        are checked (ValueError), its values are not. Passing a reused float64
        `out` of shape (B, n, steps, 2) saves the page faults of a fresh large array, which can
        cost more than the simulation itself.
        """
        batch = positions.shape[0]
        if out is None:
            out = np.empty((batch, self.n_joints, steps, 2))
        lock_step = np.empty(batch, dtype=np.int64)
        lock_node = np.empty(batch, dtype=np.int64)
        simulate_candidates(
            self.topology.order,
            self.topology.fixed_joints,
            positions,
            self.crank(steps),
            True,
            out,
            lock_step,
            lock_node,
        )
        return out, lock_step, lock_node

    def first_lock(
        self, positions: ArrayLike, steps: int = DEFAULT_STEPS
    ) -> tuple[np.ndarray, np.ndarray]:
        """First locking step and joint per position set (-1 where valid); stores no paths."""
        positions, steps = self._prepare(positions, steps)
        return self.lock_check(positions, steps)

    def lock_check(self, positions: np.ndarray, steps: int) -> tuple[np.ndarray, np.ndarray]:
        """Fast path of `first_lock`: positions as `run` takes them."""
        # The path and fixed joints are the validated topology's: only positions need a check.
        check_buffer("positions", positions, (None, self.n_joints, 2))
        batch = positions.shape[0]
        lock_step = np.empty(batch, dtype=np.int64)
        lock_node = np.empty(batch, dtype=np.int64)
        # Scratch per call (it is tiny), so threads may share a simulator.
        scratch = np.empty((1, self.n_joints, CHECK_BLOCK, 2))
        _simulate_candidates(
            self.topology.order,
            self.topology.fixed_joints,
            positions,
            self.crank(steps),
            False,
            scratch,
            lock_step,
            lock_node,
        )
        return lock_step, lock_node


class _TopologyCache:
    """Analysed topologies by the bytes of the arrays they were given: a bounded LRU, shared
    by threads. Only topologies that pass the analysis are kept, so a bad one raises the same
    error at every call."""

    def __init__(self, size: int) -> None:
        self.size = size
        self._simulators: OrderedDict[tuple, TopologySimulator] = OrderedDict()
        self._lock = threading.Lock()

    @staticmethod
    def key(adjacency: np.ndarray, node_types: np.ndarray) -> tuple | None:
        """What the analysis of these arrays depends on (copied: a caller may change its
        arrays later), or None for arrays not to cache: non-numeric ones, which the analysis
        refuses with a message, and large ones."""
        if (
            adjacency.dtype.kind not in "biuf"
            or node_types.dtype.kind not in "biuf"
            or adjacency.size > CACHE_MAX_JOINTS * CACHE_MAX_JOINTS
            or node_types.size > CACHE_MAX_JOINTS
        ):
            return None
        return (
            adjacency.dtype.str,
            adjacency.shape,
            adjacency.tobytes(),
            node_types.dtype.str,
            node_types.shape,
            node_types.tobytes(),
        )

    def simulator(self, adjacency: ArrayLike, node_types: ArrayLike) -> TopologySimulator:
        """The simulator of this topology, analysed at its first call only."""
        try:
            adjacency, node_types = np.asarray(adjacency), np.asarray(node_types)
        except (TypeError, ValueError):  # ragged lists: the analysis names the problem
            return TopologySimulator(adjacency, node_types)
        key = self.key(adjacency, node_types)
        if key is None:
            return TopologySimulator(adjacency, node_types)
        with self._lock:
            simulator = self._simulators.get(key)
            if simulator is not None:
                self._simulators.move_to_end(key)
                return simulator
        # Raises for a bad topology. Its arrays are copies of the caller's, so a caller that
        # changes its own arrays later changes neither this simulator nor its key. They stay
        # writable: read-only arrays would be another type for each compiled kernel.
        simulator = TopologySimulator(adjacency, node_types)
        with self._lock:
            self._simulators[key] = simulator
            while len(self._simulators) > self.size:
                self._simulators.popitem(last=False)
        return simulator

    def clear(self) -> None:
        with self._lock:
            self._simulators.clear()

    def __len__(self) -> int:
        return len(self._simulators)


#: The topologies the one-call functions below have analysed.
topology_cache = _TopologyCache(TOPOLOGY_CACHE_SIZE)


def simulate_batch(
    adjacency: ArrayLike,
    node_types: ArrayLike,
    positions: ArrayLike,
    steps: int = DEFAULT_STEPS,
) -> tuple[np.ndarray, np.ndarray]:
    """One topology, positions (B, n, 2) -> (trajectories (B, n, steps, 2), valid (B,))."""
    return topology_cache.simulator(adjacency, node_types).simulate(positions, steps)


def checked_input(
    topology: Topology, positions: ArrayLike, steps: object, *, batch: bool = False
) -> tuple[np.ndarray, int]:
    """(positions, steps) of `topology` as `inputs.as_positions` and `as_steps` return them,
    refused as they and `inputs.check_positions` refuse them, in the API's order: for a
    batch (B, n, 2) the steps first, else the positions' form, the steps, their geometry.

    The positions' checks run in full only for an array that is not plain float64 or where
    `_positions_suspect` finds something they might refuse: a call in a loop costs about a
    microsecond, not tens."""
    if batch:
        steps = as_steps(steps)
    n = topology.n_joints
    plain = (
        type(positions) is np.ndarray
        and positions.dtype == np.float64
        and positions.flags.c_contiguous
        and positions.shape[-2:] == (n, 2)
        and positions.ndim == (3 if batch else 2)
    )
    if not plain:
        positions = as_positions(positions, n, batch=batch)
    link_i, link_j = topology.links
    sets = positions.reshape(-1, n, 2)
    suspect = _positions_suspect(sets, link_i, link_j, MAX_COORDINATE, MIN_LINK_LENGTH)
    if suspect:
        as_positions(positions, n, batch=batch)  # names NaN or infinite entries
    if not batch:
        steps = as_steps(steps)
    if suspect:
        check_positions(topology.adjacency, positions, topology.links)
    return positions, int(steps)


def simulate(
    adjacency: ArrayLike,
    node_types: ArrayLike,
    positions: ArrayLike,
    steps: int = DEFAULT_STEPS,
) -> np.ndarray:
    """Trajectories (n, steps, 2) of one mechanism; raises `LockingError` if it locks.

    The topology's analysis is kept (`topology_cache`), so calls in a loop pay only for the
    positions' checks and the simulation.
    """
    simulator = topology_cache.simulator(adjacency, node_types)
    topology = simulator.topology
    positions, steps = checked_input(topology, positions, steps)
    out = np.empty((simulator.n_joints, steps, 2))
    geometry = np.empty((topology.order.shape[0], 3))
    step, node = _simulate_turn(
        topology.order, topology.fixed_joints, positions, crank_turn(steps), out, geometry
    )
    if step >= 0:
        raise LockingError(step, node)
    return out


def simulate_until_lock(
    adjacency: ArrayLike,
    node_types: ArrayLike,
    positions: ArrayLike,
    steps: int = DEFAULT_STEPS,
) -> tuple[np.ndarray, int, int]:
    """Trajectories (n, s, 2) of the steps before the first lock, and that lock's (step, joint).

    Without a lock, s = steps and the lock is (-1, -1). Malformed input raises
    `InvalidMechanismError` as `simulate` does.
    """
    simulator = topology_cache.simulator(adjacency, node_types)
    topology = simulator.topology
    positions, steps = checked_input(topology, positions, steps)
    out = np.empty((simulator.n_joints, steps, 2))
    geometry = np.empty((topology.order.shape[0], 3))
    crank = crank_turn(steps)
    step, node = _simulate_turn(
        topology.order, topology.fixed_joints, positions, crank, out, geometry
    )
    if step < 0:
        return out, -1, -1
    # Every step before the first lock assembles: solve just those, on the same crank angles,
    # without the check between steps (the part of a turn before a lock does not close).
    before = np.empty((simulator.n_joints, step, 2))
    _simulate_one(
        topology.order, topology.fixed_joints, positions, crank[:step], True, before, geometry
    )
    return before, step, node
