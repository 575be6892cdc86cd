"""Import of the LINKS release's own files into a links-ray root
(docs/guides/importing-the-release.md).

The release's files are read with the restricted unpickler of `release.pickles`, one batch at
a time, and one file's batch at a time: a batch's mechanisms stay in memory while its
simulations are checked and dropped, then its curated (j, node) pairs are read. Each batch is
split by joint count into shards committed by the commit protocol (`data.commit`) under the
root's writer lease, so an interrupted import resumes where it stopped and every shard is
committed exactly once:

    shard_id = SHARDS_PER_BATCH * release_batch + n_joints
    mechanism_id = BATCH_STRIDE * release_batch + release_index
    topology_id = mechanism_id // 5, variant = mechanism_id % 5   (the release's groups of 5)
    a negative's id = NEGATIVE_ID_BASE + mechanism_id

so `release_location(mechanism_id)` is the row's (release_batch, release_index). Joints keep
their release order; node types map to links-ray's: True (fixed) to FIXED (0), joint 1 to
ACTUATED (2), any other joint to SIMPLE (1). Positions are the release's float32 values as
float64, exactly.

Every mechanism is checked with links-ray's own validators and solver: at the release's angles
(`release.format.release_trajectories`' solver), compared with the release's own trajectories
where it has them; and over links-ray's own turn (DEFAULT_STEPS steps from the initial angle),
where one that locks goes to `negatives`. `paths` are links-ray's curation of the rest
(`pathset.trajectory_paths`); `curated` are the paths the release curated when it has
`curated_dataset`, else curation's seeded choice (`pathset.curated_mask`).

Pure numpy/pyarrow: no Ray.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pyarrow as pa

from links_ray.data.commit import ShardWriter, committed_shards, remove_uncommitted
from links_ray.data.lease import Lease
from links_ray.data.pathset import (
    KEEP_SHARE,
    MECHANISMS_PER_BATCH,
    arc_circle_counts,
    curated_mask,
    path_ids,
    path_shares,
    trajectory_paths,
)
from links_ray.data.schemas import SCHEMAS, TRAJECTORY_DTYPE, list_array
from links_ray.data.shards import NEGATIVE_ID_BASE, VARIANTS
from links_ray.data.store import IMPORTED_SOURCE, META, Store
from links_ray.engine.inputs import (
    ACTUATED,
    DEFAULT_STEPS,
    FIXED,
    SIMPLE,
    InvalidMechanismError,
    as_positions,
    check_positions,
)
from links_ray.engine.mechanism import MAX_DATASET_JOINTS, Topology, analyze_topology
from links_ray.engine.solver import TopologySimulator
from links_ray.engine.transmission import mechanism_transmission_deg
from links_ray.release.format import RELEASE_STEPS, release_turn
from links_ray.release.pickles import ReleaseFileError, read_batches, release_files

__all__ = ["BATCH_STRIDE", "import_release", "release_location"]

#: Ids a release batch spans: a multiple of 5, so a batch's groups of five stay topologies.
BATCH_STRIDE = VARIANTS * (1 << 22)
#: Shard ids a release batch spans: one per joint count.
SHARDS_PER_BATCH = 32
#: A joint's largest distance from the release's own trajectory, relative to the mechanism's
#: size (the largest coordinate difference of its x0), below which the two agree: the
#: release's float32 rounding is some 1e-7 of it.
AGREEMENT_TOLERANCE = 1e-4
#: Disagreeing mechanisms named in the import summary (every shard's marker names all of its).
SHOWN_DISAGREEING = 100
IMPORT_FORMAT = 1
#: A mechanism's check against the release (`_release_check`), and the summary's count of each.
VERDICT_STATS = {
    "agree": "agreeing",
    "disagree": "disagreeing",
    "locks": "locking_at_release_angles",
    "unchecked": "unchecked",
}
VERDICTS = tuple(VERDICT_STATS)
#: Called with "batch <b> committed" after each release batch's shards are all committed:
#: the fault tests' way to stop an import between batches.
Failpoint = Callable[[str], None]


def release_location(mechanism_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(release_batch, release_index) of imported mechanism ids, valid or negative."""
    ids = np.asarray(mechanism_ids, dtype=np.int64)
    ids = np.where(ids >= NEGATIVE_ID_BASE, ids - NEGATIVE_ID_BASE, ids)
    return ids // BATCH_STRIDE, ids % BATCH_STRIDE


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


