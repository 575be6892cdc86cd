"""Retrieval: find curated paths whose shape matches a drawn curve, and the mechanisms that
trace them where the curve was drawn (the paper's case study, as an index).

The distance is the bidirectional chamfer distance between normalized paths, least over the
query's four variants (as drawn, turned 180 degrees, mirrored, both). Search has three stages:

1. Scan. Rows are grouped in coarse lists by k-means on their paths' distance fields (on a
   grid, reduced by PCA to `DIMENSIONS` components); a query scans the lists nearest its own
   variants' fields until they hold `PROBED_ROWS` rows (all of them, up to that size). Each
   scanned path's `SCAN_POINTS` sketch points are looked up in the query's table of distances
   (`search_kernels.sketch_scan`): their mean is the path-to-query half of the chamfer
   distance, sampled, in each variant. The least pass on as candidates (`stage_sizes`), each
   with its likeliest variant (and the second, if within `VARIANT_MARGIN`).
2. Estimate. Each candidate pair gets nearest-point distances from a sample of query points,
   plus the path's distance to the query from the query's table of nearest points. Roughly
   for all, from the first half of the paths' 256-byte sketches, then from the whole sketch
   for the best `REFINED` (`search_kernels.sketch_chamfer`).
3. Exact. The best `FINALISTS` by estimate are traced again from their mechanisms
   (`MechanismBank`: the stored points, bit for bit) and get the exact chamfer distance: in
   their likeliest variant, and in each other one whose lower bound could beat both that and
   the k-th best.

In memory an index holds, per path, its sketch and the row of its mechanism (about 270
bytes), and the packed mechanisms (about 90 bytes a path): no path's points.
`brute_force` is exact over every path, streaming the curated points from Parquet: a lower
bound prunes the paths that cannot beat the k-th best, and the rest get the exact distance.

An index may cover one part of the curated shards (those whose number is `part` modulo
`parts`), so that several Serve replicas split a dataset too large for one. The arrays of each
part are saved under ``ROOT/_links/index/part-P-of-N/`` and reused while its curated shards are
unchanged; a build streams the curated table, so it needs memory only for what it keeps.

No Ray: the Serve app and the CLI wrap this module.
"""

from __future__ import annotations

import io
import json
import time
import uuid
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from numpy.typing import ArrayLike

from links_ray.data.commit import committed_files, committed_shards
from links_ray.data.dataset import isin, open_table
from links_ray.data.lease import Lease, LeaseHeld, index_lease_name
from links_ray.data.store import META, Store, StoreError
from links_ray.engine.cpus import usable_cpus
from links_ray.engine.inputs import DEFAULT_K, as_transmission_deg, validate_query
from links_ray.engine.mechanism import reduce_mechanism
from links_ray.engine.paths import chamfer_to_many, normalization
from links_ray.engine.solver import simulate
from links_ray.search import kernels
from links_ray.search.mechanisms import MechanismBank

#: PCA components of the distance fields that place paths and queries in coarse lists.
DIMENSIONS = 64
#: Paths passed from the scan to the estimate: this share of the index's paths, and at least
#: MIN_CANDIDATES (every path, in every variant, when there are no more than that); past
#: GROWTH_ROWS paths, see `stage_sizes`.
CANDIDATE_SHARE, MIN_CANDIDATES = 0.01, 3_000
#: Sketch points the scan reads of each path (evenly spaced in time, all in the sketch's
#: leading half: one cache line per coordinate).
SCAN_POINTS = 16
SCAN_SLOTS = kernels.scan_slots(SCAN_POINTS)
#: A candidate's second likeliest variant is estimated too when its scan score is within
#: this of the likeliest.
VARIANT_MARGIN = 0.002
#: Candidate pairs estimated from their whole sketches, and the query points that estimate
#: measures from (the rough one measures from `search_kernels.ROUGH_SAMPLE`).
REFINED, QUERY_SAMPLE = 1_500, 64
#: Paths traced again and given the exact chamfer distance (in their likeliest variant, and
#: in the others where a lower bound leaves them able to matter).
FINALISTS = 128
#: Past GROWTH_ROWS paths, the candidates, the pairs estimated from whole sketches and the
#: finalists grow as (paths / GROWTH_ROWS) ** GROWTH_POWER: ten times the paths put about
#: ten times as many near copies around a query, too close for the estimates to tell apart.
#: At 10 million paths the 1-million sizes found 0.94 of the true best three; grown by 3.2,
#: 0.967 (README, retrieval at the paper's scale, has the trade measured).
GROWTH_ROWS, GROWTH_POWER = 1_000_000, 0.5
#: Every second point of a stored path makes its distance field.
FIELD_STRIDE = 2
#: Paths whose distance fields fit the PCA basis and the coarse lists' centroids, and rows
#: read and featurized per block.
SAMPLE, BUILD_BLOCK = 100_000, 50_000
INDEX_FOLDER = f"{META}/index"
#: How often a process waiting for another's index build looks for the saved index.
CACHE_POLL_S = 1.0
#: How long `RetrievalIndex.open` waits for another process's build of the same part by
#: default: twice the longest build measured (10M paths, 773 s on 2 cores).
BUILD_WAIT_S = 1800.0
#: How far a lower bound may exceed the exact distance it bounds by rounding (they are
#: computed differently).
ROUNDING = 1e-9
INDEX_FORMAT = 7  # 7: no codes; the scan reads sketches
#: The coarse partition (an inverted file): about this many rows per list (at most
#: MAX_LISTS lists), fitted by KMEANS_ROUNDS rounds of k-means on the field codes of the
#: SAMPLE paths. A query scans the lists nearest it until they hold PROBED_ROWS rows (every
#: list of an index no larger), so a scan costs the same at 10 million paths as at 1 million.
ROWS_PER_LIST, MAX_LISTS, KMEANS_ROUNDS = 10_000, 4_096, 8
PROBED_ROWS = 250_000
#: Exact brute force: queries bounded together in one pass over the points, the nodes a
#: side of their distance tables (a finer grid than the search's: tighter bounds), and how
#: far a float32 sum of 200 bounds may exceed its exact value.
BRUTE_FORCE_QUERIES, BRUTE_FORCE_NODES, BOUND_ROUNDING = 100, 513, 1e-4


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


