"""Export of a root as the LINKS release's own pickled files (docs/guides/exports.md):
`dataset`, `simulation_dataset`, `normalized_dataset` and `curated_dataset`, batch by batch,
as code written for the release reads them (`export_release_files`).

Mechanisms are read shard by shard in mechanism_id order and simulated again at the release's
angles (`release.format`); curves are normalized and classified by the release's rules, and the
curated set is the root's, or curation's seeded choice on the release's classification.

Pure numpy/pyarrow: no Ray.
"""

from __future__ import annotations

import os
import pickle
from collections import deque
from collections.abc import Iterator, Sequence
from contextlib import ExitStack
from dataclasses import dataclass

import numpy as np
import pyarrow as pa

from links_ray.data.curation import by_mechanism_id, curated_mask, list_values, path_ids
from links_ray.data.splits import split_mask
from links_ray.data.store import META, Store
from links_ray.engine.kinematics.mechanism import FIXED
from links_ray.release.export_source import open_export
from links_ray.release.format import (
    RELEASE_FILES,
    release_arcs,
    release_circles,
    release_normalize_many,
    release_trajectories_many,
)

#: Mechanisms per batch of the release's files by default: the release's own batch.
DEFAULT_RELEASE_BATCH = 100_000
#: Protocol 4 pickles numpy arrays by `_reconstruct` (as the release's files hold them);
#: protocol 5 would name `_frombuffer` instead.
RELEASE_PICKLE_PROTOCOL = 4
#: Curves normalized at once by the release export (float64 scratch of about 30 KB a curve).
NORMALIZE_BLOCK = 8192


def export_release_files(
    root: str | Store,
    out: str,
    chunk_size: int = DEFAULT_RELEASE_BATCH,
    split: str | None = None,
    split_fractions: Sequence[float] | None = None,
    batches: int | None = None,
) -> dict:
    """Write the committed mechanisms at `root` into the local folder `out` (new or empty) as
    the release's four files, `RELEASE_FILES`, that code written for the release reads with
    `pickle.load` until EOFError (only the first `batches` batches, if given); returns a
    summary (mechanisms, locked, curves, batches).

    Each file holds one pickled list a batch: up to `chunk_size` mechanisms in mechanism_id
    order, joint counts mixed. Per mechanism (j its index in the batch):
    `dataset` `[A (n, n) bool, x0 (n, 2) float32, node_type (n,) bool, True for fixed]`, the
    root's adjacency, positions and node types in links-ray's joint order (joint 0 fixed,
    joint 1 the crank's tip, as the release has them); `simulation_dataset` `[x_sol
    (n, 200, 2) float32, j]`, x0 simulated at the release's angles (`release.format`);
    `normalized_dataset` `[curve (200, 2) float32, j, node]` for every moving joint, x_sol's
    path normalized by `release_normalize_many`; `curated_dataset` the same for the curated
    joints: the root's `curated` table where curation wrote one, else links-ray's seeded
    choice (`pathset.curated_mask`, the recorded seed or 0) on the release's classification
    (`release_arcs` first, `release_circles` for the others). Only lists, Python ints and
    numpy arrays are pickled (protocol 4), so a reader allowing numpy arrays and lists only
    reads them.

    A mechanism that locks at the release's angles keeps its `dataset` entry and gets no
    other, as in the release. links-ray's mechanisms turn fully at links-ray's own 200 steps;
    the release's angles are the same full turn at other points, so one locks only if it
    nearly locks between links-ray's steps (or from x0's float32 rounding): never in practice.
    The summary counts them.

    Memory: the batch being written (its simulations and normalized curves, 1.6 KB a joint
    each, and while a file's list is pickled a copy of its arrays: about 60 KB a 13-joint
    mechanism) and the mechanisms of the shards it draws from (one a joint count in generated
    roots).
    """
    store, generated, curated, fractions = open_export(
        root, out, chunk_size, split, split_fractions
    )
    seed = int((store.read_json(f"{META}/curation.json") or {}).get("seed", 0))
    os.makedirs(out, exist_ok=True)
    partial = {name: os.path.join(out, f".{name}.partial") for name in RELEASE_FILES}
    summary = {
        "format": "release",
        "source": store.uri,
        "chunk_size": int(chunk_size),
        "split": split,
        "curation_seed": seed,
        "mechanisms": 0,
        "locked": 0,
        "normalized": 0,
        "curated": 0,
        "seeded_shards": 0,
        "batches": [],
    }
    with ExitStack() as files:
        streams = {name: files.enter_context(open(path, "wb")) for name, path in partial.items()}
        runs = _runs_in_id_order(store, generated, curated, split, fractions, summary)
        for batch in _batches(runs, chunk_size):
            entry = _write_release_batch(streams, batch, seed)
            summary["batches"].append(entry)
            for key in ("mechanisms", "locked", "normalized", "curated"):
                summary[key] += entry[key]
            if batches is not None and len(summary["batches"]) >= batches:
                break
    # Named last: a folder holding the four names holds a finished export.
    for name, path in partial.items():
        os.replace(path, os.path.join(out, name))
    return summary


