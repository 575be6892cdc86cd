"""One batch of the LINKS release's files, checked as the import reads it: every entry's
shape and type, each mechanism analyzed by links-ray's validators and simulated at the
release's angles against the release's own trajectory (`release_check`), and the release's
curated (j, node) pairs. Anything else is one `ReleaseFileError` naming the file, the batch
and the index.

Pure numpy: no Ray.
"""

from __future__ import annotations

import copy
from typing import Any

import numpy as np

from links_ray.engine.inputs import InvalidMechanismError
from links_ray.engine.kinematics.mechanism import MAX_DATASET_JOINTS, Topology, analyze_topology
from links_ray.engine.node_kinds import ACTUATED, FIXED, SIMPLE
from links_ray.release.format import RELEASE_STEPS, release_turn
from links_ray.release.ids import BATCH_STRIDE
from links_ray.release.pickles import ReleaseFileError

#: A joint's largest distance from the release's own trajectory, relative to the mechanism's
#: size (the largest coordinate difference of its x0), below which the two agree: the
#: release's float32 rounding is some 1e-7 of it.
AGREEMENT_TOLERANCE = 1e-4
#: A mechanism's check against the release (`release_check`), and the summary's count of each.
VERDICT_STATS = {
    "agree": "agreeing",
    "disagree": "disagreeing",
    "locks": "locking_at_release_angles",
    "unchecked": "unchecked",
}
VERDICTS = tuple(VERDICT_STATS)
#: The dtypes a release trajectory (`x_sol`) or curve may have: the release's files hold
#: float32, but its own numpy solver (`sim.solve_rev_vectorized`) makes float64.
FLOAT_DTYPES = ("float16", "float32", "float64")
#: One entry of a batch of `simulation_dataset`: (its index k in the batch, x_sol, j).
Solution = tuple[int, Any, int]


def _entries(value: Any, shown: str, width: int) -> list:
    if not isinstance(value, list):
        raise ReleaseFileError(f"{shown} is a {type(value).__name__}, not a list")
    for index, entry in enumerate(value):
        if not isinstance(entry, list | tuple) or len(entry) != width:
            raise ReleaseFileError(f"{shown} index {index} is not a list of {width} items")
    return value


