"""Export to the LINKS release layout (docs/guides/exports.md): numpy arrays chunk by chunk
(`format="numpy"`, below), or the release's own pickled files (`format="release"`, see
`export_release_files`).

Like the original release, each chunk holds mechanisms (adjacency, initial positions, node
types), their simulations, every moving joint's normalized curve and the curated curves, each
curve with the index of its mechanism in the chunk and of its joint. A chunk here is up to
`chunk_size` mechanisms of one joint count, in mechanism_id order, so every array is dense
(no padding). Generation shards are read one at a time: memory holds a chunk and a shard.

Simulations come from the `simulations` table or are simulated again as curation does
(`pathset.simulated_trajectories`); normalized curves from `paths` or made from the
trajectories (`pathset.trajectory_paths`: the same rows bit for bit); curated curves from
`curated` or chosen from the normalized ones with the recorded curation seed
(`pathset.curated_mask`, seed 0 when the root was never curated, as `links curate` would).

Import, the other direction, is `links_ray.release.importer.import_release` (and
`release_location`, a row's way back to the release).

Pure numpy/pyarrow: no Ray.
"""

from __future__ import annotations

import json
import os
import pickle
from collections import deque
from collections.abc import Iterator, Sequence
from contextlib import ExitStack
from dataclasses import dataclass
from itertools import groupby

import numpy as np
import pyarrow as pa

from links_ray.data.commit import committed_shards
from links_ray.data.pathset import (
    MECHANISMS_PER_BATCH,
    by_mechanism_id,
    curated_mask,
    list_values,
    path_ids,
    simulated_trajectories,
    trajectory_paths,
)
from links_ray.data.splits import check_fractions, check_split, split_mask
from links_ray.data.store import META, Store
from links_ray.engine.inputs import DEFAULT_STEPS
from links_ray.engine.mechanism import FIXED
from links_ray.release.format import (
    RELEASE_FILES,
    release_arcs,
    release_circles,
    release_normalize_many,
    release_trajectories_many,
)

#: Mechanisms per chunk by default: a 20-joint chunk's simulations take 320 MB.
DEFAULT_CHUNK_MECHANISMS = 10_000
#: Mechanisms per batch of the release's files by default: the release's own batch.
DEFAULT_RELEASE_BATCH = 100_000
#: What `export_release` writes: numpy chunks, or the release's own pickled files.
EXPORT_FORMATS = ("numpy", "release")
#: Protocol 4 pickles numpy arrays by `_reconstruct` (as the release's files hold them);
#: protocol 5 would name `_frombuffer` instead.
RELEASE_PICKLE_PROTOCOL = 4
#: Curves normalized at once by the release export (float64 scratch of about 30 KB a curve).
NORMALIZE_BLOCK = 8192
RELEASE_FORMAT = "links-ray-release/1"
MANIFEST = "manifest.json"
#: The curve sets of a chunk, each with `<set>.npy` and its index arrays.
CURVE_SETS = ("normalized", "curated")
_CURVE_COLUMNS = ["path_id", "mechanism_id", "joint", "points", "is_arc", "is_circle"]


@dataclass
class _Curves:
    """Curves in path_id order (so in mechanism_id order too)."""

    path_id: np.ndarray  # (P,) int64
    mechanism_id: np.ndarray  # (P,) int64
    joint: np.ndarray  # (P,) int8
    points: np.ndarray  # (P, steps, 2) float32

    @classmethod
    def of(cls, rows: pa.Table, steps: int) -> _Curves:
        rows = rows.sort_by("path_id")
        return cls(
            path_id=rows.column("path_id").to_numpy(),
            mechanism_id=rows.column("mechanism_id").to_numpy(),
            joint=rows.column("joint").to_numpy().astype(np.int8),
            points=list_values(rows.column("points"), steps * 2).reshape(-1, steps, 2),
        )

    def select(self, rows: slice | np.ndarray) -> _Curves:
        return _Curves(
            self.path_id[rows], self.mechanism_id[rows], self.joint[rows], self.points[rows]
        )

    @classmethod
    def concat(cls, parts: Sequence[_Curves]) -> _Curves:
        return cls(*(np.concatenate([getattr(p, name) for p in parts]) for name in _CURVE_FIELDS))


_CURVE_FIELDS = ("path_id", "mechanism_id", "joint", "points")