def distance_fields(paths: np.ndarray, stride: int = 1) -> np.ndarray:
    """Distance fields (P, GRID * GRID) float32 of normalized paths (P, T, 2)."""
    fields = np.empty((len(paths), kernels.GRID * kernels.GRID), dtype=np.float32)
    compute = kernels.distance_fields if len(paths) > 4 else kernels.distance_fields_serial
    compute(np.ascontiguousarray(paths), stride, fields)
    return fields


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
    """The PCA basis of distance fields: what places paths and queries in coarse lists."""

    mean: np.ndarray  # (GRID * GRID,) float32
    components: np.ndarray  # (GRID * GRID, DIMENSIONS) float32

    @classmethod
    def fit(cls, fields: np.ndarray) -> Basis:
        mean = fields.mean(axis=0)
        _, _, vt = np.linalg.svd(fields - mean, full_matrices=False)
        components = np.ascontiguousarray(vt[:DIMENSIONS].T, dtype=np.float32)
        return cls(mean.astype(np.float32), components)

    def field_codes(self, fields: np.ndarray) -> np.ndarray:
        """(P, DIMENSIONS) float32: distance fields in the basis."""
        return ((fields - self.mean) @ self.components).astype(np.float32)

    def query(self, variants: np.ndarray) -> np.ndarray:
        """(4, DIMENSIONS): the field codes of a query's four variants."""
        return self.field_codes(distance_fields(variants))


def stage_sizes(paths: int) -> tuple[int, int, int]:
    """(candidates, refined, finalists) of a search over an index of `paths` paths: the scan
    passes on the candidates, the best `refined` candidate pairs by rough estimate get the
    fine one, and the best `finalists` rows by fine estimate the exact distance."""
    growth = max(1.0, paths / GROWTH_ROWS) ** GROWTH_POWER
    candidates = CANDIDATE_SHARE * min(paths, GROWTH_ROWS) * growth
    return (
        max(MIN_CANDIDATES, round(candidates)),
        round(REFINED * growth),
        round(FINALISTS * growth),
    )


def check_part(part: int, parts: int) -> None:
    """ValueError unless 0 <= part < parts."""
    for name, value in (("part", part), ("parts", parts)):
        if isinstance(value, bool) or not isinstance(value, int | np.integer):
            raise ValueError(f"{name} must be an integer, got {value!r}")
    if parts < 1 or not 0 <= part < parts:
        raise ValueError(f"part must be in 0..parts-1 with parts >= 1, got part {part} of {parts}")


def cache_folder(part: int, parts: int) -> str:
    """Where part `part` of an index split in `parts` keeps its arrays."""
    return f"{INDEX_FOLDER}/part-{part}-of-{parts}"


