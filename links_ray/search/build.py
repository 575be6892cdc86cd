"""The build of a retrieval index: the arrays an index holds, streamed from the curated table.

A build reads the curated files block by block and keeps, per path, its sketch
(`kernels.sketch_paths`), its mechanism's row in a `MechanismBank` and its joint, and its least
transmission angle; no path's points. It groups the rows in coarse lists (an inverted file):
k-means on the PCA codes (`Basis`) of the paths' distance fields, fitted on a sample of
`SAMPLE` paths. The query pipeline (`search.query`) scans the lists nearest a query.

No Ray.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import pyarrow as pa

from links_ray.data.commit import committed_files
from links_ray.data.derived import PathFilter, file_batches, file_schema
from links_ray.data.store import Store
from links_ray.search import kernels
from links_ray.search.mechanisms import MechanismBank

#: PCA components of the distance fields that place paths and queries in coarse lists.
DIMENSIONS = 64
#: Every second point of a stored path makes its distance field.
FIELD_STRIDE = 2
#: Paths whose distance fields fit the PCA basis and the coarse lists' centroids, and rows
#: read and featurized per block.
SAMPLE, BUILD_BLOCK = 100_000, 50_000
#: The coarse partition (an inverted file): about this many rows per list (at most
#: MAX_LISTS lists), fitted by KMEANS_ROUNDS rounds of k-means on the field codes of the
#: SAMPLE paths.
ROWS_PER_LIST, MAX_LISTS, KMEANS_ROUNDS = 10_000, 4_096, 8


def distance_fields(paths: np.ndarray, stride: int = 1) -> np.ndarray:
    """Distance fields (P, GRID * GRID) float32 of normalized paths (P, T, 2), from every
    `stride`-th point of each path (`kernels.GRID`)."""
    fields = np.empty((len(paths), kernels.GRID * kernels.GRID), dtype=np.float32)
    compute = kernels.distance_fields if len(paths) > 4 else kernels.distance_fields_serial
    compute(np.ascontiguousarray(paths), stride, fields)
    return fields


def sketch_paths(points: np.ndarray) -> np.ndarray:
    """The sketches (N, 2 * SKETCH_POINTS) uint8 of normalized paths (N, T, 2)."""
    sketches = np.empty((len(points), 2 * kernels.SKETCH_POINTS), dtype=np.uint8)
    kernels.sketch_paths(points, sketches)
    return sketches


@dataclass
class Basis:
    """The PCA basis of distance fields: what places paths and queries in coarse lists."""

    mean: np.ndarray  # (GRID * GRID,) float32
    components: np.ndarray  # (GRID * GRID, DIMENSIONS) float32

    @classmethod
    def fit(cls, fields: np.ndarray) -> Basis:
        """The mean and first DIMENSIONS principal components of distance fields (P, GRID *
        GRID)."""
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


def curated_batches(
    store: Store,
    files: list[str],
    columns: list[str],
    block: int,
    keeps: PathFilter | None = None,
) -> Iterator[pa.RecordBatch]:
    """Record batches of up to `block` rows of these curated files, in order (only the paths
    `keeps` holds, when given); a lean root's points derived from its mechanisms
    (`data.derived`)."""
    yield from file_batches(store, "curated", files, columns, block, keeps)


def batch_points(batch: pa.RecordBatch) -> np.ndarray:
    """The `points` of a record batch as (rows, steps, 2) float32 (a batch's own offsets are
    32-bit, and never overflow: a batch holds at most `BUILD_BLOCK` paths)."""
    column = batch.column("points")
    values = column.flatten().to_numpy()
    return values.reshape(len(column), -1, 2)


def build_arrays(
    store: Store, files: list[str], rows: int, keeps: PathFilter | None = None
) -> dict:
    """Sketches, coarse lists and mechanisms of the paths in `files` (`rows` of them; only
    those `keeps` holds, when given), streamed block by block: the keyword arguments of a
    `RetrievalIndex` besides its place.

    Raises ValueError if the files hold more or fewer rows than `rows`, or paths of
    different lengths.
    """
    sample = _sample_paths(store, files, rows, keeps)
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
    if "min_transmission_deg" in file_schema(store, files[0]).names:  # all written alike
        columns.append("min_transmission_deg")
    for batch in curated_batches(store, files, columns, BUILD_BLOCK, keeps):
        end = start + batch.num_rows
        if end > rows:
            raise ValueError(f"{store.uri}: the curated files hold more rows than their markers")
        points = batch_points(batch)
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
    bank = MechanismBank.from_tables(_source_mechanisms(store, np.unique(mechanism_id)))
    by_row = {
        "mechanism_row": bank.rows_of(mechanism_id),
        "joint": joint,
        "sketches": sketches,
        "transmission": transmission,
    }
    del mechanism_id, joint, sketches, transmission  # by_row holds the only references
    file_row = np.argsort(lists, kind="stable").astype(np.int32 if rows < 2**31 else np.int64)
    list_start = np.searchsorted(lists[file_row], np.arange(len(centroids) + 1)).astype(np.int64)
    if len(centroids) > 1:  # rows grouped by list: a list is scanned in one sweep
        for name in by_row:  # one at a time: a single array is held twice at once
            by_row[name] = by_row[name][file_row]
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


def _sample_paths(
    store: Store, files: list[str], rows: int, keeps: PathFilter | None
) -> np.ndarray:
    """Up to SAMPLE paths drawn from files spread evenly over `files` (twice as many paths as
    it needs, when the files hold them), as (P, steps, 2) float32."""
    share = min(1.0, 2 * SAMPLE / max(rows, 1))
    chosen = files[:: max(1, round(1 / share))] if share < 1 else files
    points = np.concatenate(
        [batch_points(b) for b in curated_batches(store, chosen, ["points"], BUILD_BLOCK, keeps)]
    )
    picked = np.random.default_rng(0).permutation(len(points))[:SAMPLE]
    return points[np.sort(picked)]


def _source_mechanisms(store: Store, wanted: np.ndarray) -> Iterator[pa.Table]:
    """The rows of the mechanisms with these ids (ascending, distinct), file by file: one
    file's rows are held at a time, however many mechanisms the root holds."""
    columns = ["mechanism_id", "adjacency", "node_types", "positions"]
    for relative in committed_files(store, "mechanisms"):
        table = store.read_parquet(relative, columns)
        ids = table.column("mechanism_id").to_numpy()
        at = np.minimum(np.searchsorted(wanted, ids), max(len(wanted) - 1, 0))
        keep = wanted[at] == ids if len(wanted) else np.zeros(len(ids), dtype=bool)
        if keep.any():
            yield table.filter(pa.array(keep))