@dataclass(eq=False)
class _ShardRows:
    """One shard's mechanisms in mechanism_id order, and its curated joints (None: choose)."""

    mechanism_id: np.ndarray  # (k,) int64
    adjacency: np.ndarray  # (k, n, n) uint8
    node_types: np.ndarray  # (k, n) int8
    positions: np.ndarray  # (k, n, 2) float64
    curated: np.ndarray | None  # (k, n) bool
    cursor: int = 0

    @property
    def next_id(self) -> int:
        return int(self.mechanism_id[self.cursor])


def _shard_rows(
    store: Store,
    marker: dict,
    curation: dict | None,
    split: str | None,
    fractions: Sequence[float],
) -> _ShardRows:
    n = int(marker["n_joints"])
    mechanisms = by_mechanism_id(store.read_parquet(marker["files"]["mechanisms"]))
    if split is not None:
        mechanisms = mechanisms.filter(pa.array(split_mask(mechanisms, split, fractions)))
    ids = mechanisms.column("mechanism_id").to_numpy()
    kept = None
    curation_files = (curation or {}).get("files", {})
    if "curated" in curation_files:
        rows = store.read_parquet(curation_files["curated"], ["mechanism_id", "joint"])
        mechanism_ids = rows.column("mechanism_id").to_numpy()
        joints = rows.column("joint").to_numpy().astype(np.int64)
        mine = np.isin(mechanism_ids, ids)
        kept = np.zeros((len(ids), n), dtype=bool)
        kept[np.searchsorted(ids, mechanism_ids[mine]), joints[mine]] = True
    return _ShardRows(
        mechanism_id=ids,
        adjacency=list_values(mechanisms.column("adjacency"), n * n).reshape(-1, n, n),
        node_types=list_values(mechanisms.column("node_types"), n),
        positions=list_values(mechanisms.column("positions"), 2 * n).reshape(-1, n, 2),
        curated=kept,
    )


def _runs_in_id_order(
    store: Store,
    generated: dict[int, dict],
    curated: dict[int, dict],
    split: str | None,
    fractions: Sequence[float],
    summary: dict,
) -> Iterator[tuple[_ShardRows, int, int]]:
    """(shard rows, start, stop): runs of consecutive mechanisms of one shard that together
    are every mechanism in mechanism_id order. A shard is read when the order reaches its
    least id and let go when its last row is taken, so only shards whose ids interleave are
    held at once (one a joint count in generated roots)."""
    starts = []
    for marker in generated.values():
        ids = store.read_parquet(marker["files"]["mechanisms"], ["mechanism_id"]).column(0)
        if len(ids):
            starts.append((int(ids.to_numpy().min()), marker["shard"], marker))
    pending = deque(sorted(starts, key=lambda start: start[:2]))
    held: list[_ShardRows] = []
    while pending or held:
        while pending and (not held or pending[0][0] <= min(r.next_id for r in held)):
            _, shard, marker = pending.popleft()
            rows = _shard_rows(store, marker, curated.get(shard), split, fractions)
            summary["seeded_shards"] += rows.curated is None and len(rows.mechanism_id) > 0
            if len(rows.mechanism_id):
                held.append(rows)
        if not held:
            continue
        first = min(held, key=lambda r: r.next_id)
        bounds = [r.next_id for r in held if r is not first]
        if pending:
            bounds.append(pending[0][0])
        stop = len(first.mechanism_id)
        if bounds:
            stop = int(np.searchsorted(first.mechanism_id, min(bounds), side="left"))
        stop = max(stop, first.cursor + 1)
        yield first, first.cursor, stop
        first.cursor = stop
        if first.cursor == len(first.mechanism_id):
            held.remove(first)


def _batches(
    runs: Iterator[tuple[_ShardRows, int, int]], size: int
) -> Iterator[list[tuple[_ShardRows, int, int]]]:
    """The runs regrouped into batches of `size` mechanisms (the last may hold fewer)."""
    batch: list[tuple[_ShardRows, int, int]] = []
    held = 0
    for rows, start, stop in runs:
        while start < stop:
            take = min(stop - start, size - held)
            batch.append((rows, start, start + take))
            held += take
            start += take
            if held == size:
                yield batch
                batch, held = [], 0
    if batch:
        yield batch


