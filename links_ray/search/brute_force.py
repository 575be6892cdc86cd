"""Exact brute force over every path of a retrieval index: the truth retrieval is measured by.

`brute_force_many` streams the curated points (the index holds none; `RetrievalIndex` reads them
from Parquet) and is exact
over every path and every variant of the query: a lower bound prunes the paths that cannot
beat the k-th best, and the rest get the exact distance.

No Ray.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import numpy as np
from numpy.typing import ArrayLike

from links_ray.engine.inputs import validate_query
from links_ray.engine.kinematics.paths import normalization
from links_ray.search import kernels
from links_ray.search.arrays import IndexArrays
from links_ray.search.query import (
    QUERY_SAMPLE,
    ScanBuffers,
    best_rows,
    exact_pairs,
    query_variants,
    ranked,
    spread_indices,
)

#: Queries bounded together in one pass over the points, the nodes a side of their distance
#: tables (a finer grid than the search's: tighter bounds), and how far a float32 sum of 200
#: bounds may exceed its exact value.
BRUTE_FORCE_QUERIES, BRUTE_FORCE_NODES, BOUND_ROUNDING = 100, 513, 1e-4


def brute_force_many(
    arrays: IndexArrays,
    points: Callable[[], Iterable[tuple[int, np.ndarray]]],
    queries: list[ArrayLike],
    k: int,
    buffers: ScanBuffers | None = None,
) -> list[list[tuple[int, float, int]]]:
    """Exact k best (row, chamfer, variant) of an index's `arrays` over every path and variant
    for each query, best first, in one pass over the curated points a group of queries.
    `points()` yields (first file row, points (B, steps, 2) float32) of every path in the
    curated files' order (`RetrievalIndex.iter_points`); `buffers` are the scan's (None: new
    ones). Raises ValueError naming a bad query.

    The exact distances of `ranked`'s answer bound the k-th best from above; a path whose
    path-to-query half bounded below (`nearest_node_bounds`), plus its query-to-path half
    bounded below from `QUERY_SAMPLE` of the query's points, exceeds that cannot be among
    the best. The rest get the exact distance.
    """
    k = min(k, len(arrays))
    normalized = [normalization(validate_query(q, k)[0])[0] for q in queries]
    found: list[list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = [[] for _ in queries]
    for first in range(0, len(queries), BRUTE_FORCE_QUERIES):
        group = range(first, min(len(queries), first + BRUTE_FORCE_QUERIES))
        limits = np.array([ranked(arrays, normalized[q], k, buffers=buffers)[-1][1] for q in group])
        tables = np.empty((BRUTE_FORCE_NODES, BRUTE_FORCE_NODES, len(group)), np.float32)
        owners = np.empty((BRUTE_FORCE_NODES,) * 2, dtype=np.int32)
        table = np.empty((BRUTE_FORCE_NODES,) * 2)
        for column, q in enumerate(group):
            kernels.distance_table(normalized[q], table, owners)
            tables[:, :, column] = table
        variants = [query_variants(normalized[q]) for q in group]
        samples = [normalized[q][spread_indices(len(normalized[q]), QUERY_SAMPLE)] for q in group]
        for start, block in points():
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
                distances = exact_pairs(variants[column], block, local, which)
                found[q].append((local + start, which, distances))
    index_row = np.empty(len(arrays), dtype=np.int64)
    index_row[arrays.file_row] = np.arange(len(arrays))
    answers = []
    for parts in found:
        rows, which, distances = (np.concatenate(column) for column in zip(*parts, strict=True))
        rows = index_row[rows]
        answers.append(best_rows(rows, arrays.path_ids(rows), which, distances, k))
    return answers
