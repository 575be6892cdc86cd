"""Retrieval: find curated paths whose shape matches a drawn curve, and the mechanisms that
trace them where the curve was drawn (the paper's case study, as an index).

The distance is the bidirectional chamfer distance between normalized paths, least over the
query's four variants (as drawn, turned 180 degrees, mirrored, both). Search has three stages:

1. Scan. Chamfer's two halves are, on a grid, dot products: the query's point mass against a
   path's distance field, and the path's point mass against the query's distance field. With
   the fields reduced by PCA to `DIMENSIONS` per half (and int8 codes), every path gets a
   linear estimate of its chamfer distance to each variant. One pass over the leading
   `HEAD_COMPONENTS` of every code keeps `HEAD_KEEP` times as many rows as there are
   candidates; their whole codes keep the candidates (`CANDIDATE_SHARE` of the paths, at least
   `MIN_CANDIDATES`), each with its likeliest variant (and the second, if within `VARIANT_MARGIN`).
2. Estimate. Each candidate pair gets nearest-point distances from a sample of query points,
   plus the path's distance to the query from the query's table of nearest points (nearly
   exact: the misses against exact search are near ties). Roughly for all, from the paths'
   128-byte sketches (`search_kernels.rough_chamfer`), then finely for the best `REFINED`,
   from the whole paths (`search_kernels.estimate_chamfer`).
3. Exact. The best `FINALISTS` by estimate get the exact chamfer distance: in their likeliest
   variant, and in each other one whose lower bound could beat both that and the k-th best.

`brute_force` is exact over every path: a lower bound prunes the paths that cannot beat the
k-th best, and the rest get the exact distance.

The index (codes, PCA basis, ids) is saved at ``ROOT/_links/index.npz`` and reused while the
curated tables are unchanged; the curated points are read from Parquet when it opens, and
sketched then.

No Ray: the Serve app and the CLI wrap this module.
"""

from __future__ import annotations

import io
import json
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.dataset as pads
from numpy.typing import ArrayLike

from links_ray.data.commit import committed_shards
from links_ray.data.dataset import open_table
from links_ray.data.lease import Lease
from links_ray.data.store import META, Store, StoreError
from links_ray.engine.inputs import DEFAULT_K, validate_query
from links_ray.engine.mechanism import reduce_mechanism
from links_ray.engine.paths import chamfer_to_many, normalization
from links_ray.engine.solver import simulate
from links_ray.search import kernels

#: PCA components of the distance fields; a path's code holds two sets (2 * DIMENSIONS int8).
DIMENSIONS = 64
#: Paths passed from the scan to the estimate: this share of all, and at least MIN_CANDIDATES
#: (every path, in every variant, when there are no more than that).
CANDIDATE_SHARE, MIN_CANDIDATES = 0.025, 3_000
#: Components per half in the head of a code; the head scan keeps HEAD_KEEP times as many rows
#: as there are candidates, for the whole codes to rank.
HEAD_COMPONENTS, HEAD_KEEP = 24, 4
HEAD_COLUMNS = np.r_[0:HEAD_COMPONENTS, DIMENSIONS : DIMENSIONS + HEAD_COMPONENTS]
TAIL_COLUMNS = np.r_[HEAD_COMPONENTS:DIMENSIONS, DIMENSIONS + HEAD_COMPONENTS : 2 * DIMENSIONS]
#: A candidate's second likeliest variant is estimated too when its linear estimate is within
#: this of the likeliest.
VARIANT_MARGIN = 0.002
#: Candidate pairs given the fine estimate, the query points it measures from (the rough
#: estimate measures from `search_kernels.ROUGH_SAMPLE`), and the stride of the path points
#: it measures the distance to the query at.
REFINED, QUERY_SAMPLE, FINE_STRIDE = 3_000, 32, 2
#: Paths given the exact chamfer distance (in their likeliest variant, and in the others where
#: a lower bound leaves them able to matter).
FINALISTS = 48
#: Every second point of a stored path makes its distance field.
FIELD_STRIDE = 2
#: Distance fields used to fit the PCA basis, and rows featurized per block while building.
PCA_SAMPLE, BUILD_BLOCK = 50_000, 50_000
INDEX_FILE = f"{META}/index.npz"
#: How far a lower bound may exceed the exact distance it bounds by rounding (they are
#: computed differently).
ROUNDING = 1e-9
INDEX_FORMAT = 3


