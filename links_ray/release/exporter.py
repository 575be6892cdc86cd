"""Export to the LINKS release layout (docs/guides/exports.md): numpy arrays chunk by chunk
(`format="numpy"`, below), or the release's own pickled files (`format="release"`:
`release.pickled_export.export_release_files`).

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
from collections.abc import Sequence
from dataclasses import dataclass
from itertools import groupby

import numpy as np
import pyarrow as pa

from links_ray.data.curation import (
    JOINT_BITS,
    MECHANISMS_PER_BATCH,
    by_mechanism_id,
    curated_mask,
    list_values,
    simulated_trajectories,
    trajectory_paths,
)
from links_ray.data.derived import file_schema, has_points, rows_of_ids
from links_ray.data.splits import split_mask
from links_ray.data.store import META, Store
from links_ray.engine.inputs import DEFAULT_STEPS
from links_ray.release.export_source import open_export
from links_ray.release.pickled_export import DEFAULT_RELEASE_BATCH, export_release_files

#: Mechanisms per chunk by default: a 20-joint chunk's simulations take 320 MB.
DEFAULT_CHUNK_MECHANISMS = 10_000
#: What `export_release` writes: numpy chunks, or the release's own pickled files.
EXPORT_FORMATS = ("numpy", "release")
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
    store, generated, curated, fractions = open_export(
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

    if "paths" in curation_files and has_points(file_schema(store, curation_files["paths"])):
        paths = _of_mechanisms(store.read_parquet(curation_files["paths"], _CURVE_COLUMNS), ids)
    else:  # not written, or written as ids (a lean root): made from the trajectories
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
    curated_file = curation_files.get("curated")
    if curated_file and has_points(file_schema(store, curated_file)):
        kept = _of_mechanisms(store.read_parquet(curated_file, _CURVE_COLUMNS), ids)
    elif curated_file:  # a lean root's curated ids: their paths, as curation made them
        chosen = store.read_parquet(curated_file, ["path_id"]).column("path_id").to_numpy()
        chosen = chosen[np.isin(chosen >> JOINT_BITS, ids)]  # of the split's mechanisms
        kept = pa.concat_tables(rows_of_ids([paths], chosen, f"{store.uri}/{curated_file}"))
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