@dataclass
class _Part:
    """Mechanisms of one joint count in mechanism_id order, with their simulations and curves."""

    mechanism_id: np.ndarray  # (M,) int64
    topology_id: np.ndarray  # (M,) int64
    adjacency: np.ndarray  # (M, n, n) uint8
    node_types: np.ndarray  # (M, n) int8
    positions: np.ndarray  # (M, n, 2) float64
    simulations: np.ndarray  # (M, n, steps, 2) float32
    curves: dict[str, _Curves]

    def __len__(self) -> int:
        return len(self.mechanism_id)

    def split_at(self, count: int) -> tuple[_Part, _Part]:
        """The first `count` mechanisms with their curves, and the rest with theirs."""
        last = self.mechanism_id[count - 1]
        cuts = {
            name: int(np.searchsorted(c.mechanism_id, last, side="right"))
            for name, c in self.curves.items()
        }
        head = _Part(
            *(getattr(self, field)[:count] for field in _MECHANISM_FIELDS),
            curves={name: c.select(slice(None, cuts[name])) for name, c in self.curves.items()},
        )
        tail = _Part(
            *(getattr(self, field)[count:] for field in _MECHANISM_FIELDS),
            curves={name: c.select(slice(cuts[name], None)) for name, c in self.curves.items()},
        )
        return head, tail

    @classmethod
    def concat(cls, parts: Sequence[_Part]) -> _Part:
        if len(parts) == 1:
            return parts[0]
        return cls(
            *(np.concatenate([getattr(p, name) for p in parts]) for name in _MECHANISM_FIELDS),
            curves={name: _Curves.concat([p.curves[name] for p in parts]) for name in CURVE_SETS},
        )


_MECHANISM_FIELDS = (
    "mechanism_id",
    "topology_id",
    "adjacency",
    "node_types",
    "positions",
    "simulations",
)


def export_release(
    root: str | Store,
    out: str,
    chunk_size: int | None = None,
    split: str | None = None,
    split_fractions: Sequence[float] | None = None,
    format: str = "numpy",
) -> dict:
    """Write the committed mechanisms at `root` (a folder, s3://bucket/prefix or a Store) into
    the local folder `out` (new or empty) in the LINKS release layout.

    `format="numpy"`: numpy chunks of one joint count each; returns the manifest it wrote as
    `out/manifest.json`. `format="release"`: the release's four pickled files
    (`export_release_files`); returns its summary. `chunk_size` mechanisms per chunk (batch)
    at most, by default DEFAULT_CHUNK_MECHANISMS for numpy and DEFAULT_RELEASE_BATCH for the
    release; `split` keeps one split's topologies (`links_ray.split_of`, `split_fractions` as
    there).
    """
    if format not in EXPORT_FORMATS:
        raise ValueError(f"format must be one of {', '.join(EXPORT_FORMATS)}, got {format!r}")
    if format == "release":
        return export_release_files(
            root,
            out,
            DEFAULT_RELEASE_BATCH if chunk_size is None else chunk_size,
            split,
            split_fractions,
        )
    chunk_size = DEFAULT_CHUNK_MECHANISMS if chunk_size is None else chunk_size
    store, generated, curated, fractions = _open_export(
        root, out, chunk_size, split, split_fractions
    )
    steps = int((store.read_json(f"{META}/run.json") or {}).get("steps", DEFAULT_STEPS))
    seed = int((store.read_json(f"{META}/curation.json") or {}).get("seed", 0))
    os.makedirs(out, exist_ok=True)

    chunks: list[dict] = []
    resimulated = 0
    by_size = groupby(
        sorted(generated.values(), key=lambda m: m["n_joints"]), lambda m: m["n_joints"]
    )
    for n_joints, markers in by_size:
        pending: list[_Part] = []
        held = 0
        for marker in markers:  # shard order is mechanism_id order within a joint count
            part, made = _shard_part(
                store, marker, curated.get(marker["shard"]), steps, seed, split, fractions
            )
            resimulated += made
            if part is None:
                continue
            pending.append(part)
            held += len(part)
            while held >= chunk_size:
                chunk, rest = _Part.concat(pending).split_at(chunk_size)
                chunks.append(_write_chunk(out, len(chunks), n_joints, chunk))
                pending, held = ([rest] if len(rest) else []), len(rest)
        if held:
            chunks.append(_write_chunk(out, len(chunks), n_joints, _Part.concat(pending)))

    manifest = {
        "format": RELEASE_FORMAT,
        "source": store.uri,
        "steps": steps,
        "chunk_size": int(chunk_size),
        "split": split,
        "split_fractions": list(fractions) if split is not None else None,
        "curation_seed": seed,
        "mechanisms": sum(c["mechanisms"] for c in chunks),
        **{name: sum(c[name] for c in chunks) for name in CURVE_SETS},
        "resimulated": resimulated,
        "chunks": chunks,
    }
    # Last, and whole: a folder with a manifest holds a finished export.
    temporary = os.path.join(out, f".{MANIFEST}.tmp")
    with open(temporary, "w") as stream:
        json.dump(manifest, stream, indent=1)
    os.replace(temporary, os.path.join(out, MANIFEST))
    return manifest


def _open_export(
    root: str | Store,
    out: str,
    chunk_size: int,
    split: str | None,
    split_fractions: Sequence[float] | None,
) -> tuple[Store, dict[int, dict], dict[int, dict], Sequence[float]]:
    """The arguments checked, and the root's generation and curation markers."""
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, int | np.integer):
        raise ValueError(f"chunk_size must be an integer, got {chunk_size!r}")
    if chunk_size < 1:
        raise ValueError(f"chunk_size must be at least 1, got {chunk_size}")
    if split is not None:
        check_split(split)
    fractions = check_fractions(split_fractions)
    _check_out(out)
    store = root if isinstance(root, Store) else Store.open(root, writable=False)
    generated = committed_shards(store, "shards")
    if not generated:
        raise ValueError(f"{store.uri} holds no generated shards: run links generate first")
    return store, generated, committed_shards(store, "curation"), fractions