def _index(value: Any, shown: str, limit: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or not 0 <= value < limit:
        raise ReleaseFileError(
            f"{shown}: j must be an index of the batch's {limit}, got {_shown_number(value)}"
        )
    return int(value)


def _shown_number(value: Any) -> str:
    # Only a number is shown: a file's list could be deeply nested or huge.
    return (
        repr(value) if isinstance(value, int | float | np.number) else f"a {type(value).__name__}"
    )


def _array(value: Any, shown: str, name: str, shape: tuple[int, ...], dtype: type) -> np.ndarray:
    if not isinstance(value, np.ndarray) or value.dtype != np.dtype(dtype) or value.shape != shape:
        got = (
            f"{value.shape} {value.dtype}"
            if isinstance(value, np.ndarray)
            else type(value).__name__
        )
        raise ReleaseFileError(f"{shown}: {name} must be {shape} {np.dtype(dtype).name}, got {got}")
    return value


def _floats(value: Any, shown: str, name: str, shape: tuple[int, ...]) -> np.ndarray:
    """`value` if it is a finite array of `shape` in one of FLOAT_DTYPES (either byte order);
    ReleaseFileError in one line otherwise. It is only read, never stored, so any of them
    serves: values are compared in float64."""
    if (
        not isinstance(value, np.ndarray)
        or value.dtype.newbyteorder("=").name not in FLOAT_DTYPES
        or value.shape != shape
    ):
        got = (
            f"{value.shape} {value.dtype}"
            if isinstance(value, np.ndarray)
            else type(value).__name__
        )
        raise ReleaseFileError(
            f"{shown}: {name} must be {shape} float16, float32 or float64, got {got}"
        )
    if not np.isfinite(value).all():
        raise ReleaseFileError(f"{shown}: {name} must be finite, and holds NaN or infinity")
    return value


class CheckedBatch:
    """One release batch, checked: its mechanisms, each one's check against the release's
    simulation of it (the simulations themselves are not kept), and the release's curated
    (j, node) pairs of it."""

    def __init__(self, shown: str, batch: int, value: Any) -> None:
        self.batch = batch
        entries = _entries(value, f"{shown} batch {batch}", 3)
        if len(entries) > BATCH_STRIDE:
            raise ReleaseFileError(
                f"{shown} batch {batch} holds {len(entries)} mechanisms; at most {BATCH_STRIDE}"
            )
        self.size = len(entries)
        # By index in the batch: lists of the whole batch, dicts in a part of it (`part`).
        self.adjacency: list[np.ndarray] | dict[int, np.ndarray] = []
        self.fixed: list[np.ndarray] | dict[int, np.ndarray] = []
        self.x0: list[np.ndarray] | dict[int, np.ndarray] = []
        for index, (a, x0, fixed) in enumerate(entries):
            where = f"{shown} batch {batch} index {index}"
            n = len(fixed) if isinstance(fixed, np.ndarray) and fixed.ndim == 1 else -1
            if not 2 <= n <= MAX_DATASET_JOINTS:
                raise ReleaseFileError(
                    f"{where}: node_type must be (n,) bool with n from 2 to "
                    f"{MAX_DATASET_JOINTS}, got "
                    + (
                        f"{fixed.shape} {fixed.dtype}"
                        if isinstance(fixed, np.ndarray)
                        else type(fixed).__name__
                    )
                )
            self.fixed.append(_array(fixed, where, "node_type", (n,), np.bool_))
            self.adjacency.append(_array(a, where, "A", (n, n), np.bool_))
            self.x0.append(_array(x0, where, "x0", (n, 2), np.float32))
        self.n_joints = np.array([len(f) for f in self.fixed], dtype=np.int64)
        #: Each checked mechanism's check against the release (one of VERDICTS) and its error
        #: there, by index in the batch.
        self.checks: dict[int, tuple[str, float]] = {}
        self.curated: set[tuple[int, int]] | None = None
        self._shown = shown
        self._topologies: dict[tuple[bytes, bytes], Topology] = {}

    def topology(self, j: int) -> Topology:
        """The analyzed topology of mechanism `j` (shared by every mechanism with the same
        `A` and `node_type`); ReleaseFileError naming `j` for one links-ray cannot simulate."""
        key = (self.adjacency[j].tobytes(), self.fixed[j].tobytes())
        found = self._topologies.get(key)
        if found is None:
            try:
                found = analyze_topology(self.adjacency[j], node_types_of(self.fixed[j]))
            except InvalidMechanismError as exc:
                raise ReleaseFileError(
                    f"{self._shown} batch {self.batch} index {j}: {exc}"
                ) from None
            self._topologies[key] = found
        return found

    def part(self, n: int) -> CheckedBatch:
        """The mechanisms of `n` joints of this batch, with their batch indices, checks so far
        and curated pairs: what one shard of the import reads, without the rest of the batch
        (small enough to hand to another process)."""
        indices = np.flatnonzero(self.n_joints == n).tolist()
        part = copy.copy(self)
        part.adjacency = {j: self.adjacency[j] for j in indices}
        part.fixed = {j: self.fixed[j] for j in indices}
        part.x0 = {j: self.x0[j] for j in indices}
        part.checks = {j: check for j, check in self.checks.items() if j in part.x0}
        if self.curated is not None:
            part.curated = {(j, node) for j, node in self.curated if self.n_joints[j] == n}
        part._topologies = {}
        return part

    def solutions_by_joints(self, shown: str, value: Any) -> dict[int, list[Solution]]:
        """The entries of `value` (the batch of `simulation_dataset`) as (k, x_sol, j), by the
        joint count of mechanism j, each j checked to be an index of the batch; `x_sol` is
        checked by `check_solutions`, in the part of the batch that holds j."""
        grouped: dict[int, list[Solution]] = {}
        for k, (x_sol, j) in enumerate(_entries(value, f"{shown} batch {self.batch}", 2)):
            j = _index(j, f"{shown} batch {self.batch} index {k}", self.size)
            grouped.setdefault(int(self.n_joints[j]), []).append((k, x_sol, j))
        return grouped

    def check_solutions(self, shown: str, solutions: list[Solution]) -> None:
        """Check each mechanism the release simulated against its trajectory, given as
        `solutions_by_joints` gives them (from the file `shown`), keeping only the verdicts: a
        batch's trajectories are its largest part, and are dropped with `solutions`."""
        for k, x_sol, j in solutions:
            where = f"{shown} batch {self.batch} index {k}"
            n = int(self.n_joints[j])
            _floats(x_sol, where, "x_sol", (n, RELEASE_STEPS, 2))
            self._check(j, x_sol)

    def verdict(self, j: int) -> tuple[str, float]:
        """Mechanism `j`'s check (VERDICTS) and error; one the release has no trajectory of is
        checked only for locking at the release's angles."""
        if j not in self.checks:
            self._check(j, None)
        return self.checks[j]

    def _check(self, j: int, solution: np.ndarray | None) -> None:
        self.checks[j] = release_check(self.topology(j), self.x0[j].astype(np.float64), solution)

    def add_curated(self, shown: str, value: Any) -> None:
        """Keep the release's curated (j, node) pairs of this batch from `value` (the batch of
        `curated_dataset`), each checked to name a joint of one of its mechanisms."""
        self.curated = set()
        for k, (curve, j, node) in enumerate(_entries(value, f"{shown} batch {self.batch}", 3)):
            where = f"{shown} batch {self.batch} index {k}"
            _floats(curve, where, "curve", (RELEASE_STEPS, 2))
            j = _index(j, where, self.size)
            if isinstance(node, bool) or not isinstance(node, int | np.integer):
                raise ReleaseFileError(f"{where}: node must be an int, got {_shown_number(node)}")
            if not 0 <= node < self.n_joints[j]:
                raise ReleaseFileError(
                    f"{where}: node {node} is not a joint of mechanism {j} "
                    f"({self.n_joints[j]} joints)"
                )
            self.curated.add((j, int(node)))


def node_types_of(fixed: np.ndarray) -> np.ndarray:
    """links-ray's node types (int8) of a release `node_type` (True for fixed): FIXED for
    fixed joints, ACTUATED for joint 1 (the crank's tip), SIMPLE for the others."""
    types = np.where(fixed, FIXED, SIMPLE).astype(np.int8)
    if not fixed[1]:
        types[1] = ACTUATED
    return types


def release_check(
    topology: Topology, positions: np.ndarray, solution: np.ndarray | None
) -> tuple[str, float]:
    """("agree" | "disagree" | "locks" | "unchecked", error): links-ray's solver at the
    release's angles against the release's own trajectory `solution` (any of FLOAT_DTYPES),
    within AGREEMENT_TOLERANCE, or a few of float16's roundings for a float16 one."""
    out, (step, _) = release_turn(topology, positions)
    if step >= 0:
        return "locks", 0.0
    if solution is None:
        return "unchecked", 0.0
    size = max(float(np.ptp(positions, axis=0).max()), 1e-12)
    error = float(np.abs(out - solution.astype(np.float64)).max()) / size
    if not np.isfinite(error):
        error = float("inf")
    # float16 rounds at about 1e-3, past the tolerance: its own rounding is no disagreement.
    tolerance = max(AGREEMENT_TOLERANCE, 4.0 * float(np.finfo(solution.dtype).eps))
    return ("agree" if error <= tolerance else "disagree"), error