def _write_release_batch(
    streams: dict, batch: list[tuple[_ShardRows, int, int]], seed: int
) -> dict:
    """Pickle one batch into each of the four files; returns its counts."""
    dataset: list = []
    simulations: list = []
    waiting: list[np.ndarray] = []  # moving joints' trajectories not yet normalized
    blocks: list[np.ndarray] = []  # normalized curves, a block of runs at a time
    owners: list[np.ndarray] = []  # per run: each curve's mechanism index in the batch
    nodes: list[np.ndarray] = []
    arcs: list[np.ndarray] = []
    ids_of: list[np.ndarray] = []
    chosen: list[np.ndarray | None] = []  # per run: the root's curated flags, or None
    locked = 0

    def normalize_waiting() -> None:
        # Normalized from x_sol as the file holds it, so that a reader normalizing it gets it;
        # some runs at a time, so that no copy of the batch's curves is held.
        if waiting:
            block = np.concatenate(waiting)
            waiting.clear()
            blocks.append(release_normalize_many(block).astype(np.float32))

    for rows, start, stop in batch:
        run = slice(start, stop)
        fixed = rows.node_types[run] == FIXED
        adjacency = rows.adjacency[run].astype(bool)
        # Simulated from the positions as the file holds them, so that a reader simulating x0
        # gets x_sol.
        x0 = rows.positions[run].astype(np.float32)
        trajectories, locks = release_trajectories_many(
            rows.adjacency[run], rows.node_types[run], x0
        )
        # A locked mechanism's turn past its lock is meaningless (and may overflow float32);
        # the file holds none of it.
        trajectories[locks >= 0] = 0.0
        x_sol = trajectories.astype(np.float32)
        del trajectories
        base = len(dataset)
        for k in range(stop - start):
            dataset.append([adjacency[k], x0[k], fixed[k]])
            if locks[k] < 0:
                simulations.append([x_sol[k], base + k])
        locked += int(np.count_nonzero(locks >= 0))
        moving, joints = np.nonzero(~fixed & (locks < 0)[:, None])
        waiting.append(x_sol[moving, joints])
        if sum(map(len, waiting)) >= NORMALIZE_BLOCK:
            normalize_waiting()
        owners.append(base + moving)
        nodes.append(joints)
        arcs.append(release_arcs(adjacency, fixed)[moving, joints])
        ids_of.append(rows.mechanism_id[run][moving])
        chosen.append(None if rows.curated is None else rows.curated[run][moving, joints])
    normalize_waiting()

    owner, node, is_arc = (np.concatenate(part) for part in (owners, nodes, arcs))
    curves = [curve for block in blocks for curve in block]
    is_circle = np.empty(len(curves), dtype=bool)
    done = 0
    for block in blocks:
        is_circle[done : done + len(block)] = release_circles(
            block, is_arc[done : done + len(block)]
        )
        done += len(block)
    keep = np.concatenate(
        [
            np.zeros(len(part), dtype=bool) if flags is None else flags
            for part, flags in zip(nodes, chosen, strict=True)
        ]
    )
    seeded = np.concatenate(
        [np.full(len(part), flags is None) for part, flags in zip(nodes, chosen, strict=True)]
    )
    if seeded.any():
        choice = pa.table(
            {
                "path_id": path_ids(np.concatenate(ids_of)[seeded], node[seeded]),
                "is_arc": is_arc[seeded],
                "is_circle": is_circle[seeded],
            }
        )
        keep[seeded] = curated_mask(choice, seed)

    normalized = [[curves[p], int(owner[p]), int(node[p])] for p in range(len(curves))]
    curated = [normalized[p] for p in np.flatnonzero(keep)]
    lists = (dataset, simulations, normalized, curated)
    counts = [len(values) for values in lists]
    for name, values in zip(RELEASE_FILES, lists, strict=True):
        pickler = pickle.Pickler(streams[name], protocol=RELEASE_PICKLE_PROTOCOL)
        # No memo: it would hold a copy of every array's bytes until the whole list is written
        # (2.2 GB more for a batch's simulations), where the pickler otherwise streams it.
        # Nothing in these lists is referenced twice, so a reader sees the same objects.
        pickler.fast = True
        pickler.dump(values)
        # Let each file's arrays go once written (the simulations are the largest).
        values.clear()
    first_rows, _, _ = batch[0]
    last_rows, _, last_stop = batch[-1]
    return {
        "mechanisms": counts[0],
        "locked": locked,
        "normalized": counts[2],
        "curated": counts[3],
        "first_mechanism_id": int(first_rows.mechanism_id[batch[0][1]]),
        "last_mechanism_id": int(last_rows.mechanism_id[last_stop - 1]),
    }