def read_points(path: str) -> np.ndarray:
    """Points from a JSON file holding [[x, y], ...] or {"points": [[x, y], ...]}."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"cannot read points from {path}: {exc}") from None
    return data["points"] if isinstance(data, dict) and "points" in data else data


def variant_map(variant: int) -> tuple[np.ndarray, np.ndarray]:
    """(matrix, offset) of a query variant in normalized coordinates."""
    flip_x = variant in (1, 3)
    flip_y = variant in (1, 2)
    matrix = np.diag([-1.0 if flip_x else 1.0, -1.0 if flip_y else 1.0])
    return matrix, np.array([1.0 if flip_x else 0.0, 1.0 if flip_y else 0.0])


def path_features(paths: np.ndarray, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Distance fields and point masses (P, GRID * GRID) float32 of normalized paths (P, T, 2)."""
    cells = kernels.GRID * kernels.GRID
    fields = np.empty((len(paths), cells), dtype=np.float32)
    mass = np.empty((len(paths), cells), dtype=np.float32)
    compute = kernels.path_features if len(paths) > 4 else kernels.path_features_serial
    compute(np.ascontiguousarray(paths), stride, fields, mass)
    return fields, mass


def distance_table(normalized: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The query's exact distance from each node of the `search_kernels` table grid, and the
    index of the query point at that distance."""
    table = np.empty((kernels.TABLE_CELLS + 1,) * 2)
    owners = np.empty(table.shape, dtype=np.int32)
    kernels.distance_table(normalized, table, owners)
    return table, owners


def query_variants(normalized: np.ndarray) -> np.ndarray:
    """(4, T, 2): the normalized query as drawn, turned 180 degrees, mirrored, and both."""
    return np.stack([normalized @ m.T + b for m, b in map(variant_map, range(4))])


@dataclass
class Basis:
    """The PCA basis of distance fields, and the int8 scale of the codes."""

    mean: np.ndarray  # (GRID * GRID,) float32
    components: np.ndarray  # (GRID * GRID, DIMENSIONS) float32
    scale: np.ndarray  # (2 * DIMENSIONS,) float32

    @classmethod
    def fit(cls, fields: np.ndarray) -> Basis:
        mean = fields.mean(axis=0)
        _, _, vt = np.linalg.svd(fields - mean, full_matrices=False)
        components = np.ascontiguousarray(vt[:DIMENSIONS].T, dtype=np.float32)
        return cls(mean.astype(np.float32), components, np.ones(2 * DIMENSIONS, np.float32))

    def project(self, fields: np.ndarray, mass: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Unquantized codes (P, 2 * DIMENSIONS) and biases (P,) of paths.

        The bias subtracts what the estimate gives a path against itself (its mass against
        its own field, which the grid makes positive), so that near matches are not ranked by
        how well their own curve happens to sit on the grid.
        """
        codes = np.concatenate(
            [(fields - self.mean) @ self.components, mass @ self.components], axis=1
        )
        return codes, mass @ self.mean - (fields * mass).sum(axis=1)

    def query(self, variants: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Scan weights (4, 2 * DIMENSIONS) against int8 codes, and offsets (4,), of the
        query's variants: code . weight + offset + bias estimates the chamfer distance."""
        fields, mass = path_features(variants)
        weights = np.concatenate(
            [mass @ self.components, (fields - self.mean) @ self.components], axis=1
        )
        return (weights * self.scale).astype(np.float32), (mass @ self.mean).astype(np.float32)


@dataclass
class RetrievalIndex:
    """Curated paths, their codes, and the way back to their mechanisms.

    One query at a time: the scan writes into buffers the index keeps (callers that serve
    concurrent requests hold a lock, as the Serve app does).
    """

    store: Store
    path_id: np.ndarray
    mechanism_id: np.ndarray
    joint: np.ndarray
    points: np.ndarray  # (N, T, 2) float32 normalized
    # Each path's int8 code, split in two: the leading HEAD_COMPONENTS of each half, scanned
    # for every query, and the rest, read only for the rows the head ranks best.
    head: np.ndarray  # (N, 2 * HEAD_COMPONENTS) int8
    tail: np.ndarray  # (N, 2 * (DIMENSIONS - HEAD_COMPONENTS)) int8
    bias: np.ndarray  # (N,) float32
    basis: Basis
    mechanisms: pa.Table  # the mechanisms the paths come from, sorted by mechanism_id
    sketches: np.ndarray  # (N, 2 * SKETCH_POINTS) uint8, see `search_kernels`
    build_s: float = 0.0
    _scores: np.ndarray | None = None  # the scan's output, reused across queries

    def __len__(self) -> int:
        return len(self.path_id)

    @property
    def nbytes(self) -> int:
        """Memory the index holds."""
        arrays = (
            self.path_id,
            self.mechanism_id,
            self.joint,
            self.points,
            self.sketches,
            self.head,
            self.tail,
            self.bias,
            self.basis.components,
        )
        # And the scan's scores.
        return sum(a.nbytes for a in arrays) + self.mechanisms.nbytes + 4 * len(self)

    @classmethod
    def open(cls, root: str | Store, rebuild: bool = False) -> RetrievalIndex:
        """Load the index saved beside the data, or build (and save) it from `curated/`.

        Of several processes opening one root at once (Serve replicas), the one holding the
        root's index lease builds and saves the cache; the others wait for it and load it. A
        cache that cannot be read, or was made from other curated shards, is rebuilt.
        """
        store = root if isinstance(root, Store) else Store.open(root, writable=False)
        markers = committed_shards(store, "curation")
        curated = open_table(store, "curated", markers)
        table = curated.to_table(columns=["path_id", "mechanism_id", "joint", "points"])
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
            "points": points,
            "sketches": sketch_paths(points),
        }
        columns["mechanisms"] = _source_mechanisms(store, columns["mechanism_id"])
        fingerprint = _fingerprint(markers)
        saved = None if rebuild else _load_cache(store, fingerprint, path_id)
        if saved is not None:
            return cls(**columns, **saved)
        lease = None if rebuild else _build_lease(store, fingerprint, path_id)
        if isinstance(lease, dict):  # another process built it meanwhile
            return cls(**columns, **lease)
        try:
            start = time.perf_counter()
            head, tail, bias, basis = _encode(points)
            index = cls(
                **columns,
                head=head,
                tail=tail,
                bias=bias,
                basis=basis,
                build_s=time.perf_counter() - start,
            )
            buffer = io.BytesIO()
            np.savez(
                buffer,
                format=INDEX_FORMAT,
                fingerprint=fingerprint,
                path_id=path_id,
                head=head,
                tail=tail,
                bias=bias,
                mean=basis.mean,
                components=basis.components,
                scale=basis.scale,
            )
            try:
                store.write_bytes(INDEX_FILE, buffer.getvalue())
            except OSError:  # a read-only root: serve from memory, build again next time
                pass
        finally:
            if lease is not None:
                lease.release()
        return index

    def candidates(
        self, weights: np.ndarray, offsets: np.ndarray, count: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """About `count` rows whose scanned estimate, at their best variant, is least (every
        row when `count` reaches the total), for the query weights and offsets of
        `Basis.query`; and for each, 4 * its likeliest variant + the second likeliest if
        nearly as likely (`score_rows`), or -1 when every row is returned."""
        if count >= len(self):
            return np.arange(len(self)), np.full(len(self), -1, dtype=np.int8)
        if self._scores is None:
            self._scores = np.empty(len(self), dtype=np.float32)
        head_weights = np.ascontiguousarray(weights[:, HEAD_COLUMNS])
        kernels.scan(self.head, head_weights, offsets, self.bias, self._scores)
        wide = _about_least(self._scores, HEAD_KEEP * count)
        scores = np.empty(len(wide), dtype=np.float32)
        likely = np.empty(len(wide), dtype=np.int8)
        kernels.score_rows(
            self.head,
            self.tail,
            wide,
            head_weights,
            np.ascontiguousarray(weights[:, TAIL_COLUMNS]),
            offsets,
            self.bias,
            VARIANT_MARGIN,
            scores,
            likely,
        )
        best = _about_least(scores, count)
        return wide[best], likely[best]

    def ranked(
        self, normalized: np.ndarray, k: int = DEFAULT_K, candidates: int | None = None
    ) -> list[tuple[int, float, int]]:
        """The k best (row, chamfer, variant), best first, for a normalized query; the scan
        passes on `candidates` paths (by default `CANDIDATE_SHARE` of them)."""
        if candidates is None:
            candidates = max(MIN_CANDIDATES, round(CANDIDATE_SHARE * len(self)))
        variants = query_variants(normalized)
        weights, offsets = self.basis.query(variants)
        rows, likely = self.candidates(weights, offsets, candidates)
        # Each candidate with its likely variants (every variant on the exhaustive path).
        if len(rows) == len(self):
            pair_rows, pair_variants = np.repeat(rows, 4), np.tile(np.arange(4), len(rows))
        else:
            first, second = likely // 4, likely % 4
            both = second != first
            pair_rows = np.concatenate([rows, rows[both]])
            pair_variants = np.concatenate([first, second[both]]).astype(np.int64)
        table, owners = distance_table(normalized)
        if len(pair_rows) > REFINED:  # a rough estimate of every pair first
            rough = self._rough_estimate(normalized, owners, pair_rows, pair_variants)
            best = np.argpartition(rough, REFINED)[:REFINED]
            pair_rows, pair_variants = pair_rows[best], pair_variants[best]
        fine = self._estimate(normalized, owners, pair_rows, pair_variants)
        # Rows by their best estimate (a row may come twice, once per variant).
        order = np.argsort(fine, kind="stable")
        _, first = np.unique(pair_rows[order], return_index=True)
        finalists = order[np.sort(first)][: max(FINALISTS, k)]
        return self._exact_finalists(
            variants, table, pair_rows[finalists], pair_variants[finalists], k
        )

    def _exact_finalists(
        self,
        variants: np.ndarray,
        table: np.ndarray,
        rows: np.ndarray,
        likely: np.ndarray,
        k: int,
    ) -> list[tuple[int, float, int]]:
        """The k best (row, chamfer, variant) of `rows`, each at its least exact distance over
        the four variants, as if all were measured; `likely` is each row's likeliest variant.

        Those are measured first. Another variant of a row is measured only if the lower
        bound of `path_to_query_bounds` leaves it able to beat both that row's distance and
        the k-th best so far: no other pair can change the answer.
        """
        distances = _exact_pairs(variants, self.points, rows, likely)
        bounds = np.empty((len(rows), 4))
        kernels.path_to_query_bounds(table, self.points[rows], bounds)
        last = min(k, len(rows)) - 1
        kth = np.partition(distances, last)[last]
        bounds[np.arange(len(rows)), likely] = np.inf
        bounds -= ROUNDING
        able = (bounds < distances[:, None]) & (bounds <= kth)
        more, more_variants = np.nonzero(able)
        if len(more):
            measured = _exact_pairs(variants, self.points, rows[more], more_variants)
            rows = np.concatenate([rows, rows[more]])
            likely = np.concatenate([likely, more_variants])
            distances = np.concatenate([distances, measured])
        return _best_rows(rows, likely, distances, k)

    def warm(self, seconds: float = 5.0, queries: int = 200) -> int:
        """Answer queries until `seconds` pass or `queries` are answered; return how many.

        The first (an ellipse) loads the compiled kernels. The rest are the index's own paths.
        On the 2-core VM we measure on, the first seconds of queries after a load ran up to
        20 times slower (spikes of 0.3-0.8 s) while later ones did not, and waiting instead
        of querying did not help; answering them before taking traffic keeps them from users.
        """
        if not (seconds >= 0 and queries >= 1):
            raise ValueError(f"warm needs seconds >= 0 and queries >= 1, got {seconds}, {queries}")
        if not len(self):
            return 0
        angle = np.linspace(0, 2 * np.pi, 100)
        self.retrieve(np.column_stack([np.cos(angle), 0.5 * np.sin(angle)]))
        rows = np.random.default_rng(0).integers(len(self), size=queries - 1)
        start = time.perf_counter()
        answered = 1
        for row in rows:
            if time.perf_counter() - start >= seconds:
                break
            self.retrieve(self.points[row])
            answered += 1
        return answered

    def retrieve(self, points: object, k: int = DEFAULT_K) -> list[dict]:
        """The k best results for a query, best first, each with its mechanism in the query's
        frame (docs/CONTRACT.md, HTTP API, describes a result)."""
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
        """The mechanisms of index rows `rows`, by mechanism id."""
        ids = self.mechanisms.column("mechanism_id").to_numpy()
        at = np.searchsorted(ids, self.mechanism_id[rows])
        found = {}
        for row in self.mechanisms.take(at).to_pylist():
            n = len(row["node_types"])
            found[row["mechanism_id"]] = (
                np.array(row["adjacency"], dtype=np.uint8).reshape(n, n),
                np.array(row["node_types"], dtype=np.int8),
                np.array(row["positions"]).reshape(n, 2),
            )
        return found

    def _estimate(
        self, normalized: np.ndarray, owners: np.ndarray, rows: np.ndarray, variants: np.ndarray
    ) -> np.ndarray:
        """Estimated chamfer distances of (row, variant) pairs from the whole paths."""
        sample = np.ascontiguousarray(normalized[_spread(len(normalized), QUERY_SAMPLE)])
        out = np.empty(len(rows))
        kernels.estimate_chamfer(
            normalized, sample, owners, self.points, rows, variants, FINE_STRIDE, out
        )
        return out

    def _rough_estimate(
        self, normalized: np.ndarray, owners: np.ndarray, rows: np.ndarray, variants: np.ndarray
    ) -> np.ndarray:
        """Roughly estimated chamfer distances of (row, variant) pairs from their sketches."""
        levels = np.empty((kernels.SKETCH_LEVELS + 1,) * 2, dtype=np.float32)
        kernels.level_table(normalized, owners, levels)
        picked = normalized[_spread(len(normalized), kernels.ROUGH_SAMPLE)]
        sample = np.rint(picked * kernels.SKETCH_LEVELS).astype(np.int32)
        out = np.empty(len(rows))
        kernels.rough_chamfer(sample, levels, self.sketches, rows, variants, out)
        return out

    def brute_force(self, points: ArrayLike, k: int = DEFAULT_K) -> list[tuple[int, float, int]]:
        """Exact k best (row, chamfer, variant) over every path and variant, best first.

        The exact distances of `ranked`'s answer bound the k-th best from above; a path whose
        path-to-query half alone is bounded below by more than that cannot be among the best.
        """
        normalized, _, _ = normalization(validate_query(points, k)[0])
        k = min(k, len(self))
        limit = self.ranked(normalized, k)[-1][1] + ROUNDING
        table, _ = distance_table(normalized)
        bounds = np.empty((len(self), 4))
        kernels.path_to_query_bounds(table, self.points, bounds)
        pairs = np.flatnonzero(bounds.ravel() <= limit)
        rows, variants = pairs // 4, pairs % 4
        distances = _exact_pairs(query_variants(normalized), self.points, rows, variants)
        return _best_rows(rows, variants, distances, k)


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


def _fingerprint(markers: dict[int, dict]) -> str:
    """Changes whenever curated shards are added or redone."""
    rows = sorted(
        (shard, m["rows"].get("curated", 0), m.get("attempt")) for shard, m in markers.items()
    )
    return json.dumps(rows)


def _load_cache(store: Store, fingerprint: str, path_id: np.ndarray) -> dict | None:
    """The saved codes and basis if the cache holds this fingerprint's, else None (also for a
    cache that is missing, damaged or of another format)."""
    saved = store.read_bytes(INDEX_FILE)
    if saved is None:
        return None
    try:
        arrays = np.load(io.BytesIO(saved))
        if (
            int(arrays["format"]) != INDEX_FORMAT
            or str(arrays["fingerprint"]) != fingerprint
            or not np.array_equal(arrays["path_id"], path_id)
        ):
            return None
        basis = Basis(arrays["mean"], arrays["components"], arrays["scale"])
        return {
            "head": arrays["head"],
            "tail": arrays["tail"],
            "bias": arrays["bias"],
            "basis": basis,
        }
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
        return None


#: How often a process waiting for another's index build looks for the cache.
CACHE_POLL_S = 1.0


def _build_lease(store: Store, fingerprint: str, path_id: np.ndarray) -> Lease | dict | None:
    """The index lease (this process builds), the cache another process built while this one
    waited, or None (build without the lease: the root takes no writes)."""
    while True:
        try:
            got = Lease.try_acquire(store, "index", "the retrieval index build", ttl_s=60.0)
        except (OSError, StoreError):
            return None
        if isinstance(got, Lease):
            got.keep_renewed()  # a large build takes minutes
            # The cache may have been written between our look and our lease.
            saved = _load_cache(store, fingerprint, path_id)
            if saved is None:
                return got
            got.release()
            return saved
        time.sleep(CACHE_POLL_S)
        saved = _load_cache(store, fingerprint, path_id)
        if saved is not None:
            return saved


#: One score in this many makes the sample that sets a selection threshold.
SELECTION_STRIDE = 16


def _about_least(values: np.ndarray, count: int) -> np.ndarray:
    """Ascending indices of about the `count` least values (of all, if there are fewer): those
    at or below the matching quantile of a strided sample, so a few percent more or fewer."""
    if count >= len(values):
        return np.arange(len(values))
    if len(values) < 64 * SELECTION_STRIDE:  # too few for the sample to estimate a quantile
        return np.sort(np.argpartition(values, count - 1)[:count])
    # A partition of the whole array would cost more than the scan that made it.
    sample = values[::SELECTION_STRIDE]
    rank = min(len(sample) - 1, count * len(sample) // len(values))
    return np.flatnonzero(values <= np.partition(sample, rank)[rank])


def _spread(length: int, count: int) -> np.ndarray:
    """Up to `count` distinct indices evenly over range(length)."""
    return np.unique(np.linspace(0, length - 1, count).round().astype(int))


def sketch_paths(points: np.ndarray) -> np.ndarray:
    """The sketches (N, 2 * SKETCH_POINTS) uint8 of normalized paths (N, T, 2)."""
    sketches = np.empty((len(points), 2 * kernels.SKETCH_POINTS), dtype=np.uint8)
    kernels.sketch_paths(points, sketches)
    return sketches


def _source_mechanisms(store: Store, mechanism_ids: np.ndarray) -> pa.Table:
    """The mechanisms with these ids, sorted by id: answers need them at once, and a Parquet
    lookup per answer would cost more than the search."""
    wanted = pa.array(np.unique(mechanism_ids))
    table = open_table(store, "mechanisms").to_table(
        columns=["mechanism_id", "adjacency", "node_types", "positions"],
        filter=pads.field("mechanism_id").isin(wanted),
    )
    return table.sort_by("mechanism_id").combine_chunks()


def _encode(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, Basis]:
    """The int8 codes of normalized paths (N, T, 2), split into head (N, 2 * HEAD_COMPONENTS)
    and tail, their biases, and the basis."""
    sample = np.sort(np.random.default_rng(0).permutation(len(points))[:PCA_SAMPLE])
    basis = Basis.fit(path_features(points[sample], FIELD_STRIDE)[0])
    raw = np.empty((len(points), 2 * DIMENSIONS), dtype=np.float32)
    bias = np.empty(len(points), dtype=np.float32)
    for start in range(0, len(points), BUILD_BLOCK):
        block = slice(start, start + BUILD_BLOCK)
        raw[block], bias[block] = basis.project(*path_features(points[block], FIELD_STRIDE))
    basis.scale = np.maximum(np.abs(raw).max(axis=0), 1e-12) / 127
    codes = np.round(raw / basis.scale).astype(np.int8)
    head = np.ascontiguousarray(codes[:, HEAD_COLUMNS])
    return head, np.ascontiguousarray(codes[:, TAIL_COLUMNS]), bias, basis


def _exact_pairs(
    variants: np.ndarray, points: np.ndarray, rows: np.ndarray, which: np.ndarray
) -> np.ndarray:
    """Exact chamfer distances between query variant which[i] and path rows[i]."""
    distances = np.empty(len(rows))
    for variant in range(4):
        chosen = np.flatnonzero(which == variant)
        for block in np.array_split(chosen, max(1, len(chosen) // 8192)):
            if len(block):
                distances[block] = chamfer_to_many(variants[variant], points[rows[block]])
    return distances


def _best_rows(
    rows: np.ndarray, variants: np.ndarray, distances: np.ndarray, k: int
) -> list[tuple[int, float, int]]:
    """The k best (row, distance, variant), best first, each row once at its least distance
    (rows may repeat, once per variant measured); ties go to the lower row, then variant."""
    order = np.lexsort((variants, rows, distances))
    answer: list[tuple[int, float, int]] = []
    seen: set[int] = set()
    for i in order:
        if int(rows[i]) in seen:
            continue
        seen.add(int(rows[i]))
        answer.append((int(rows[i]), float(distances[i]), int(variants[i])))
        if len(answer) == k:
            break
    return answer
