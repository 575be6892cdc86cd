"""The query pipeline of a retrieval index: scan, estimates, exact.

Its functions read an index's arrays (`IndexArrays`) and write only the scan's buffers they are
given (`ScanBuffers`); `RetrievalIndex` passes both in.

The distance is the bidirectional chamfer distance between normalized paths, least over the
query's four variants (as drawn, turned 180 degrees, mirrored, both). A query passes three
stages, each narrower and more exact than the last:

1. Scan (`probe`, `candidates`). A query scans the coarse lists nearest its own variants'
   distance fields until they hold `PROBED_ROWS` rows (all of them, up to that size). Each
   scanned path's `SCAN_POINTS` sketch points are looked up in the query's table of distances
   (`kernels.sketch_scan`): their mean is the path-to-query half of the chamfer distance,
   sampled, in each variant. The least pass on as candidates (`stage_sizes`), each with its
   likeliest variant (and the second, if within `VARIANT_MARGIN`). Only the rows a query
   may answer with (`allowed_rows`: a transmission floor, a joint limit) pass; when they are
   no more than the candidates, they all pass, in every variant, unscanned.
2. Estimate (`estimate`). Each candidate pair gets nearest-point distances from a sample of
   query points, plus the path's distance to the query from the query's table of nearest
   points. Roughly for all, from the first half of the paths' sketches, then from the whole
   sketch for the best `REFINED` (`kernels.sketch_chamfer`).
3. Exact (`exact_finalists`). The best `EXACT_CANDIDATES` by estimate are traced again from
   their mechanisms (`MechanismBank`: the stored points, bit for bit) and get the exact
   chamfer distance: in their likeliest variant, and in each other one whose lower bound could
   beat both that and the k-th best.

No Ray.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from links_ray.engine.cpus import usable_cpus
from links_ray.engine.kinematics.paths import chamfer_to_many
from links_ray.search import kernels
from links_ray.search.arrays import IndexArrays

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
#: measures from (the rough one measures from `kernels.ROUGH_SAMPLE`).
REFINED, QUERY_SAMPLE = 1_500, 64
#: Paths traced again and given the exact chamfer distance (in their likeliest variant, and
#: in the others where a lower bound leaves them able to matter): the exact stage's
#: candidates.
EXACT_CANDIDATES = 128
#: Past GROWTH_ROWS paths, the candidates, the pairs estimated from whole sketches and the
#: exact stage's candidates grow as (paths / GROWTH_ROWS) ** GROWTH_POWER: ten times the paths
#: put about ten times as many near copies around a query, too close for the estimates to tell
#: apart (docs/benchmarks.md has the trade of recall and time measured).
GROWTH_ROWS, GROWTH_POWER = 1_000_000, 0.5
#: Rows a query scans: the lists nearest it until they hold this many (every list of an index
#: no larger), so a scan costs the same however many paths the index holds.
PROBED_ROWS = 250_000
#: How far a lower bound may exceed the exact distance it bounds by rounding (they are
#: computed differently).
ROUNDING = 1e-9
#: One score in this many makes the sample that sets a selection threshold.
SELECTION_STRIDE = 16

_NO_MIDPOINTS = np.empty(0, dtype=np.int32)


@dataclass
class ScanBuffers:
    """The scan's output for up to `rows` rows: each scanned row's score and likely variants.

    An index keeps one between queries, so that a scan allocates nothing of the index's size
    (one query at a time uses it); its arrays are allocated on the first scan, as an index
    small enough to pass every row on never scans.
    """

    rows: int
    scores: np.ndarray | None = None  # (rows,) float32
    likely: np.ndarray | None = None  # (rows,) int8

    def take(self, scanned: int) -> tuple[np.ndarray, np.ndarray]:
        """(scores, likely) for the first `scanned` rows (at most `rows`)."""
        if self.scores is None or self.likely is None:
            self.scores = np.empty(self.rows, dtype=np.float32)
            self.likely = np.empty(self.rows, dtype=np.int8)
        return self.scores[:scanned], self.likely[:scanned]


def variant_map(variant: int) -> tuple[np.ndarray, np.ndarray]:
    """(matrix, offset) of query variant 0-3 (as drawn, turned 180 degrees, mirrored, both)
    in normalized coordinates."""
    flip_x = variant in (1, 3)
    flip_y = variant in (1, 2)
    matrix = np.diag([-1.0 if flip_x else 1.0, -1.0 if flip_y else 1.0])
    return matrix, np.array([1.0 if flip_x else 0.0, 1.0 if flip_y else 0.0])


def query_variants(normalized: np.ndarray) -> np.ndarray:
    """(4, T, 2): the normalized query as drawn, turned 180 degrees, mirrored, and both."""
    return np.stack([normalized @ m.T + b for m, b in map(variant_map, range(4))])


def distance_table(normalized: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The query's exact distance from each node of the `kernels` table grid, and the index of
    the query point at that distance."""
    table = np.empty((kernels.TABLE_CELLS + 1,) * 2)
    owners = np.empty(table.shape, dtype=np.int32)
    kernels.distance_table(normalized, table, owners)
    return table, owners