@dataclass
class RetrievalIndex:
    """Curated paths, their codes and sketches, and the mechanisms that trace them.

    One query at a time: the scan writes into buffers the index keeps (callers that serve
    concurrent requests hold a lock, as the Serve app does).
    """

    store: Store
    files: list[str]  # the curated files indexed, in row order
    steps: int  # points per path
    mechanism_row: np.ndarray  # (N,) int32: each path's mechanism, a row of `bank`
    joint: np.ndarray  # (N,) int8
    sketches: np.ndarray  # (N, 2 * SKETCH_POINTS) uint8, see `search_kernels`
    transmission: np.ndarray  # (N,) float32: min_transmission_deg (NaN where not stored)
    # Rows are grouped by coarse list: list l is rows list_start[l]:list_start[l + 1], its
    # centroid centroids[l] (field codes). file_row[r] is row r's place in the curated files.
    list_start: np.ndarray  # (L + 1,) int64
    centroids: np.ndarray  # (L, DIMENSIONS) float32
    file_row: np.ndarray  # (N,) int32 or int64
    basis: Basis
    bank: MechanismBank
    part: int = 0
    parts: int = 1
    build_s: float = 0.0
    fingerprint: str = ""  # of the curated shards indexed (changes when any is redone)
    _scores: np.ndarray | None = field(default=None, repr=False)  # the scan's, reused
    _likely: np.ndarray | None = field(default=None, repr=False)

    def __len__(self) -> int:
        return len(self.joint)

    @property
    def nbytes(self) -> int:
        """Memory the index holds, the scan's output buffer included."""
        arrays = (
            *(getattr(self, name) for name in ROW_ARRAYS),
            self.list_start,
            self.centroids,
        )
        basis = self.basis.mean.nbytes + self.basis.components.nbytes
        # The scan's scores (float32) and likely variants (int8), kept between queries.
        return sum(a.nbytes for a in arrays) + basis + self.bank.nbytes + 5 * len(self)

    @property
    def mechanism_id(self) -> np.ndarray:
        """(N,) int64: each path's mechanism id (computed)."""
        return self.bank.ids[self.mechanism_row]

    @property
    def path_id(self) -> np.ndarray:
        """(N,) int64: each path's id, 32 * mechanism_id + joint (computed)."""
        return self.path_ids(np.arange(len(self)))

    def path_ids(self, rows: np.ndarray) -> np.ndarray:
        return (self.bank.ids[self.mechanism_row[rows]] << 5) | self.joint[rows].astype(np.int64)

    def paths(self, rows: np.ndarray) -> np.ndarray:
        """(len(rows), steps, 2) float32: the curated points of these rows, traced again."""
        rows = np.asarray(rows, dtype=np.int64)
        return self.bank.paths(self.mechanism_row[rows], self.joint[rows], self.steps)

    @classmethod
    def open(
        cls,
        root: str | Store,
        rebuild: bool = False,
        part: int = 0,
        parts: int = 1,
        wait_s: float = BUILD_WAIT_S,
    ) -> RetrievalIndex:
        """Load the index of `root`'s curated shards numbered `part` modulo `parts` (all, by
        default) saved beside the data, or build (and save) it; `rebuild`: build it anyway.

        Of several processes opening one part at once (Serve replicas), the one holding the
        part's index lease builds and saves it; the others wait for it and load it, or, with
        `rebuild`, take the lease after it and build again. After `wait_s` seconds of waiting,
        `LeaseHeld` names the holder. A saved index that cannot be read, or was made from other
        curated shards, is rebuilt.
        """
        check_part(part, parts)
        if not wait_s >= 0:
            raise ValueError(f"wait_s must be zero or more, got {wait_s!r}")
        store = root if isinstance(root, Store) else Store.open(root, writable=False)
        markers = {
            shard: marker
            for shard, marker in committed_shards(store, "curation").items()
            if shard % parts == part and "curated" in marker["files"]
        }
        files = committed_files(store, "curated", markers)
        if not files:
            where = "" if parts == 1 else f" in part {part} of {parts}"
            raise ValueError(f"{store.uri} has no curated table{where} yet")
        folder = cache_folder(part, parts)
        fingerprint = _fingerprint(markers)
        rows = sum(marker["rows"].get("curated", 0) for marker in markers.values())
        common = {
            "store": store,
            "files": files,
            "part": part,
            "parts": parts,
            "fingerprint": fingerprint,
        }
        saved = None if rebuild else _load_cache(store, folder, fingerprint, rows)
        if saved is not None:
            return cls(**common, **saved)
        lease = _build_lease(store, part, parts, fingerprint, rows, rebuild, wait_s)
        if isinstance(lease, dict):  # another process built it meanwhile
            return cls(**common, **lease)
        try:
            start = time.perf_counter()
            arrays = _build(store, files, rows)
            index = cls(**common, **arrays, build_s=time.perf_counter() - start)
            try:
                _save(store, folder, fingerprint, arrays, index.build_s)
            except OSError:  # a read-only root: serve from memory, build again next time
                pass
        finally:
            if lease is not None:
                lease.release()
        return index

    def iter_points(self, block: int = BUILD_BLOCK) -> Iterator[tuple[int, np.ndarray]]:
        """(first file row, points (B, steps, 2) float32) of every path, in the curated
        files' order (row r of the index is file row `file_row[r]`), read from Parquet: the
        index holds no points."""
        start = 0
        for batch in _curated_batches(self.store, self.files, ["points"], block):
            points = _batch_points(batch)
            yield start, points
            start += len(points)

    def probe(self, field_codes: np.ndarray, rows: int = PROBED_ROWS) -> tuple[np.ndarray, ...]:
        """The row ranges to scan for a query whose variants have these field codes: the
        lists nearest any variant, nearest first, until they hold `rows` rows, in row order
        (`scan_pieces`: starts, ends, at)."""
        sizes = np.diff(self.list_start)
        if len(sizes) == 1 or rows >= len(self):
            chosen = np.arange(len(sizes))
        else:
            gaps = (self.centroids**2).sum(axis=1) - 2 * field_codes @ self.centroids.T
            order = np.argsort(gaps.min(axis=0), kind="stable")
            enough = np.searchsorted(np.cumsum(sizes[order]), rows) + 1
            chosen = np.sort(order[:enough])
        return kernels.scan_pieces(self.list_start[chosen], self.list_start[chosen + 1])

    def candidates(
        self,
        levels: np.ndarray,
        count: int,
        pieces: tuple[np.ndarray, ...],
        min_transmission: float = 0.0,
    ) -> tuple[np.ndarray, np.ndarray]:
        """About `count` rows of the scanned `pieces` (`probe`) whose scan score (at their best
        variant) against the query's `levels` table is least (every row when `count` reaches
        the total); and for each, 4 * its likeliest variant + the second likeliest if nearly as
        likely (`search_kernels.sketch_scan`), or -1 when every row is returned. Only rows
        whose path keeps `min_transmission` degrees (when above 0) are passed on."""
        if count >= len(self):
            rows = np.arange(len(self))
            if min_transmission > 0:
                rows = np.flatnonzero(self.transmission >= min_transmission)
            return rows, np.full(len(rows), -1, dtype=np.int8)
        starts, ends, at = pieces
        scanned = int(at[-1] + ends[-1] - starts[-1])
        if self._scores is None:
            self._scores = np.empty(len(self), dtype=np.float32)
            self._likely = np.empty(len(self), dtype=np.int8)
        scores, likely = self._scores[:scanned], self._likely[:scanned]
        kernels.sketch_scan(
            self.sketches, starts, ends, at, levels, SCAN_SLOTS, VARIANT_MARGIN, scores, likely
        )
        if min_transmission > 0:
            angles = np.concatenate(
                [self.transmission[s:e] for s, e in zip(starts, ends, strict=True)]
            )
            scores[~(angles >= min_transmission)] = np.inf
        positions = _about_least(scores, count)
        positions = positions[np.isfinite(scores[positions])]
        piece = np.searchsorted(at, positions, side="right") - 1
        return starts[piece] + positions - at[piece], likely[positions]

    def ranked(
        self,
        normalized: np.ndarray,
        k: int = DEFAULT_K,
        candidates: int | None = None,
        probed: int = PROBED_ROWS,
        min_transmission: float = 0.0,
    ) -> list[tuple[int, float, int]]:
        """The k best (row, chamfer, variant), best first, for a normalized query, among the
        paths keeping `min_transmission` degrees (all, at 0); the scan of the lists nearest
        it, `probed` rows, passes on `candidates` paths (by default as `stage_sizes` says)."""
        default_candidates, refined, finalists = stage_sizes(len(self))
        count = candidates or default_candidates
        variants = query_variants(normalized)
        pieces = self.probe(self.basis.query(variants), probed)
        table, owners = distance_table(normalized)
        levels = np.empty((kernels.SKETCH_LEVELS + 1,) * 2, dtype=np.float32)
        kernels.level_table(normalized, owners, levels)
        rows, likely = self.candidates(levels, count, pieces, min_transmission)
        if len(rows) == 0:
            return []
        # Each candidate with its likely variants (every variant on the exhaustive path).
        if count >= len(self):
            pair_rows, pair_variants = np.repeat(rows, 4), np.tile(np.arange(4), len(rows))
        else:
            first, second = likely // 4, likely % 4
            both = second != first
            pair_rows = np.concatenate([rows, rows[both]])
            pair_variants = np.concatenate([first, second[both]]).astype(np.int64)
        if len(pair_rows) > refined:  # a rough estimate of every pair first
            rough = self._estimate(
                normalized, levels, pair_rows, pair_variants, kernels.ROUGH_SAMPLE, rough=True
            )
            best = np.argpartition(rough, refined)[:refined]
            pair_rows, pair_variants = pair_rows[best], pair_variants[best]
        fine = self._estimate(normalized, levels, pair_rows, pair_variants, QUERY_SAMPLE)
        # Rows by their best estimate (a row may come twice, once per variant).
        order = np.argsort(fine, kind="stable")
        _, first = np.unique(pair_rows[order], return_index=True)
        chosen = order[np.sort(first)][: max(finalists, k)]
        return self._exact_finalists(variants, table, pair_rows[chosen], pair_variants[chosen], k)

    def _exact_finalists(
        self,
        variants: np.ndarray,
        table: np.ndarray,
        rows: np.ndarray,
        likely: np.ndarray,
        k: int,
        points: np.ndarray | None = None,
    ) -> list[tuple[int, float, int]]:
        """The k best (row, chamfer, variant) of `rows`, each at its least exact distance over
        the four variants, as if all were measured; `likely` is each row's likeliest variant,
        and `points` their paths (traced again when not given).

        Those are measured first. Another variant of a row is measured only if the lower
        bound of `path_to_query_bounds` leaves it able to beat both that row's distance and
        the k-th best so far: no other pair can change the answer.
        """
        if points is None:
            points = self.paths(rows)
        local = np.arange(len(rows))
        distances = _exact_pairs(variants, points, local, likely)
        bounds = np.empty((len(rows), 4))
        kernels.path_to_query_bounds(table, points, bounds)
        last = min(k, len(rows)) - 1
        kth = np.partition(distances, last)[last]
        bounds[local, likely] = np.inf
        bounds -= ROUNDING
        able = (bounds < distances[:, None]) & (bounds <= kth)
        more, more_variants = np.nonzero(able)
        if len(more):
            measured = _exact_pairs(variants, points, more, more_variants)
            local = np.concatenate([local, more])
            likely = np.concatenate([likely, more_variants])
            distances = np.concatenate([distances, measured])
        rows = np.asarray(rows)[local]
        return _best_rows(rows, self.path_ids(rows), likely, distances, k)

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
        for path in self.paths(rows):
            if time.perf_counter() - start >= seconds:
                break
            self.retrieve(path)
            answered += 1
        return answered

    def retrieve(
        self, points: object, k: int = DEFAULT_K, min_transmission: object = 0.0
    ) -> list[dict]:
        """The k best results for a query, best first, each with its mechanism in the query's
        frame (docs/CONTRACT.md, HTTP API, describes a result), among the paths whose least
        transmission angle is at least `min_transmission` degrees (fewer than k if fewer do)."""
        query, k = validate_query(points, k)
        floor = as_transmission_deg(min_transmission, "min_transmission")
        normalized, query_matrix, query_offset = normalization(query)
        ranked = self.ranked(normalized, k, min_transmission=floor)
        rows = np.array([row for row, _, _ in ranked], dtype=np.int64)
        paths = self.paths(rows)
        results = []
        for (row, distance, variant), path in zip(ranked, paths, strict=True):
            joint = int(self.joint[row])
            adjacency, node_types, positions, index = reduce_mechanism(
                *self.bank.mechanism(int(self.mechanism_row[row])), joint
            )
            placed = _into_query_frame(
                adjacency, node_types, positions, index, variant, query_matrix, query_offset
            )
            results.append(
                {
                    "path_id": int(self.path_ids(np.array([row]))[0]),
                    "mechanism_id": int(self.bank.ids[self.mechanism_row[row]]),
                    "joint": joint,
                    "chamfer": distance,
                    "min_transmission_deg": _degrees_or_none(self.transmission[row]),
                    "points": path.astype(float).tolist(),
                    "mechanism": {
                        "adjacency": adjacency.tolist(),
                        "node_types": node_types.tolist(),
                        "positions": placed.tolist(),
                    },
                    "mechanism_joint": index,
                }
            )
        return results

    def _estimate(
        self,
        normalized: np.ndarray,
        levels: np.ndarray,
        rows: np.ndarray,
        variants: np.ndarray,
        sample_size: int,
        rough: bool = False,
    ) -> np.ndarray:
        """Estimated chamfer distances of (row, variant) pairs from the paths' sketches (their
        leading half only, if `rough`), measured from `sample_size` query points."""
        picked = normalized[_spread(len(normalized), sample_size)]
        sample = np.rint(picked * kernels.SKETCH_LEVELS).astype(np.int32)
        used = kernels.ROUGH_POINTS if rough else kernels.SKETCH_POINTS
        midpoints = _NO_MIDPOINTS if rough else kernels.sketch_midpoints(self.steps)
        out = np.empty(len(rows))
        kernels.sketch_chamfer(sample, levels, self.sketches, rows, variants, used, midpoints, out)
        return out

    def brute_force(self, points: ArrayLike, k: int = DEFAULT_K) -> list[tuple[int, float, int]]:
        """Exact k best (row, chamfer, variant) over every path and variant, best first."""
        return self.brute_force_many([points], k)[0]

    def brute_force_many(
        self, queries: list[ArrayLike], k: int = DEFAULT_K
    ) -> list[list[tuple[int, float, int]]]:
        """`brute_force` of each query, in one pass over the curated points.

        The exact distances of `ranked`'s answer bound the k-th best from above; a path whose
        path-to-query half bounded below (`nearest_node_bounds`), plus its query-to-path half
        bounded below from `QUERY_SAMPLE` of the query's points, exceeds that cannot be among
        the best. The rest get the exact distance.
        """
        k = min(k, len(self))
        normalized = [normalization(validate_query(q, k)[0])[0] for q in queries]
        found: list[list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = [[] for _ in queries]
        for first in range(0, len(queries), BRUTE_FORCE_QUERIES):
            group = range(first, min(len(queries), first + BRUTE_FORCE_QUERIES))
            limits = np.array([self.ranked(normalized[q], k)[-1][1] for q in group])
            tables = np.empty((BRUTE_FORCE_NODES, BRUTE_FORCE_NODES, len(group)), np.float32)
            owners = np.empty((BRUTE_FORCE_NODES,) * 2, dtype=np.int32)
            table = np.empty((BRUTE_FORCE_NODES,) * 2)
            for column, q in enumerate(group):
                kernels.distance_table(normalized[q], table, owners)
                tables[:, :, column] = table
            variants = [query_variants(normalized[q]) for q in group]
            samples = [normalized[q][_spread(len(normalized[q]), QUERY_SAMPLE)] for q in group]
            for start, block in self.iter_points():
                bounds = np.empty((len(block), 4, len(group)), dtype=np.float32)
                kernels.nearest_node_bounds(tables, block, bounds)
                able = bounds <= limits + BOUND_ROUNDING
                for column, q in enumerate(group):
                    local, which = np.nonzero(able[:, :, column])
                    # The query-to-path half, bounded from a sample of the query's points.
                    sums = np.empty(len(local))
                    kernels.sample_to_path_sums(samples[column], block, local, which, sums)
                    lower = bounds[local, which, column] + sums / len(normalized[q])
                    keep = lower <= limits[column] + BOUND_ROUNDING
                    local, which = local[keep], which[keep]
                    distances = _exact_pairs(variants[column], block, local, which)
                    found[q].append((local + start, which, distances))
        index_row = np.empty(len(self), dtype=np.int64)
        index_row[self.file_row] = np.arange(len(self))
        answers = []
        for parts in found:
            rows, which, distances = (np.concatenate(column) for column in zip(*parts, strict=True))
            rows = index_row[rows]
            answers.append(_best_rows(rows, self.path_ids(rows), which, distances, k))
        return answers


_NO_MIDPOINTS = np.empty(0, dtype=np.int32)


def _degrees_or_none(angle: np.floating) -> float | None:
    """An angle for JSON: None where the dataset stores none (NaN)."""
    return None if np.isnan(angle) else float(angle)


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


def _curated_batches(
    store: Store, files: list[str], columns: list[str], block: int
) -> Iterator[pa.RecordBatch]:
    """Record batches of up to `block` rows of these curated files, in order."""
    for relative in files:
        with store.fs.open_input_file(store.path(relative)) as source:
            yield from pq.ParquetFile(source).iter_batches(batch_size=block, columns=columns)


def _curated_schema(store: Store, files: list[str]) -> pa.Schema:
    """The columns of the first curated file (all of a dataset's are written alike)."""
    with store.fs.open_input_file(store.path(files[0])) as source:
        return pq.ParquetFile(source).schema_arrow


def _batch_points(batch: pa.RecordBatch) -> np.ndarray:
    """The `points` of a record batch as (rows, steps, 2) float32 (a batch's own offsets are
    32-bit, and never overflow: a batch holds at most `BUILD_BLOCK` paths)."""
    column = batch.column("points")
    values = column.flatten().to_numpy()
    return values.reshape(len(column), -1, 2)


def _build(store: Store, files: list[str], rows: int) -> dict:
    """Sketches, coarse lists and mechanisms of the paths in `files` (`rows` of them),
    streamed block by block."""
    sample = _sample_paths(store, files, rows)
    steps = sample.shape[1]
    fields = distance_fields(sample, FIELD_STRIDE)
    basis = Basis.fit(fields)
    centroids = _centroids(basis.field_codes(fields), min(MAX_LISTS, max(1, rows // ROWS_PER_LIST)))
    del sample, fields
    lists = np.zeros(rows, dtype=np.int32)
    sketches = np.empty((rows, 2 * kernels.SKETCH_POINTS), dtype=np.uint8)
    mechanism_id = np.empty(rows, dtype=np.int64)
    joint = np.empty(rows, dtype=np.int8)
    transmission = np.full(rows, np.nan, dtype=np.float32)  # NaN: a dataset made before it
    start = 0
    columns = ["mechanism_id", "joint", "points"]
    if "min_transmission_deg" in _curated_schema(store, files).names:
        columns.append("min_transmission_deg")
    for batch in _curated_batches(store, files, columns, BUILD_BLOCK):
        end = start + batch.num_rows
        if end > rows:
            raise ValueError(f"{store.uri}: the curated files hold more rows than their markers")
        points = _batch_points(batch)
        if points.shape[1] != steps:
            raise ValueError(f"{store.uri}: curated paths of {points.shape[1]} and {steps} points")
        if len(centroids) > 1:
            codes = basis.field_codes(distance_fields(points, FIELD_STRIDE))
            lists[start:end] = _nearest_centroid(codes, centroids)
        kernels.sketch_paths(points, sketches[start:end])
        mechanism_id[start:end] = batch.column("mechanism_id").to_numpy()
        joint[start:end] = batch.column("joint").to_numpy()
        if "min_transmission_deg" in columns:
            transmission[start:end] = batch.column("min_transmission_deg").to_numpy()
        start = end
    if start != rows:
        raise ValueError(f"{store.uri}: the curated files hold fewer rows than their markers")
    bank = MechanismBank.from_table(_source_mechanisms(store, mechanism_id))
    by_row = {
        "mechanism_row": bank.rows_of(mechanism_id),
        "joint": joint,
        "sketches": sketches,
        "transmission": transmission,
    }
    file_row = np.argsort(lists, kind="stable").astype(np.int32 if rows < 2**31 else np.int64)
    list_start = np.searchsorted(lists[file_row], np.arange(len(centroids) + 1)).astype(np.int64)
    if len(centroids) > 1:  # rows grouped by list: a list is scanned in one sweep
        by_row = {name: array[file_row] for name, array in by_row.items()}
    return {
        **by_row,
        "steps": steps,
        "file_row": file_row,
        "list_start": list_start,
        "centroids": centroids,
        "basis": basis,
        "bank": bank,
    }


def _centroids(codes: np.ndarray, count: int) -> np.ndarray:
    """`count` centroids (count, DIMENSIONS) of the field codes of a sample of paths, by
    KMEANS_ROUNDS rounds of k-means (one centroid at zero when count is 1)."""
    if count == 1:
        return np.zeros((1, DIMENSIONS), dtype=np.float32)
    rng = np.random.default_rng(0)
    centroids = codes[rng.permutation(len(codes))[:count]]
    for _ in range(KMEANS_ROUNDS):
        nearest = _nearest_centroid(codes, centroids)
        sizes = np.bincount(nearest, minlength=count)
        for d in range(centroids.shape[1]):
            sums = np.bincount(nearest, weights=codes[:, d], minlength=count)
            centroids[:, d] = np.where(sizes > 0, sums / np.maximum(sizes, 1), centroids[:, d])
    return centroids


def _nearest_centroid(points: np.ndarray, centroids: np.ndarray) -> np.ndarray:
    """The index of the nearest centroid of each point (squared distances through BLAS)."""
    gaps = (centroids**2).sum(axis=1) - 2 * points @ centroids.T
    return gaps.argmin(axis=1).astype(np.int32)


def _sample_paths(store: Store, files: list[str], rows: int) -> np.ndarray:
    """Up to SAMPLE paths drawn from files spread evenly over `files` (twice as many paths as
    it needs, when the files hold them), as (P, steps, 2) float32."""
    share = min(1.0, 2 * SAMPLE / max(rows, 1))
    chosen = files[:: max(1, round(1 / share))] if share < 1 else files
    points = np.concatenate(
        [_batch_points(b) for b in _curated_batches(store, chosen, ["points"], BUILD_BLOCK)]
    )
    picked = np.random.default_rng(0).permutation(len(points))[:SAMPLE]
    return points[np.sort(picked)]


#: The arrays a saved index holds: one entry per row, and the rest, besides the basis.
ROW_ARRAYS = (
    "mechanism_row",
    "joint",
    "sketches",
    "transmission",
    "file_row",
)
SAVED_ARRAYS = (*ROW_ARRAYS, "list_start", "centroids")
BASIS_ARRAYS = ("mean", "components")
#: What a saved index was built with: one built otherwise is rebuilt.
BUILD_SETTINGS = {
    "dimensions": DIMENSIONS,
    "sketch_points": kernels.SKETCH_POINTS,
    "sample": SAMPLE,
    "rows_per_list": ROWS_PER_LIST,
    "max_lists": MAX_LISTS,
}


def _save(store: Store, folder: str, fingerprint: str, arrays: dict, build_s: float) -> None:
    """Save an index's arrays in a new build folder, then point `current.json` at it (the
    commit), then delete older builds."""
    build = uuid.uuid4().hex[:12]
    named = {name: arrays[name] for name in SAVED_ARRAYS}
    named.update({f"basis_{name}": getattr(arrays["basis"], name) for name in BASIS_ARRAYS})
    named.update({f"bank_{name}": array for name, array in arrays["bank"].arrays().items()})
    for name, array in named.items():
        buffer = io.BytesIO()
        np.save(buffer, array)
        store.write_bytes(f"{folder}/{build}/{name}.npy", buffer.getbuffer())
    current = {
        "format": INDEX_FORMAT,
        "fingerprint": fingerprint,
        "build": build,
        "rows": len(arrays["joint"]),
        "steps": arrays["steps"],
        "settings": BUILD_SETTINGS,
        "build_s": build_s,
        "arrays": sorted(named),
    }
    store.write_json(f"{folder}/current.json", current)
    older = {relative[len(folder) + 1 :].split("/")[0] for relative in store.list_files(folder)}
    for name in older - {build, "current.json"}:
        store.delete_folder(f"{folder}/{name}")


def _load_cache(store: Store, folder: str, fingerprint: str, rows: int) -> dict | None:
    """The saved index if it holds this fingerprint's paths, else None (also for one that is
    missing, damaged or of another format)."""
    current = store.read_json(f"{folder}/current.json")
    if (
        current is None
        or current.get("format") != INDEX_FORMAT
        or current.get("fingerprint") != fingerprint
        or current.get("rows") != rows
        or current.get("settings") != BUILD_SETTINGS
    ):
        return None
    named = {}
    try:
        for name in current["arrays"]:
            data = store.read_bytes(f"{folder}/{current['build']}/{name}.npy")
            if data is None:
                return None
            named[name] = np.load(io.BytesIO(data), allow_pickle=False)
        basis = Basis(*(named.pop(f"basis_{name}") for name in BASIS_ARRAYS))
        bank = MechanismBank(
            **{name[5:]: named.pop(name) for name in list(named) if name.startswith("bank_")}
        )
        saved = {name: named.pop(name) for name in SAVED_ARRAYS}
    except (OSError, ValueError, KeyError, TypeError, EOFError):
        return None
    if named or any(len(saved[name]) != rows for name in ROW_ARRAYS):
        return None
    return {**saved, "steps": int(current["steps"]), "basis": basis, "bank": bank}


def _build_lease(
    store: Store, part: int, parts: int, fingerprint: str, rows: int, rebuild: bool, wait_s: float
) -> Lease | dict | None:
    """The part's index lease (this process builds), the index another process built while
    this one waited (not with `rebuild`), or None (build without the lease: the root takes no
    writes). `LeaseHeld` after `wait_s` seconds, naming the holder."""
    folder = cache_folder(part, parts)

    def saved() -> dict | None:
        return None if rebuild else _load_cache(store, folder, fingerprint, rows)

    try:
        got = Lease.acquire_waiting(
            store,
            index_lease_name(part, parts),
            "the retrieval index build",
            wait_s,
            done=saved,
            poll_s=CACHE_POLL_S,
        )
    except LeaseHeld:
        raise
    except (OSError, StoreError):
        return None
    if isinstance(got, dict):
        return got
    got.keep_renewed()  # a large build takes minutes
    # The index may have been saved between our look and our lease.
    found = saved()
    if found is None:
        return got
    got.release()
    return found


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


def _source_mechanisms(store: Store, mechanism_ids: np.ndarray) -> pa.Table:
    """The mechanisms with these ids (each once). The filter holds the ids in Arrow's memory
    (`dataset.isin`): a command that stops right after building an index would otherwise
    abort now and then at exit."""
    return open_table(store, "mechanisms").to_table(
        columns=["mechanism_id", "adjacency", "node_types", "positions"],
        filter=isin("mechanism_id", mechanism_ids),
    )


def _exact_pairs(
    variants: np.ndarray, points: np.ndarray, rows: np.ndarray, which: np.ndarray
) -> np.ndarray:
    """Exact chamfer distances between query variant which[i] and path points[rows[i]]; many
    pairs are measured on every CPU the process was given (the kernel releases the GIL)."""
    distances = np.empty(len(rows))

    def measure(variant: int, block: np.ndarray) -> None:
        distances[block] = chamfer_to_many(variants[variant], points[rows[block]])

    blocks = []
    for variant in range(4):
        chosen = np.flatnonzero(which == variant)
        parts = max(1, len(chosen) // 2048)
        blocks += [(variant, block) for block in np.array_split(chosen, parts) if len(block)]
    if len(rows) > 4096:  # worth the threads (a query's few finalists are not)
        with ThreadPoolExecutor(usable_cpus()) as pool:
            list(pool.map(lambda job: measure(*job), blocks))
    else:
        for job in blocks:
            measure(*job)
    # A path that no longer traces (damaged data) is never an answer.
    return np.nan_to_num(distances, nan=np.inf)


def _best_rows(
    rows: np.ndarray, path_ids: np.ndarray, variants: np.ndarray, distances: np.ndarray, k: int
) -> list[tuple[int, float, int]]:
    """The k best (row, distance, variant), best first, each row once at its least distance
    (rows may repeat, once per variant measured); ties go to the lower path id, then variant,
    as a merge of several indexes' answers orders them."""
    order = np.lexsort((variants, path_ids, distances))
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


def sketch_paths(points: np.ndarray) -> np.ndarray:
    """The sketches (N, 2 * SKETCH_POINTS) uint8 of normalized paths (N, T, 2)."""
    sketches = np.empty((len(points), 2 * kernels.SKETCH_POINTS), dtype=np.uint8)
    kernels.sketch_paths(points, sketches)
    return sketches
