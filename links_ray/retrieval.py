"""Retrieval: find curated paths whose shape matches a drawn curve, and the mechanisms that
trace them where the curve was drawn (the paper's case study, as an index).

Search has two stages:

1. Candidates by descriptor. A normalized path's descriptor is its distance field: the
   distance from each node of a 16 x 16 grid over [0, 1]^2 to the nearest path point. Two
   paths whose fields are close have a small chamfer distance. The fields are reduced to 32
   dimensions by PCA; each path is scored by plain L2 against the nearest of the query's four
   variants (as drawn, turned 180 degrees, mirrored, both), and the best `CANDIDATES` go on.
2. Exact re-ranking with the chamfer kernel against that variant. On the exhaustive path
   (small datasets, and `brute_force`) every path meets every variant.

The index (descriptors, ids, PCA) is saved at ``ROOT/_links/index.npz`` and reused while the
curated tables are unchanged; the curated points are read from Parquet when it opens.

No Ray: the Serve app and the CLI wrap this module.
"""

from __future__ import annotations

import io
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow.dataset as pads
from numba import njit, prange
from numpy.typing import ArrayLike

from links_ray.dataset import open_table
from links_ray.mechanism import reduce_mechanism
from links_ray.paths import chamfer_to_many, longest_chord
from links_ray.solver import simulate
from links_ray.storage import META, Store

GRID = 16
DIMENSIONS = 32
#: Paths taken by descriptor, then re-ranked by chamfer on COARSE_POINTS points each.
CANDIDATES = 10_000
COARSE_POINTS = 50
#: Paths re-ranked exactly, on all their points, against all four query variants.
FINALISTS = 200
#: Points per path used for descriptors (every fourth of 200).
DESCRIPTOR_STRIDE = 4
MIN_POINTS, MAX_POINTS = 3, 10_000
MAX_K = 100
#: Query coordinates and extent the normalization handles without overflow.
MAX_COORDINATE, MIN_EXTENT = 1e12, 1e-9
INDEX_FILE = f"{META}/index.npz"
INDEX_FORMAT = 1
#: The query's four readings, as maps of normalized coordinates (each its own inverse).
VARIANTS = ("as drawn", "turned 180", "mirrored", "turned and mirrored")


def validate_query(points: object, k: object = 3) -> tuple[np.ndarray, int]:
    """The query as a float64 (T, 2) array and k, or ValueError naming the problem."""
    if isinstance(k, bool) or not isinstance(k, int | np.integer):
        raise ValueError(f"k must be an integer from 1 to {MAX_K}, got {k!r}")
    if not 1 <= k <= MAX_K:
        raise ValueError(f"k must be from 1 to {MAX_K}, got {k}")
    try:
        array = np.asarray(points)
    except (TypeError, ValueError):
        raise ValueError("points must be a list of [x, y] number pairs") from None
    if array.dtype.kind not in "iuf":
        raise ValueError("points must be a list of [x, y] number pairs")
    array = array.astype(np.float64)
    if array.ndim != 2 or array.shape[1] != 2:
        raise ValueError(f"points must be [x, y] pairs, got an array of shape {array.shape}")
    if not MIN_POINTS <= len(array) <= MAX_POINTS:
        raise ValueError(f"points must hold {MIN_POINTS} to {MAX_POINTS} pairs, got {len(array)}")
    if not np.all(np.isfinite(array)):
        raise ValueError("points must be finite numbers")
    if np.any(np.abs(array) > MAX_COORDINATE):
        raise ValueError(f"points must lie within +-{MAX_COORDINATE:g}")
    if np.all(array == array[0]):
        raise ValueError("points are all the same point: there is no curve")
    if np.ptp(array, axis=0).max() < MIN_EXTENT:
        raise ValueError(f"points span less than {MIN_EXTENT:g}: there is no curve to match")
    return array, int(k)