def stage_sizes(paths: int) -> tuple[int, int, int]:
    """(candidates, refined, exact candidates) of a search over an index of `paths` paths: the
    scan passes on the candidates, the best `refined` candidate pairs by rough estimate get the
    fine one, and the best `exact candidates` rows by fine estimate the exact distance."""
    growth = max(1.0, paths / GROWTH_ROWS) ** GROWTH_POWER
    candidates = CANDIDATE_SHARE * min(paths, GROWTH_ROWS) * growth
    return (
        max(MIN_CANDIDATES, round(candidates)),
        round(REFINED * growth),
        round(EXACT_CANDIDATES * growth),
    )


def probe(
    arrays: IndexArrays, field_codes: np.ndarray, rows: int = PROBED_ROWS
) -> tuple[np.ndarray, ...]:
    """The row ranges of an index to scan for a query whose variants have these field codes:
    the lists nearest any variant, nearest first, until they hold `rows` rows, in row order
    (`kernels.scan_pieces`: starts, ends, at)."""
    sizes = np.diff(arrays.list_start)
    if len(sizes) == 1 or rows >= len(arrays):
        chosen = np.arange(len(sizes))
    else:
        gaps = (arrays.centroids**2).sum(axis=1) - 2 * field_codes @ arrays.centroids.T
        order = np.argsort(gaps.min(axis=0), kind="stable")
        enough = np.searchsorted(np.cumsum(sizes[order]), rows) + 1
        chosen = np.sort(order[:enough])
    return kernels.scan_pieces(arrays.list_start[chosen], arrays.list_start[chosen + 1])


def allowed_rows(
    transmission: np.ndarray,
    n_joints: np.ndarray | None,
    min_transmission: float = 0.0,
    max_joints: int | None = None,
) -> np.ndarray | None:
    """(N,) bool: which paths a query may answer with, those whose `transmission` keeps
    `min_transmission` degrees (when above 0) and whose reduced mechanism has at most
    `max_joints` joints (when given; `n_joints` counts them and is read only then); None when
    every path may."""
    allowed = None
    if min_transmission > 0:
        allowed = transmission >= min_transmission
    if max_joints is not None:
        if n_joints is None:
            raise ValueError("max_joints needs the paths' joint counts (n_joints)")
        simple = n_joints <= max_joints
        allowed = simple if allowed is None else allowed & simple
    return allowed