class _Batch:
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
        self.adjacency: list[np.ndarray] = []
        self.fixed: list[np.ndarray] = []
        self.x0: list[np.ndarray] = []
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
        #: Each mechanism's check against the release (an index of VERDICTS, -1 until checked)
        #: and its error there.
        self.verdicts = np.full(self.size, -1, dtype=np.int8)
        self.errors = np.zeros(self.size)
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

    def check_solutions(self, shown: str, value: Any) -> None:
        """Check every mechanism the release simulated against its trajectory in `value` (the
        batch of `simulation_dataset`), keeping only the verdicts: a batch's trajectories are
        its largest part, and are dropped with `value`."""
        for k, (x_sol, j) in enumerate(_entries(value, f"{shown} batch {self.batch}", 2)):
            where = f"{shown} batch {self.batch} index {k}"
            j = _index(j, where, self.size)
            n = int(self.n_joints[j])
            _array(x_sol, where, "x_sol", (n, RELEASE_STEPS, 2), np.float32)
            self._check(j, x_sol)

    def verdict(self, j: int) -> tuple[str, float]:
        """Mechanism `j`'s check (VERDICTS) and error; one the release has no trajectory of is
        checked only for locking at the release's angles."""
        if self.verdicts[j] < 0:
            self._check(j, None)
        return VERDICTS[self.verdicts[j]], float(self.errors[j])

    def _check(self, j: int, solution: np.ndarray | None) -> None:
        verdict, error = _release_check(self.topology(j), self.x0[j].astype(np.float64), solution)
        self.verdicts[j] = VERDICTS.index(verdict)
        self.errors[j] = error

    def add_curated(self, shown: str, value: Any) -> None:
        self.curated = set()
        for k, (curve, j, node) in enumerate(_entries(value, f"{shown} batch {self.batch}", 3)):
            where = f"{shown} batch {self.batch} index {k}"
            _array(curve, where, "curve", (RELEASE_STEPS, 2), np.float32)
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


def _rows(table: str, columns: dict[str, np.ndarray]) -> pa.RecordBatch:
    arrays = []
    for field in SCHEMAS[table]:
        values = columns[field.name]
        if pa.types.is_list(field.type):
            arrays.append(list_array(values.reshape(len(values), -1), field.type.value_type))
        else:
            arrays.append(pa.array(values, type=field.type))
    return pa.RecordBatch.from_arrays(arrays, schema=SCHEMAS[table])


def _release_check(
    topology: Topology, positions: np.ndarray, solution: np.ndarray | None
) -> tuple[str, float]:
    """("agree" | "disagree" | "locks" | "unchecked", error): links-ray's solver at the
    release's angles against the release's own trajectory."""
    out, (step, _) = release_turn(topology, positions)
    if step >= 0:
        return "locks", 0.0
    if solution is None:
        return "unchecked", 0.0
    size = max(float(np.ptp(positions, axis=0).max()), 1e-12)
    error = float(np.abs(out - solution).max()) / size
    if not np.isfinite(error):
        error = float("inf")
    return ("agree" if error <= AGREEMENT_TOLERANCE else "disagree"), error