def read_points(path: str) -> np.ndarray:
    """Points from a JSON file holding [[x, y], ...] or {"points": [[x, y], ...]}."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"cannot read points from {path}: {exc}") from None
    return data["points"] if isinstance(data, dict) and "points" in data else data


def normalization(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`normalize_path` with its map: (normalized, matrix, offset), normalized = p @ M.T + b."""
    i, j = longest_chord(points)
    vx, vy = points[j] - points[i]
    matrix = np.array([[vx, vy], [-vy, vx]]) / (vx * vx + vy * vy)
    turned = (points - points[i]) @ matrix.T
    offset = 0.5 - (turned.min(axis=0) + turned.max(axis=0)) / 2 - points[i] @ matrix.T
    return points @ matrix.T + offset, matrix, offset


def variant_map(variant: int) -> tuple[np.ndarray, np.ndarray]:
    """(matrix, offset) of a query variant in normalized coordinates."""
    flip_x = variant in (1, 3)
    flip_y = variant in (1, 2)
    matrix = np.diag([-1.0 if flip_x else 1.0, -1.0 if flip_y else 1.0])
    return matrix, np.array([1.0 if flip_x else 0.0, 1.0 if flip_y else 0.0])


@njit(cache=True, nogil=True, parallel=True)
def _distance_fields(paths: np.ndarray, stride: int, grid: np.ndarray, out: np.ndarray) -> None:
    size = grid.shape[0]
    for p in prange(paths.shape[0]):
        for a in range(size):
            for b in range(size):
                best = np.inf
                for t in range(0, paths.shape[1], stride):
                    dx = paths[p, t, 0] - grid[a]
                    dy = paths[p, t, 1] - grid[b]
                    best = min(best, dx * dx + dy * dy)
                out[p, a * size + b] = np.sqrt(best)


def distance_fields(paths: np.ndarray, stride: int = DESCRIPTOR_STRIDE) -> np.ndarray:
    """(P, GRID * GRID) float32 distance fields of normalized paths (P, T, 2)."""
    grid = (np.arange(GRID) + 0.5) / GRID
    out = np.empty((len(paths), GRID * GRID), dtype=np.float32)
    _distance_fields(np.ascontiguousarray(paths), stride, grid, out)
    return out