def candidates(
    arrays: IndexArrays,
    levels: np.ndarray,
    count: int,
    pieces: tuple[np.ndarray, ...],
    allowed: np.ndarray | None = None,
    buffers: ScanBuffers | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """About `count` rows of the scanned `pieces` (`probe`) whose scan score (at their best
    variant) against the query's `levels` table is least (every allowed row when `count`
    reaches their number); and for each, 4 * its likeliest variant + the second likeliest if
    nearly as likely (`kernels.sketch_scan`), or -1 when every allowed row is returned. Only
    rows `allowed` (N,) bool (`allowed_rows`; None: all) are passed on. The scan writes into
    `buffers` (None: new ones, for this call only)."""
    if count >= (len(arrays) if allowed is None else np.count_nonzero(allowed)):
        rows = np.arange(len(arrays)) if allowed is None else np.flatnonzero(allowed)
        return rows, np.full(len(rows), -1, dtype=np.int8)
    starts, ends, at = pieces
    scanned = int(at[-1] + ends[-1] - starts[-1])
    scores, likely = (buffers or ScanBuffers(len(arrays))).take(scanned)
    kernels.sketch_scan(
        arrays.sketches, starts, ends, at, levels, SCAN_SLOTS, VARIANT_MARGIN, scores, likely
    )
    if allowed is not None:
        kept = np.concatenate([allowed[s:e] for s, e in zip(starts, ends, strict=True)])
        scores[~kept] = np.inf
    positions = _about_least(scores, count)
    positions = positions[np.isfinite(scores[positions])]
    piece = np.searchsorted(at, positions, side="right") - 1
    return starts[piece] + positions - at[piece], likely[positions]


def ranked(
    arrays: IndexArrays,
    normalized: np.ndarray,
    k: int,
    candidates_count: int | None = None,
    probed: int = PROBED_ROWS,
    allowed: np.ndarray | None = None,
    buffers: ScanBuffers | None = None,
) -> list[tuple[int, float, int]]:
    """The k best (row, chamfer, variant) of an index's `arrays`, best first, for a
    normalized query, among the rows `allowed` (`allowed_rows`; None: all); the scan of the
    lists nearest it, `probed` rows, passes on `candidates_count` paths (by default as
    `stage_sizes` says), writing into `buffers` (None: new ones)."""
    default_candidates, refined, exact_count = stage_sizes(len(arrays))
    count = candidates_count or default_candidates
    variants = query_variants(normalized)
    pieces = probe(arrays, arrays.basis.query(variants), probed)
    table, owners = distance_table(normalized)
    levels = np.empty((kernels.SKETCH_LEVELS + 1,) * 2, dtype=np.float32)
    kernels.level_table(normalized, owners, levels)
    rows, likely = candidates(arrays, levels, count, pieces, allowed, buffers)
    if len(rows) == 0:
        return []
    # Each candidate with its likely variants (every variant on the exhaustive path).
    if likely[0] < 0:
        pair_rows, pair_variants = np.repeat(rows, 4), np.tile(np.arange(4), len(rows))
    else:
        first, second = likely // 4, likely % 4
        both = second != first
        pair_rows = np.concatenate([rows, rows[both]])
        pair_variants = np.concatenate([first, second[both]]).astype(np.int64)
    if len(pair_rows) > refined:  # a rough estimate of every pair first
        rough = estimate(
            arrays, normalized, levels, pair_rows, pair_variants, kernels.ROUGH_SAMPLE, rough=True
        )
        best = np.argpartition(rough, refined)[:refined]
        pair_rows, pair_variants = pair_rows[best], pair_variants[best]
    fine = estimate(arrays, normalized, levels, pair_rows, pair_variants, QUERY_SAMPLE)
    # Rows by their best estimate (a row may come twice, once per variant).
    order = np.argsort(fine, kind="stable")
    _, first = np.unique(pair_rows[order], return_index=True)
    chosen = order[np.sort(first)][: max(exact_count, k)]
    return exact_finalists(arrays, variants, table, pair_rows[chosen], pair_variants[chosen], k)


def estimate(
    arrays: IndexArrays,
    normalized: np.ndarray,
    levels: np.ndarray,
    rows: np.ndarray,
    variants: np.ndarray,
    sample_size: int,
    rough: bool = False,
) -> np.ndarray:
    """Estimated chamfer distances of (row, variant) pairs from the paths' sketches (their
    leading half only, if `rough`), measured from `sample_size` query points."""
    picked = normalized[spread_indices(len(normalized), sample_size)]
    sample = np.rint(picked * kernels.SKETCH_LEVELS).astype(np.int32)
    used = kernels.ROUGH_POINTS if rough else kernels.SKETCH_POINTS
    midpoints = _NO_MIDPOINTS if rough else kernels.sketch_midpoints(arrays.steps)
    out = np.empty(len(rows))
    kernels.sketch_chamfer(sample, levels, arrays.sketches, rows, variants, used, midpoints, out)
    return out


def exact_finalists(
    arrays: IndexArrays,
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
        points = arrays.paths(rows)
    local = np.arange(len(rows))
    distances = exact_pairs(variants, points, local, likely)
    bounds = np.empty((len(rows), 4))
    kernels.path_to_query_bounds(table, points, bounds)
    last = min(k, len(rows)) - 1
    kth = np.partition(distances, last)[last]
    bounds[local, likely] = np.inf
    bounds -= ROUNDING
    able = (bounds < distances[:, None]) & (bounds <= kth)
    more, more_variants = np.nonzero(able)
    if len(more):
        measured = exact_pairs(variants, points, more, more_variants)
        local = np.concatenate([local, more])
        likely = np.concatenate([likely, more_variants])
        distances = np.concatenate([distances, measured])
    rows = np.asarray(rows)[local]
    return best_rows(rows, arrays.path_ids(rows), likely, distances, k)


def exact_pairs(
    variants: np.ndarray, points: np.ndarray, rows: np.ndarray, which: np.ndarray
) -> np.ndarray:
    """Exact chamfer distances between query variant which[i] and path points[rows[i]] (inf
    for a path that does not trace); many pairs are measured on every CPU the process was
    given (the kernel releases the GIL)."""
    distances = np.empty(len(rows))

    def measure(variant: int, block: np.ndarray) -> None:
        distances[block] = chamfer_to_many(variants[variant], points[rows[block]])

    blocks = []
    for variant in range(4):
        chosen = np.flatnonzero(which == variant)
        parts = max(1, len(chosen) // 2048)
        blocks += [(variant, block) for block in np.array_split(chosen, parts) if len(block)]
    if len(rows) > 4096:  # worth the threads (a query's few exact candidates are not)
        with ThreadPoolExecutor(usable_cpus()) as pool:
            list(pool.map(lambda job: measure(*job), blocks))
    else:
        for job in blocks:
            measure(*job)
    # A path that no longer traces (damaged data) is never an answer.
    return np.nan_to_num(distances, nan=np.inf)


def best_rows(
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


def spread_indices(length: int, count: int) -> np.ndarray:
    """Up to `count` distinct indices evenly over range(length)."""
    return np.unique(np.linspace(0, length - 1, count).round().astype(int))


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