def _group_rows(
    batch: _Batch,
    shown: str,
    indices: np.ndarray,
    n: int,
    seed: int,
    write: Callable[[str, pa.RecordBatch], None],
) -> tuple[dict, dict]:
    """Hand the rows of one joint count of a batch to `write(table, record_batch)`
    (`mechanisms`, `negatives`, `paths`, `curated`), MECHANISMS_PER_BATCH mechanisms at a time;
    returns the generation stats and the curation stats."""
    start = time.perf_counter()
    stats: dict[str, Any] = {
        "release_batch": batch.batch,
        "mechanisms": 0,
        "negatives": 0,
        "topologies": 0,
        "agreeing": 0,
        "disagreeing": 0,
        "locking_at_release_angles": 0,
        "unchecked": 0,
        "worst_error": 0.0,
        "disagreeing_ids": [],
    }
    curation = {
        "mechanisms": 0,
        "resimulated": 0,
        "paths": 0,
        "curated": 0,
        "arcs": 0,
        "circles": 0,
        "both": 0,
        "release_curated_unmatched": 0,
    }
    ids_all = BATCH_STRIDE * batch.batch + indices
    stats["topologies"] = len(np.unique(ids_all // VARIANTS))
    released_curated = None
    if batch.curated is not None:
        wanted = [(j, node) for j, node in batch.curated if batch.n_joints[j] == n]
        released_curated = path_ids(
            BATCH_STRIDE * batch.batch + np.array([j for j, _ in wanted], dtype=np.int64),
            np.array([node for _, node in wanted], dtype=np.int64),
        )
        matched = 0
    for lo in range(0, len(indices), MECHANISMS_PER_BATCH):
        part = indices[lo : lo + MECHANISMS_PER_BATCH]
        ids = ids_all[lo : lo + MECHANISMS_PER_BATCH]
        adjacency = np.stack([batch.adjacency[j] for j in part]).astype(np.uint8)
        node_types = np.stack([node_types_of(batch.fixed[j]) for j in part])
        positions = np.stack([batch.x0[j] for j in part]).astype(np.float64)
        trajectories = np.empty((len(part), n, DEFAULT_STEPS, 2), dtype=TRAJECTORY_DTYPE)
        lock_step = np.empty(len(part), dtype=np.int64)
        lock_node = np.empty(len(part), dtype=np.int64)
        min_deg = np.empty(len(part), dtype=np.float32)
        changes = np.any(adjacency[1:] != adjacency[:-1], axis=(1, 2))
        changes |= np.any(node_types[1:] != node_types[:-1], axis=1)
        starts = [0, *(np.flatnonzero(changes) + 1).tolist(), len(part)]
        for first, stop in itertools.pairwise(starts):
            where = f"{shown} batch {batch.batch} index {int(part[first])}"
            topology = batch.topology(int(part[first]))
            try:
                group = as_positions(positions[first:stop], n, batch=True)
                check_positions(topology.adjacency, group, topology.links)
            except InvalidMechanismError as exc:
                raise ReleaseFileError(f"{where}: {exc}") from None
            for k in range(first, stop):
                verdict, error = batch.verdict(int(part[k]))
                stats[VERDICT_STATS[verdict]] += 1
                if verdict in ("agree", "disagree"):
                    stats["worst_error"] = max(stats["worst_error"], error)
                if verdict == "disagree":
                    stats["disagreeing_ids"].append(int(ids[k]))
            simulator = TopologySimulator.from_topology(topology)
            turned, steps_locked, nodes_locked = simulator.run(positions[first:stop], DEFAULT_STEPS)
            trajectories[first:stop] = turned.astype(TRAJECTORY_DTYPE)
            lock_step[first:stop] = steps_locked
            lock_node[first:stop] = nodes_locked
            valid = steps_locked < 0
            min_deg[first:stop] = 0.0
            if valid.any():
                min_deg[first:stop][valid] = mechanism_transmission_deg(
                    topology.order, trajectories[first:stop][valid]
                )
        valid = lock_step < 0
        shared = {
            "topology_id": ids // VARIANTS,
            "variant": (ids % VARIANTS).astype(np.int8),
            "adjacency": adjacency.reshape(len(part), -1),
            "node_types": node_types,
            "positions": positions.reshape(len(part), -1),
        }
        if valid.any():
            chosen = {key: value[valid] for key, value in shared.items()}
            mechanisms = _rows(
                "mechanisms",
                {"mechanism_id": ids[valid], "min_transmission_deg": min_deg[valid], **chosen},
            )
            write("mechanisms", mechanisms)
            paths = trajectory_paths(pa.Table.from_batches([mechanisms]), trajectories[valid], n)
            if released_curated is None:
                keep = curated_mask(paths, seed)
            else:
                keep = np.isin(paths.column("path_id").to_numpy(), released_curated)
                matched += int(keep.sum())
            curated = paths.filter(keep)
            for table, rows in (("paths", paths), ("curated", curated)):
                for record_batch in rows.to_batches():
                    write(table, record_batch)
            curation["mechanisms"] += int(valid.sum())
            curation["paths"] += len(paths)
            curation["curated"] += len(curated)
            for key, count in arc_circle_counts(paths).items():
                curation[key] += count
        if not valid.all():
            locked = ~valid
            chosen = {key: value[locked] for key, value in shared.items()}
            write(
                "negatives",
                _rows(
                    "negatives",
                    {
                        "mechanism_id": NEGATIVE_ID_BASE + ids[locked],
                        "locked_step": lock_step[locked].astype(np.int16),
                        "locked_node": lock_node[locked].astype(np.int16),
                        **chosen,
                    },
                ),
            )
        stats["mechanisms"] += int(valid.sum())
        stats["negatives"] += int((~valid).sum())
    if released_curated is not None:
        curation["release_curated_unmatched"] = len(released_curated) - matched
    seconds = time.perf_counter() - start
    stats["seconds"] = seconds
    curation["seconds"] = 0.0  # the group's time is counted once, in the generation stats
    return stats, curation


def _import_shard(
    store: Store,
    batch: _Batch,
    shown: str,
    n: int,
    seed: int,
    shard_id: int,
    generated: dict[int, dict],
    fence: Callable[[], None],
) -> dict:
    """Import the mechanisms of `n` joints of `batch` as shard `shard_id`: its generation
    shard (unless `generated` holds it already), then its curation shard; returns the
    curation marker, after recording the generation marker in `generated`."""
    writers = {"curation": ShardWriter(store, shard_id, n, stage="curation")}
    if shard_id not in generated:
        writers["shards"] = ShardWriter(store, shard_id, n, stage="shards")

    def write(table: str, record_batch: pa.RecordBatch) -> None:
        stage = "curation" if table in ("paths", "curated") else "shards"
        if stage in writers and record_batch.num_rows:
            writers[stage].write(table, record_batch)

    try:
        indices = np.flatnonzero(batch.n_joints == n).astype(np.int64)
        stats, curation = _group_rows(batch, shown, indices, n, seed, write)
        if "shards" in writers:
            fence()
            generated[shard_id] = writers["shards"].commit(stats)
        fence()
        return writers["curation"].commit(curation)
    except BaseException:
        for writer in writers.values():
            writer.abort()
        raise


def _following(store: Store, relative: str | None) -> Iterator[tuple[int, int, Any]] | None:
    return None if relative is None else read_batches(store, relative)


def _next_batch(batches: Iterator[tuple[int, int, Any]], shown: str, batch: int) -> Any:
    found = next(batches, None)
    if found is None:
        raise ReleaseFileError(f"{shown} ends before batch {batch}, which dataset holds")
    return found[2]


def import_release(
    src: str,
    out: str,
    seed: int = 0,
    failpoint: Failpoint | None = None,
) -> dict:
    """Import the LINKS release's files at `src` (a folder or s3://) into the root `out`;
    returns the import summary (also saved as `_links/import_summary.json`).

    `seed` draws the curated set when the release has no `curated_dataset`. Resumable: the
    shards an earlier import of the same release committed are kept. Raises ValueError
    (ReleaseFileError, StoreError) in one line for a file that cannot be read as the release
    writes it; the batches before the one at fault are committed.
    """
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    source = Store.open(src, writable=False)
    files = release_files(source)
    data_file = files["dataset"]
    if data_file is None:  # release_files refuses a folder without one
        raise ReleaseFileError(f"{source.uri} holds no release dataset")
    sims_file = files["simulation_dataset"]
    curated_file = files["curated_dataset"]
    curated_from = "release" if curated_file is not None else "seed"
    store = Store.open(out)
    start = time.perf_counter()
    with Lease.acquire(store, "writer", "links import-release") as lease:
        store.claim(
            f"{META}/run.json",
            {
                "source": IMPORTED_SOURCE,
                "release": source.uri,
                "format": IMPORT_FORMAT,
                "steps": DEFAULT_STEPS,
                "tables": ["mechanisms", "negatives"],
            },
        )
        store.claim(
            f"{META}/curation.json",
            {
                "seed": seed,
                "keep_share": KEEP_SHARE,
                "tables": ["paths", "curated"],
                "curated_from": curated_from,
            },
        )
        generated = committed_shards(store, "shards")
        curated = committed_shards(store, "curation")
        remove_uncommitted(store, "shards", generated)
        remove_uncommitted(store, "curation", curated)

        def fence() -> None:
            lease.confirm()

        sims = _following(source, sims_file)
        chosen = _following(source, curated_file)
        shown = f"{source.uri}/{data_file}"
        imported_now = 0  # valid mechanisms whose shards this run committed
        for number, _, value in read_batches(source, data_file):
            batch = _Batch(shown, number, value)
            del value
            shards = [
                (n, SHARDS_PER_BATCH * number + n) for n in np.unique(batch.n_joints).tolist()
            ]
            pending = [(n, i) for n, i in shards if i not in generated or i not in curated]
            # One file's batch in memory at a time: each is reduced to what the import keeps
            # (verdicts, curated pairs) before the next is read. A batch an earlier run
            # committed is read only to reach the next.
            if sims is not None:
                solutions = _next_batch(sims, f"{source.uri}/{sims_file}", number)
                if pending:
                    batch.check_solutions(f"{source.uri}/{sims_file}", solutions)
                del solutions
            if chosen is not None:
                batch.add_curated(
                    f"{source.uri}/{curated_file}",
                    _next_batch(chosen, f"{source.uri}/{curated_file}", number),
                )
            for n, shard_id in pending:
                curated[shard_id] = _import_shard(
                    store, batch, shown, n, seed, shard_id, generated, fence
                )
                imported_now += curated[shard_id]["stats"]["mechanisms"]
            del batch
            if failpoint is not None:
                failpoint(f"batch {number} committed")
        lease.confirm()
        remove_uncommitted(store, "shards", generated)
        remove_uncommitted(store, "curation", curated)
        seconds = time.perf_counter() - start
        summary = summarize_import(store, source.uri, curated_from, seconds, imported_now)
        store.write_json(f"{META}/import_summary.json", summary)
        store.write_json(
            f"{META}/curation_summary.json",
            {
                "out": store.uri,
                "tables": ["paths", "curated"],
                "shards": summary["shards"],
                "seconds": summary["seconds"],
                "mechanisms_per_core_second": summary["mechanisms_per_second"],  # one process
                **{key: summary[key] for key in ("paths", "curated", "arcs", "circles", "both")},
                "shares": path_shares(
                    summary["paths"], summary["arcs"], summary["circles"], summary["both"]
                ),
            },
        )
    return summary


def summarize_import(
    store: Store, release: str, curated_from: str, seconds: float, imported_now: int
) -> dict:
    """The import summary, from the committed shards' markers: rows, the check against the
    release's trajectories, negatives, paths, and where the curated set came from; `seconds`
    and `mechanisms_per_second` are this run's, over the `imported_now` valid mechanisms it
    committed."""
    generated = committed_shards(store, "shards")
    curated = committed_shards(store, "curation")
    counts = (
        "mechanisms",
        "negatives",
        "topologies",
        "agreeing",
        "disagreeing",
        "locking_at_release_angles",
        "unchecked",
    )
    totals = {key: sum(m["stats"].get(key, 0) for m in generated.values()) for key in counts}
    path_counts = ("paths", "curated", "arcs", "circles", "both", "release_curated_unmatched")
    paths = {key: sum(m["stats"].get(key, 0) for m in curated.values()) for key in path_counts}
    disagreeing = sorted(i for m in generated.values() for i in m["stats"]["disagreeing_ids"])
    batches = {m["stats"]["release_batch"] for m in generated.values()}
    imported = totals["mechanisms"] + totals["negatives"]
    return {
        "out": store.uri,
        "release": release,
        "release_batches": len(batches),
        "shards": len(generated),
        **totals,
        "imported": imported,
        "worst_error": max((m["stats"]["worst_error"] for m in generated.values()), default=0.0),
        "agreement_tolerance": AGREEMENT_TOLERANCE,
        "disagreeing_ids": disagreeing[:SHOWN_DISAGREEING],
        **paths,
        "curated_from": curated_from,
        "seconds": seconds,
        "imported_this_run": imported_now,
        "mechanisms_per_second": imported_now / seconds if imported_now and seconds else None,
    }