@dataclass
class RetrievalIndex:
    """Curated paths, their descriptors, and the way back to their mechanisms."""

    store: Store
    path_id: np.ndarray
    mechanism_id: np.ndarray
    joint: np.ndarray
    n_joints: np.ndarray
    points: np.ndarray  # (N, T, 2) float32 normalized
    descriptors: np.ndarray  # (N, DIMENSIONS) float32
    mean: np.ndarray
    components: np.ndarray  # (DIMENSIONS, GRID * GRID)
    build_s: float = 0.0
    _mechanism_table: pads.Dataset | None = None
    _norms: np.ndarray | None = None
    _coarse: np.ndarray | None = None  # (N, COARSE_POINTS, 2) subsampled points

    def __len__(self) -> int:
        return len(self.path_id)

    @property
    def nbytes(self) -> int:
        """Memory the index holds."""
        arrays = (self.path_id, self.mechanism_id, self.joint, self.n_joints, self.points)
        return sum(a.nbytes for a in arrays) + self.descriptors.nbytes + self.components.nbytes

    @classmethod
    def open(cls, root: str | Store, rebuild: bool = False) -> RetrievalIndex:
        """Load the index saved beside the data, or build (and save) it from `curated/`."""
        store = root if isinstance(root, Store) else Store.open(root, writable=False)
        curated = open_table(store, "curated")
        table = curated.to_table(columns=["path_id", "mechanism_id", "joint", "points", "n_joints"])
        table = table.sort_by("path_id")
        path_id = table.column("path_id").to_numpy()
        points = (
            table.column("points").combine_chunks().flatten().to_numpy().reshape(len(table), -1, 2)
        )
        columns = {
            "store": store,
            "path_id": path_id,
            "mechanism_id": table.column("mechanism_id").to_numpy(),
            "joint": table.column("joint").to_numpy(),
            "n_joints": table.column("n_joints").to_numpy(),
            "points": points,
        }
        fingerprint = _fingerprint(store)
        saved = None if rebuild else store.read_bytes(INDEX_FILE)
        if saved is not None:
            arrays = np.load(io.BytesIO(saved))
            if (
                int(arrays["format"]) == INDEX_FORMAT
                and str(arrays["fingerprint"]) == fingerprint
                and np.array_equal(arrays["path_id"], path_id)
            ):
                return cls(
                    **columns,
                    descriptors=arrays["descriptors"],
                    mean=arrays["mean"],
                    components=arrays["components"],
                )
        start = time.perf_counter()
        fields = distance_fields(points)
        sample = fields[np.random.default_rng(0).permutation(len(fields))[:50_000]]
        mean = sample.mean(axis=0)
        _, _, vt = np.linalg.svd(sample - mean, full_matrices=False)
        components = vt[:DIMENSIONS].astype(np.float32)
        descriptors = ((fields - mean) @ components.T).astype(np.float32)
        index = cls(
            **columns,
            descriptors=descriptors,
            mean=mean.astype(np.float32),
            components=components,
            build_s=time.perf_counter() - start,
        )
        buffer = io.BytesIO()
        np.savez(
            buffer,
            format=INDEX_FORMAT,
            fingerprint=fingerprint,
            path_id=path_id,
            descriptors=descriptors,
            mean=index.mean,
            components=components,
        )
        try:
            store.write_bytes(INDEX_FILE, buffer.getvalue())
        except OSError:  # a read-only root: serve from memory, build again next time
            pass
        return index

    def candidates(self, variants: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
        """The `count` paths nearest by descriptor to any query variant: (rows, variant)."""
        if count >= len(self):
            rows = np.arange(len(self))
            return np.repeat(rows, 4), np.tile(np.arange(4), len(self))
        if self._norms is None:
            self._norms = (self.descriptors**2).sum(axis=1)
        # The same point density as the index's descriptors: about 200 / DESCRIPTOR_STRIDE.
        stride = max(1, round(variants.shape[1] * DESCRIPTOR_STRIDE / self.points.shape[1]))
        fields = distance_fields(variants, stride=stride)
        query = ((fields - self.mean) @ self.components.T).astype(np.float32)
        scores = self._norms[:, None] - 2 * (self.descriptors @ query.T)  # (N, 4)
        variant = scores.argmin(axis=1)
        best = scores[np.arange(len(scores)), variant]
        rows = np.argpartition(best, count)[:count]
        return rows, variant[rows]

    def ranked(
        self, normalized: np.ndarray, k: int = 3, candidates: int = CANDIDATES
    ) -> list[tuple[int, float, int]]:
        """The k best (row, chamfer, variant), best first, for a normalized query."""
        variants = np.stack([normalized @ m.T + b for m, b in map(variant_map, range(4))])
        rows, row_variants = self.candidates(variants, candidates)
        if self._coarse is None:
            picks = np.linspace(0, self.points.shape[1] - 1, COARSE_POINTS).astype(int)
            self._coarse = np.ascontiguousarray(self.points[:, picks])
        picks = np.linspace(0, len(normalized) - 1, min(len(normalized), COARSE_POINTS))
        coarse_query = variants[:, picks.astype(int)]
        coarse = np.empty(len(rows))
        for variant in range(4):
            chosen = row_variants == variant
            if chosen.any():
                coarse[chosen] = chamfer_to_many(coarse_query[variant], self._coarse[rows[chosen]])
        # Each row once, at its best variant (the exhaustive path lists every row four times).
        order = np.argsort(coarse, kind="stable")
        unique_rows, first = np.unique(rows[order], return_index=True)
        finalists = unique_rows[np.argsort(first)][: max(FINALISTS, k)]
        exact = np.stack([chamfer_to_many(variants[v], self.points[finalists]) for v in range(4)])
        best_variant = exact.argmin(axis=0)
        best = exact[best_variant, np.arange(len(finalists))]
        order = np.argsort(best, kind="stable")[:k]
        return [(int(finalists[i]), float(best[i]), int(best_variant[i])) for i in order]

    def retrieve(self, points: object, k: int = 3) -> list[dict]:
        """SPEC section 5 results for a query: best first, mechanisms in the query's frame."""
        query, k = validate_query(points, k)
        normalized, query_matrix, query_offset = normalization(query)
        ranked = self.ranked(normalized, k)
        mechanisms = self._mechanisms([row for row, _, _ in ranked])
        results = []
        for row, distance, variant in ranked:
            mechanism_id = int(self.mechanism_id[row])
            joint = int(self.joint[row])
            adjacency, node_types, positions, index = reduce_mechanism(
                *mechanisms[mechanism_id], joint
            )
            placed = _into_query_frame(
                adjacency, node_types, positions, index, variant, query_matrix, query_offset
            )
            results.append(
                {
                    "path_id": int(self.path_id[row]),
                    "mechanism_id": mechanism_id,
                    "joint": joint,
                    "chamfer": distance,
                    "points": self.points[row].astype(float).tolist(),
                    "mechanism": {
                        "adjacency": adjacency.tolist(),
                        "node_types": node_types.tolist(),
                        "positions": placed.tolist(),
                    },
                    "mechanism_joint": index,
                }
            )
        return results

    def _mechanisms(self, rows: list[int]) -> dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """The mechanism rows of index rows `rows`, by mechanism id."""
        if self._mechanism_table is None:
            self._mechanism_table = open_table(self.store, "mechanisms")
        wanted = pads.field("n_joints").isin([int(self.n_joints[r]) for r in rows]) & pads.field(
            "mechanism_id"
        ).isin([int(self.mechanism_id[r]) for r in rows])
        table = self._mechanism_table.to_table(filter=wanted)
        found = {}
        for row in table.to_pylist():
            n = len(row["node_types"])
            found[row["mechanism_id"]] = (
                np.array(row["adjacency"], dtype=np.uint8).reshape(n, n),
                np.array(row["node_types"], dtype=np.int8),
                np.array(row["positions"]).reshape(n, 2),
            )
        return found

    def brute_force(self, points: ArrayLike, k: int = 3) -> list[tuple[int, float, int]]:
        """Exact k best over every path and variant, all points (tests, recall benchmark)."""
        normalized, _, _ = normalization(validate_query(points, k)[0])
        variants = np.stack([normalized @ m.T + b for m, b in map(variant_map, range(4))])
        exact = np.stack([chamfer_to_many(variant, self.points) for variant in variants])
        best_variant = exact.argmin(axis=0)
        best = exact[best_variant, np.arange(len(self))]
        order = np.argsort(best, kind="stable")[:k]
        return [(int(i), float(best[i]), int(best_variant[i])) for i in order]


def _into_query_frame(
    adjacency: np.ndarray,
    node_types: np.ndarray,
    positions: np.ndarray,
    joint: int,
    variant: int,
    query_matrix: np.ndarray,
    query_offset: np.ndarray,
) -> np.ndarray:
    """Move, turn, scale and (if the match was mirrored) mirror a mechanism so that `joint`
    traces its path where the query was drawn."""
    traced = simulate(adjacency, node_types, positions)[joint]
    _, matrix, offset = normalization(traced)
    variant_matrix, variant_offset = variant_map(variant)
    normalized = positions @ matrix.T + offset  # the candidate's normalized frame
    as_query = normalized @ variant_matrix.T + variant_offset  # undo the query's variant
    return (as_query - query_offset) @ np.linalg.inv(query_matrix).T


def _fingerprint(store: Store) -> str:
    """Changes whenever curated shards are added or redone."""
    markers = store.committed_shards("curation")
    rows = sorted((shard, m["rows"].get("curated", 0)) for shard, m in markers.items())
    return json.dumps(rows)