def _check_out(out: str) -> None:
    if not isinstance(out, str) or not out.strip():
        raise ValueError(f"out must be a local folder, got {out!r}")
    if "://" in out:
        raise ValueError(f"out must be a local folder, got {out}")
    if os.path.exists(out) and (not os.path.isdir(out) or os.listdir(out)):
        raise ValueError(f"{out} is not an empty folder: export into a new or empty one")


def _shard_part(
    store: Store,
    marker: dict,
    curation: dict | None,
    steps: int,
    seed: int,
    split: str | None,
    fractions: Sequence[float],
) -> tuple[_Part | None, int]:
    """One generation shard's mechanisms (of `split` only, if given) with their simulations and
    curves; and how many mechanisms it simulated again."""
    n = int(marker["n_joints"])
    files = marker["files"]
    curation_files = (curation or {}).get("files", {})
    mechanisms = by_mechanism_id(store.read_parquet(files["mechanisms"]))
    if split is not None:
        mechanisms = mechanisms.filter(pa.array(split_mask(mechanisms, split, fractions)))
    if not len(mechanisms):
        return None, 0
    ids = mechanisms.column("mechanism_id").to_numpy()

    resimulated = 0
    if "simulations" in files:
        rows = _of_mechanisms(store.read_parquet(files["simulations"]), ids)
        steps = int(rows.column("steps")[0].as_py())
        trajectories = list_values(rows.column("trajectories"), n * steps * 2)
        trajectories = trajectories.reshape(-1, n, steps, 2)
    else:
        trajectories = simulated_trajectories(mechanisms, n, steps)
        resimulated = len(ids)

    if "paths" in curation_files:
        paths = _of_mechanisms(store.read_parquet(curation_files["paths"], _CURVE_COLUMNS), ids)
    else:
        paths = pa.concat_tables(
            [
                trajectory_paths(
                    mechanisms.slice(start, MECHANISMS_PER_BATCH),
                    trajectories[start : start + MECHANISMS_PER_BATCH],
                    n,
                ).select(_CURVE_COLUMNS)
                for start in range(0, len(ids), MECHANISMS_PER_BATCH)
            ]
        )
    if "curated" in curation_files:
        kept = _of_mechanisms(store.read_parquet(curation_files["curated"], _CURVE_COLUMNS), ids)
    else:
        kept = paths.filter(pa.array(curated_mask(paths, seed)))

    part = _Part(
        mechanism_id=ids,
        topology_id=mechanisms.column("topology_id").to_numpy(),
        adjacency=list_values(mechanisms.column("adjacency"), n * n).reshape(-1, n, n),
        node_types=list_values(mechanisms.column("node_types"), n),
        positions=list_values(mechanisms.column("positions"), 2 * n).reshape(-1, n, 2),
        simulations=trajectories,
        curves={"normalized": _Curves.of(paths, steps), "curated": _Curves.of(kept, steps)},
    )
    return part, resimulated


def _of_mechanisms(rows: pa.Table, ids: np.ndarray) -> pa.Table:
    """The rows of a shard's table that belong to the mechanisms `ids` (sorted), in
    mechanism_id order; ValueError if a simulation is missing."""
    rows = rows.filter(pa.array(np.isin(rows.column("mechanism_id").to_numpy(), ids)))
    if "path_id" in rows.schema.names:
        return rows.sort_by("path_id")
    rows = by_mechanism_id(rows)
    if not np.array_equal(rows.column("mechanism_id").to_numpy(), ids):
        raise ValueError("a shard's mechanisms and simulations hold different mechanism ids")
    return rows


def _write_chunk(out: str, number: int, n_joints: int, part: _Part) -> dict:
    """Write one chunk's arrays; returns its manifest entry."""
    name = f"chunk-{number:06d}"
    folder = os.path.join(out, name)
    os.makedirs(folder)
    arrays = {name: getattr(part, name) for name in _MECHANISM_FIELDS}
    for curve_set, curves in part.curves.items():
        arrays[curve_set] = curves.points
        # The mechanism's row in this chunk, as the release indexes mechanisms.
        arrays[f"{curve_set}_mechanism"] = np.searchsorted(
            part.mechanism_id, curves.mechanism_id
        ).astype(np.int32)
        arrays[f"{curve_set}_joint"] = curves.joint
        arrays[f"{curve_set}_path_id"] = curves.path_id
    for array_name, values in arrays.items():
        np.save(os.path.join(folder, f"{array_name}.npy"), np.ascontiguousarray(values))
    return {
        "name": name,
        "n_joints": int(n_joints),
        "mechanisms": len(part),
        **{curve_set: len(part.curves[curve_set].path_id) for curve_set in CURVE_SETS},
        "first_mechanism_id": int(part.mechanism_id[0]),
        "last_mechanism_id": int(part.mechanism_id[-1]),
    }


# -- the release's own files ---------------------------------------------------------------


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
    store, generated, curated, fractions = _open_export(
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
