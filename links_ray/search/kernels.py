"""Compiled kernels of retrieval: distance fields (for the coarse lists), sketches, the sketch
scan, and the chamfer estimates and lower bounds against a query. Pure numpy/numba;
`search.build`, `search.query` and `search.brute_force` call them.

Every kernel compares candidates with the query *as drawn*: a query variant (turned 180
degrees, mirrored, both) is an isometry that is its own inverse, so the distance from a
candidate point to a variant of the query equals the distance from the same-variant image of
that point to the query. Variant v flips x when v is 1 or 3 and y when v is 1 or 2, in
normalized coordinates (x -> 1 - x, y -> 1 - y).

A query's *distance table* holds its exact distance from every node of a fine grid over
[TABLE_LO, TABLE_HI]^2, and which query point is at that distance (its *owner*). Between
nodes the distance is estimated as the distance to the nearest of the four corners' owners
(`_owned_distance`: nearly always exact, never too small), and bounded below by the distance
being 1-Lipschitz: d(p) >= d(node) - |p - node| for each node.

A path's *sketch* is SKETCH_POINTS of its points, evenly spaced in time, each coordinate
rounded to one of SKETCH_LEVELS + 1 levels over [0, 1] and stored as uint8: 256 bytes against
1,600 for the whole path. Its even points come first (x levels of points 0, 2, 4, ..., then of
points 1, 3, ...; the y levels likewise after all x levels), so the leading ROUGH_POINTS of
each half are a coarser sketch of their own, in half the cache lines. With 255 levels a
variant's flip is `level ^ 255`, and the query's distance from every level point
(`_level_table`) is read without arithmetic.

The kernels that visit rows in an arbitrary order `prefetch` the rows a few steps ahead:
without it they wait on memory most of the time.

Each kernel is called from Python through its entry point of the same name without the
underscore, which checks the buffers' shapes, types and the rows they index first
(`buffers.check_buffer`): numba checks no bounds.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from llvmlite import binding as llvm
from llvmlite import ir
from numba import njit, prange, types
from numba.core import cgutils
from numba.extending import intrinsic

from links_ray.engine.buffers import check_buffer, check_indices

#: Descriptor grid: GRID x GRID nodes spanning [0, 1]^2 (node spacing 1 / (GRID - 1)).
GRID = 24
#: Query distance table: TABLE_CELLS x TABLE_CELLS cells over [TABLE_LO, TABLE_HI]^2.
TABLE_CELLS = 128
TABLE_LO, TABLE_HI = -0.05, 1.05
#: Rows per parallel chunk: large enough that scheduling costs nothing.
_CHUNK = 4096
#: Points and coordinate levels of a path's sketch (255: all ones in uint8, see
#: `_sketch_chamfer`), and the points of its coarser leading part.
SKETCH_POINTS, SKETCH_LEVELS, ROUGH_POINTS = 128, 255, 64
#: Query points the rough estimate measures from (evenly along the query).
ROUGH_SAMPLE = 32
#: How many rows ahead the gathering kernels prefetch.
_AHEAD = 8
# Pointers became opaque in LLVM 15, and the intrinsic's name says the pointer type.
_PREFETCH = "llvm.prefetch.p0" if llvm.llvm_version_info >= (15,) else "llvm.prefetch.p0i8"


@intrinsic
def prefetch(
    typingctx: object, array: types.Array, row: types.Integer, column: types.Integer
) -> tuple:
    """`prefetch(array, row, column)` in compiled code: hint the CPU to load the cache line
    holding array[row, column] (a 2-D array) for reading. It never faults and changes no
    result; it only saves waiting when that element is read soon after."""
    signature = types.void(array, row, column)

    def codegen(context: object, builder: object, sig: object, args: tuple) -> object:
        array_type = sig.args[0]
        view = context.make_array(array_type)(context, builder, args[0])
        pointer = cgutils.get_item_pointer(
            context, builder, array_type, view, [args[1], args[2]], wraparound=False
        )
        byte_pointer = ir.IntType(8).as_pointer()
        i32 = ir.IntType(32)
        function_type = ir.FunctionType(ir.VoidType(), [byte_pointer, i32, i32, i32])
        function = cgutils.get_or_insert_function(builder.module, function_type, _PREFETCH)
        # Arguments: address, read (0), high temporal locality (3), data cache (1).
        builder.call(function, [builder.bitcast(pointer, byte_pointer), i32(0), i32(3), i32(1)])
        return context.get_dummy_value()

    return signature, codegen


@njit(cache=True, inline="always")
def _flip(x: float, y: float, variant: int) -> tuple[float, float]:
    if variant == 1 or variant == 3:
        x = 1.0 - x
    if variant == 1 or variant == 2:
        y = 1.0 - y
    return x, y


def _distance_fields(paths: np.ndarray, stride: int, fields: np.ndarray) -> None:
    """Per path: its distance field at the GRID x GRID nodes (using every `stride`-th point)."""
    step = 1.0 / (GRID - 1)
    count = paths.shape[1]
    for p in prange(paths.shape[0]):
        for a in range(GRID):
            for b in range(GRID):
                best = np.inf
                for t in range(0, count, stride):
                    dx = paths[p, t, 0] - a * step
                    dy = paths[p, t, 1] - b * step
                    best = min(best, dx * dx + dy * dy)
                fields[p, a * GRID + b] = math.sqrt(best)


#: For many paths; the serial twin serves a single query without waking threads.
_distance_fields_parallel = njit(cache=True, nogil=True, parallel=True)(_distance_fields)
_distance_fields_serial = njit(cache=True, nogil=True)(_distance_fields)


@njit(cache=True, inline="always")
def _least_two(
    a: int, sa: float, b: int, sb: float, c: int, sc: float, d: int, sd: float
) -> tuple[int, float, int, float]:
    """(index, score) of the least and of the second least of four scores."""
    if sb < sa:
        a, sa, b, sb = b, sb, a, sa
    if sd < sc:
        c, sc, d, sd = d, sd, c, sc
    if sa <= sc:
        return (a, sa, b, sb) if sb <= sc else (a, sa, c, sc)
    return (c, sc, d, sd) if sd < sa else (c, sc, a, sa)


@njit(cache=True, nogil=True, parallel=True, fastmath=True)
def _sketch_scan(
    sketches: np.ndarray,
    starts: np.ndarray,
    ends: np.ndarray,
    at: np.ndarray,
    levels: np.ndarray,
    slots: np.ndarray,
    margin: float,
    out: np.ndarray,
    likely: np.ndarray,
) -> None:
    """For the rows i of each range starts[j]:ends[j] (pieces of a few thousand rows, so the
    threads share them evenly), at o = at[j] + i - starts[j]: out[o] = the least over the four
    variants of the mean distance to the query (`levels`, its `_level_table`) of the sketch
    points stored at `slots`; likely[o] = 4 * that variant + the second least variant if its
    mean is within `margin`, else the least again.

    It is the path-to-query half of the chamfer distance, sampled: a path near the query has
    every point near it, and each point's distance is read from the table almost exactly.
    """
    n = slots.shape[0]
    flip = np.uint8(SKETCH_LEVELS)
    for j in prange(starts.shape[0]):
        base = at[j] - starts[j]
        for i in range(starts[j], ends[j]):
            s0 = np.float32(0.0)
            s1 = np.float32(0.0)
            s2 = np.float32(0.0)
            s3 = np.float32(0.0)
            for k in range(n):
                x = sketches[i, slots[k]]
                y = sketches[i, SKETCH_POINTS + slots[k]]
                # Variant 1 flips x and y, 2 flips y, 3 flips x (see the module's docstring).
                s0 += levels[x, y]
                s1 += levels[x ^ flip, y ^ flip]
                s2 += levels[x, y ^ flip]
                s3 += levels[x ^ flip, y]
            first, low, second, high = _least_two(0, s0, 1, s1, 2, s2, 3, s3)
            out[base + i] = low / n
            likely[base + i] = 4 * first + (second if (high - low) / n < margin else first)


def scan_pieces(
    starts: np.ndarray, ends: np.ndarray, piece: int = _CHUNK
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Row ranges cut into pieces of at most `piece` rows for `_sketch_scan`: (starts, ends,
    at), `at` where each piece's scores begin in the output."""
    lengths = ends - starts
    counts = (lengths + piece - 1) // piece
    first = np.repeat(starts, counts)
    within = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    piece_starts = first + within * piece
    piece_ends = np.minimum(piece_starts + piece, np.repeat(ends, counts))
    at = np.concatenate([[0], np.cumsum(piece_ends - piece_starts)[:-1]])
    return piece_starts.astype(np.int64), piece_ends.astype(np.int64), at.astype(np.int64)


def scan_slots(points: int) -> np.ndarray:
    """Where `points` sketch points evenly spaced in time are stored (int64): every
    (SKETCH_POINTS / points)-th, all even ones, so in the leading ROUGH_POINTS slots."""
    stride = SKETCH_POINTS // points
    if stride < 2 or stride * points != SKETCH_POINTS:
        raise ValueError(f"scan points must divide {SKETCH_POINTS // 2}, got {points}")
    return np.array([_slot(s) for s in range(0, SKETCH_POINTS, stride)], dtype=np.int64)


@njit(cache=True, nogil=True, parallel=True, fastmath=True)
def _distance_table(query: np.ndarray, out: np.ndarray, owners: np.ndarray) -> None:
    """out[a, b] = distance from node (TABLE_LO + a * size, TABLE_LO + b * size) to the query,
    and owners[a, b] = the index of the query point at that distance; out is square, of
    TABLE_CELLS + 1 nodes a side for the search (any number for `_nearest_node_bounds`)."""
    nodes = out.shape[0]
    size = (TABLE_HI - TABLE_LO) / (nodes - 1)
    for a in prange(nodes):
        x = TABLE_LO + a * size
        nearest = np.full(nodes, np.inf)
        owner = np.zeros(nodes, dtype=np.int32)
        # Over the column of nodes innermost, so the loop vectorizes.
        for i in range(query.shape[0]):
            dx = query[i, 0] - x
            dx2 = dx * dx
            qy = query[i, 1]
            for b in range(nodes):
                dy = qy - (TABLE_LO + b * size)
                d = dx2 + dy * dy
                closer = d < nearest[b]
                nearest[b] = d if closer else nearest[b]
                owner[b] = i if closer else owner[b]
        for b in range(nodes):
            out[a, b] = math.sqrt(nearest[b])
            owners[a, b] = owner[b]


@njit(cache=True, inline="always")
def _cell(x: float, y: float) -> tuple[int, int, float, float]:
    """The table cell holding (x, y) and the position inside it in [0, 1); a = -1 if outside."""
    scale = TABLE_CELLS / (TABLE_HI - TABLE_LO)
    fx = (x - TABLE_LO) * scale
    fy = (y - TABLE_LO) * scale
    if not (0.0 <= fx < TABLE_CELLS and 0.0 <= fy < TABLE_CELLS):
        return -1, -1, 0.0, 0.0
    a = int(fx)
    b = int(fy)
    return a, b, fx - a, fy - b


@njit(cache=True, inline="always")
def _nearest(query: np.ndarray, x: float, y: float) -> float:
    best = np.inf
    for i in range(query.shape[0]):
        dx = query[i, 0] - x
        dy = query[i, 1] - y
        best = min(best, dx * dx + dy * dy)
    return math.sqrt(best)


@njit(cache=True)
def _sketch_time(s: int, steps: int) -> int:
    """The step of a path of `steps` points that time-ordered sketch point s holds."""
    return int(s * (steps - 1) / (SKETCH_POINTS - 1) + 0.5)


@njit(cache=True, inline="always")
def _slot(s: int) -> int:
    """Where time-ordered sketch point s is stored: even points first."""
    return s // 2 + (s % 2) * (SKETCH_POINTS // 2)


@njit(cache=True, nogil=True, parallel=True)
def _sketch_paths(points: np.ndarray, out: np.ndarray) -> None:
    """out[p] = the sketch of normalized path p (T, 2): the levels of SKETCH_POINTS points
    evenly spaced in time, even points first, x levels first, then y."""
    count = points.shape[1]
    for p in prange(points.shape[0]):
        for s in range(SKETCH_POINTS):
            t = _sketch_time(s, count)
            slot = _slot(s)
            for axis in range(2):
                level = math.floor(points[p, t, axis] * SKETCH_LEVELS + 0.5)
                out[p, axis * SKETCH_POINTS + slot] = min(max(level, 0), SKETCH_LEVELS)


@njit(cache=True, inline="always")
def _owned_distance(query: np.ndarray, owners: np.ndarray, x: float, y: float) -> float:
    """The distance from (x, y) to the nearest of the query points that own the corners of
    its table cell: the exact distance to the query unless its nearest point is none of
    these, and never less. Outside the table, the exact distance."""
    a, b, _, _ = _cell(x, y)
    if a < 0:
        return _nearest(query, x, y)
    best = np.inf
    for corner in range(4):
        i = owners[a + corner // 2, b + corner % 2]
        dx = query[i, 0] - x
        dy = query[i, 1] - y
        best = min(best, dx * dx + dy * dy)
    return math.sqrt(best)


@njit(cache=True, nogil=True, parallel=True)
def _level_table(query: np.ndarray, owners: np.ndarray, out: np.ndarray) -> None:
    """out[i, j] = the distance from (i, j) / SKETCH_LEVELS to the query (`_owned_distance`):
    from every point a sketch can hold."""
    for i in prange(SKETCH_LEVELS + 1):
        for j in range(SKETCH_LEVELS + 1):
            out[i, j] = _owned_distance(query, owners, i / SKETCH_LEVELS, j / SKETCH_LEVELS)


@functools.cache
def sketch_midpoints(steps: int) -> np.ndarray:
    """The time-ordered sketch points s (int32) of a path of `steps` points that are more than
    one step before the next (s + 1): a midpoint between them stands in for what the sketch
    left out (`_sketch_chamfer`). At 200 steps, 72 of the 127 gaps. Made once per `steps` and
    shared: not to be written to."""
    times = np.array([_sketch_time(s, steps) for s in range(SKETCH_POINTS)])
    return np.flatnonzero(np.diff(times) >= 2).astype(np.int32)


@njit(cache=True, nogil=True, parallel=True, fastmath=True)
def _sketch_chamfer(
    sample: np.ndarray,
    levels: np.ndarray,
    sketches: np.ndarray,
    rows: np.ndarray,
    variants: np.ndarray,
    used: int,
    midpoints: np.ndarray,
    out: np.ndarray,
) -> None:
    """out[r] estimates chamfer(query variant `variants[r]`, path `rows[r]`) from the leading
    `used` points of the path's sketch (ROUGH_POINTS or SKETCH_POINTS): query to path from
    the query points `sample` (S, 2) int32, in levels; path to query from `levels` (the
    query's `_level_table`).

    With the whole sketch, `midpoints` (`sketch_midpoints`) adds the midpoint between each
    listed point and the next, so the estimate sees as many points as the path has: a query
    point's distance to the nearest of 128 points overstates its distance to the nearest of
    200 by about a quarter of the wider spacing, and by how much depends on where each path's
    points fall, which decides many of the near ties the fine estimate would otherwise lose.
    A midpoint's distance to the query is its ends' mean. Pass no midpoints with a partial
    sketch.
    """
    count = rows.shape[0]
    taken = sample.shape[0]
    extra = midpoints.shape[0]
    total = used + extra
    # In half levels, so that midpoints are integers too.
    doubled = 2 * sample
    for chunk in prange((count + 255) // 256):
        xs = np.empty(total, dtype=np.int32)
        ys = np.empty(total, dtype=np.int32)
        near = np.empty(used, dtype=np.float32)
        end = min(count, (chunk + 1) * 256)
        for r in range(chunk * 256, end):
            if r + _AHEAD < end:
                ahead = rows[r + _AHEAD]
                prefetch(sketches, ahead, 0)
                prefetch(sketches, ahead, used - 1)
                prefetch(sketches, ahead, SKETCH_POINTS)
                prefetch(sketches, ahead, SKETCH_POINTS + used - 1)
            p = rows[r]
            # A flip maps level l to SKETCH_LEVELS - l, which is l ^ 255 for 255 levels.
            flip_x, flip_y = _flip(0.0, 0.0, variants[r])
            mask_x = np.uint8(SKETCH_LEVELS * int(flip_x))
            mask_y = np.uint8(SKETCH_LEVELS * int(flip_y))
            to_query = np.float32(0.0)
            for t in range(used):
                x = sketches[p, t] ^ mask_x
                y = sketches[p, SKETCH_POINTS + t] ^ mask_y
                near[t] = levels[x, y]
                to_query += near[t]
                xs[t] = 2 * np.int32(x)
                ys[t] = 2 * np.int32(y)
            for m in range(extra):
                a = _slot(midpoints[m])
                b = _slot(midpoints[m] + 1)
                xs[used + m] = (xs[a] + xs[b]) // 2
                ys[used + m] = (ys[a] + ys[b]) // 2
                to_query += np.float32(0.5) * (near[a] + near[b])
            # In integers, so the minimum over the sketch vectorizes exactly.
            to_path = np.float32(0.0)
            for i in range(taken):
                best = np.int32(2**30)
                for t in range(total):
                    dx = doubled[i, 0] - xs[t]
                    dy = doubled[i, 1] - ys[t]
                    best = min(best, dx * dx + dy * dy)
                to_path += math.sqrt(np.float32(best))
            out[r] = to_path / (2 * taken * SKETCH_LEVELS) + to_query / total


@njit(cache=True, nogil=True, parallel=True)
def _path_to_query_bounds(table: np.ndarray, points: np.ndarray, out: np.ndarray) -> None:
    """out[p, v] <= the mean distance from path p, as variant v, to the query: a lower bound
    of the chamfer distance (its path-to-query half)."""
    size = (TABLE_HI - TABLE_LO) / TABLE_CELLS
    count = points.shape[1]
    for chunk in prange((points.shape[0] + 255) // 256):
        for p in range(chunk * 256, min(points.shape[0], (chunk + 1) * 256)):
            for v in range(4):
                total = 0.0
                for t in range(count):
                    x, y = _flip(np.float64(points[p, t, 0]), np.float64(points[p, t, 1]), v)
                    a, b, fx, fy = _cell(x, y)
                    if a < 0:
                        continue  # outside the table: bounded by zero
                    ux = fx * size
                    uy = fy * size
                    vx = size - ux
                    vy = size - uy
                    bound = max(
                        max(
                            table[a, b] - math.sqrt(ux * ux + uy * uy),
                            table[a + 1, b] - math.sqrt(vx * vx + uy * uy),
                        ),
                        max(
                            table[a, b + 1] - math.sqrt(ux * ux + vy * vy),
                            table[a + 1, b + 1] - math.sqrt(vx * vx + vy * vy),
                        ),
                    )
                    total += max(bound, 0.0)
                out[p, v] = total / count


@njit(cache=True, nogil=True, parallel=True, fastmath=True)
def _nearest_node_bounds(tables: np.ndarray, points: np.ndarray, out: np.ndarray) -> None:
    """out[p, v, q] <= the mean distance from path p, as variant v, to query q, for many
    queries at once: `tables` (nodes, nodes, Q) float32 holds each query's `_distance_table`
    over [TABLE_LO, TABLE_HI]^2, queries last, so the one node a path point needs gives all
    queries' distances from one place in memory. Each point is bounded from its nearest node
    (the distance is 1-Lipschitz): d(point) >= d(node) - |point - node|.

    Sums are float32: a caller comparing bounds allows for their rounding.
    """
    nodes = tables.shape[0]
    size = (TABLE_HI - TABLE_LO) / (nodes - 1)
    queries = tables.shape[2]
    count = points.shape[1]
    for chunk in prange((points.shape[0] + 63) // 64):
        total = np.empty((4, queries), dtype=np.float32)
        for p in range(chunk * 64, min(points.shape[0], (chunk + 1) * 64)):
            total[:] = 0.0
            for t in range(count):
                for v in range(4):
                    x, y = _flip(np.float64(points[p, t, 0]), np.float64(points[p, t, 1]), v)
                    a = math.floor((x - TABLE_LO) / size + 0.5)
                    b = math.floor((y - TABLE_LO) / size + 0.5)
                    if a < 0 or b < 0 or a >= nodes or b >= nodes:
                        continue  # outside the table: bounded by zero
                    dx = x - (TABLE_LO + a * size)
                    dy = y - (TABLE_LO + b * size)
                    reach = np.float32(math.sqrt(dx * dx + dy * dy))
                    for q in range(queries):
                        total[v, q] += max(tables[a, b, q] - reach, np.float32(0.0))
            for v in range(4):
                for q in range(queries):
                    out[p, v, q] = total[v, q] / count


@njit(cache=True, nogil=True, parallel=True, fastmath=True)
def _sample_to_path_sums(
    sample: np.ndarray, points: np.ndarray, rows: np.ndarray, variants: np.ndarray, out: np.ndarray
) -> None:
    """out[r] = the sum over the query points `sample` (S, 2) of their distance to path
    rows[r] as variant variants[r]. Over a subset of a query's points, divided by all its
    points, it bounds the query-to-path half of the chamfer distance from below."""
    count = points.shape[1]
    taken = sample.shape[0]
    for chunk in prange((rows.shape[0] + 63) // 64):
        nearest = np.empty(taken)
        for r in range(chunk * 64, min(rows.shape[0], (chunk + 1) * 64)):
            p = rows[r]
            shift_x, shift_y = _flip(0.0, 0.0, variants[r])
            sign_x = 1.0 - 2.0 * shift_x
            sign_y = 1.0 - 2.0 * shift_y
            nearest[:] = np.inf
            for t in range(count):
                px = shift_x + sign_x * points[p, t, 0]
                py = shift_y + sign_y * points[p, t, 1]
                for i in range(taken):
                    dx = sample[i, 0] - px
                    dy = sample[i, 1] - py
                    nearest[i] = min(nearest[i], dx * dx + dy * dy)
            total = 0.0
            for i in range(taken):
                total += math.sqrt(nearest[i])
            out[r] = total


# -- entry points ------------------------------------------------------------------------------

#: A sketch's bytes: x levels, then y levels.
SKETCH_BYTES = 2 * SKETCH_POINTS
#: Sides of a level table: every level a sketch coordinate can hold.
LEVEL_SIDE = SKETCH_LEVELS + 1
#: Sides of the search's distance table, in nodes.
TABLE_NODES = TABLE_CELLS + 1


def _check_paths(name: str, points: np.ndarray) -> tuple[int, int]:
    """(P, T) of paths `points` (P, T, 2), T >= 1."""
    check_buffer(name, points, (None, None, 2), "f")
    if points.shape[1] == 0:
        raise ValueError(f"{name} must hold at least one point per path, got shape {points.shape}")
    return points.shape[0], points.shape[1]


def _check_query(name: str, query: np.ndarray) -> int:
    """The points of a query `query` (Q, 2), Q >= 1."""
    check_buffer(name, query, (None, 2), "f")
    if query.shape[0] == 0:
        raise ValueError(f"{name} must hold at least one point, got shape {query.shape}")
    return query.shape[0]


def distance_fields(paths: np.ndarray, stride: int, fields: np.ndarray) -> None:
    """fields (P, GRID * GRID): the distance field of each path of `paths` (P, T, 2) at the
    grid's nodes, from every `stride`-th point; on all cores."""
    _check_fields(paths, stride, fields)
    _distance_fields_parallel(paths, stride, fields)


def distance_fields_serial(paths: np.ndarray, stride: int, fields: np.ndarray) -> None:
    """`distance_fields` on the calling thread alone (a query's few paths)."""
    _check_fields(paths, stride, fields)
    _distance_fields_serial(paths, stride, fields)


def _check_fields(paths: np.ndarray, stride: int, fields: np.ndarray) -> None:
    count, _ = _check_paths("paths", paths)
    if not (isinstance(stride, int | np.integer) and stride >= 1):
        raise ValueError(f"stride must be an integer >= 1, got {stride!r}")
    check_buffer("fields", fields, (count, GRID * GRID), "f")


def sketch_scan(
    sketches: np.ndarray,
    starts: np.ndarray,
    ends: np.ndarray,
    at: np.ndarray,
    levels: np.ndarray,
    slots: np.ndarray,
    margin: float,
    out: np.ndarray,
    likely: np.ndarray,
) -> None:
    """Scores `out` and likely variants `likely` of the rows starts[j]:ends[j] of `sketches`
    (R, SKETCH_BYTES) uint8, packed from at[j] on, against a query's `levels` table
    (`_sketch_scan`)."""
    check_buffer("sketches", sketches, (None, SKETCH_BYTES), np.uint8)
    check_buffer("starts", starts, (None,), "iu")
    pieces = starts.shape[0]
    check_buffer("ends", ends, (pieces,), "iu")
    check_buffer("at", at, (pieces,), "iu")
    check_buffer("levels", levels, (LEVEL_SIDE, LEVEL_SIDE), "f")
    check_buffer("slots", slots, (None,), "iu")
    check_indices("slots", slots, SKETCH_POINTS, "a sketch's points")
    check_buffer("out", out, (None,), "f")
    if pieces:
        rows = sketches.shape[0]
        if not ((starts >= 0) & (starts <= ends) & (ends <= rows)).all():
            raise ValueError(f"starts and ends must be ranges of the {rows} rows of sketches")
        if not ((at >= 0) & (at + (ends - starts) <= out.shape[0])).all():
            raise ValueError(
                f"out must hold every range's scores from its `at` on: {out.shape[0]} is too few"
            )
    check_buffer("likely", likely, (out.shape[0],), np.int8)
    _sketch_scan(sketches, starts, ends, at, levels, slots, margin, out, likely)


def distance_table(query: np.ndarray, out: np.ndarray, owners: np.ndarray) -> None:
    """out (N, N): the distance from each node of an N x N grid over [TABLE_LO, TABLE_HI]^2 to
    `query` (Q, 2), and owners (N, N) int32 the query point at that distance."""
    _check_query("query", query)
    check_buffer("out", out, (None, None), "f")
    nodes = out.shape[0]
    if nodes < 2 or out.shape[1] != nodes:
        raise ValueError(f"out must be square, at least 2 nodes a side, got shape {out.shape}")
    check_buffer("owners", owners, (nodes, nodes), np.int32)
    _distance_table(query, out, owners)


def sketch_paths(points: np.ndarray, out: np.ndarray) -> None:
    """out (P, SKETCH_BYTES) uint8: the sketch of each normalized path of `points` (P, T, 2)."""
    count, _ = _check_paths("points", points)
    check_buffer("out", out, (count, SKETCH_BYTES), np.uint8)
    _sketch_paths(points, out)


def level_table(query: np.ndarray, owners: np.ndarray, out: np.ndarray) -> None:
    """out (LEVEL_SIDE, LEVEL_SIDE): the distance from every point a sketch can hold to `query`
    (Q, 2), whose `distance_table` owners (TABLE_NODES, TABLE_NODES) are given."""
    points = _check_query("query", query)
    check_buffer("owners", owners, (TABLE_NODES, TABLE_NODES), "iu")
    check_indices("owners", owners, points, "the query's points")
    check_buffer("out", out, (LEVEL_SIDE, LEVEL_SIDE), "f")
    _level_table(query, owners, out)


def sketch_chamfer(
    sample: np.ndarray,
    levels: np.ndarray,
    sketches: np.ndarray,
    rows: np.ndarray,
    variants: np.ndarray,
    used: int,
    midpoints: np.ndarray,
    out: np.ndarray,
) -> None:
    """out[r]: the chamfer distance of query variant variants[r] and path rows[r], estimated
    from the leading `used` points of its sketch in `sketches` (R, SKETCH_BYTES) uint8 and
    `midpoints`, from query points `sample` (S, 2) int32 and `levels` (`_sketch_chamfer`)."""
    check_buffer("sample", sample, (None, 2), np.int32)
    check_buffer("levels", levels, (LEVEL_SIDE, LEVEL_SIDE), "f")
    check_buffer("sketches", sketches, (None, SKETCH_BYTES), np.uint8)
    check_buffer("rows", rows, (None,), "iu")
    count = rows.shape[0]
    check_indices("rows", rows, sketches.shape[0], "the rows of sketches")
    check_buffer("variants", variants, (count,), "iu")
    if used not in (ROUGH_POINTS, SKETCH_POINTS):
        raise ValueError(f"used must be {ROUGH_POINTS} or {SKETCH_POINTS}, got {used!r}")
    check_buffer("midpoints", midpoints, (None,), "iu")
    if midpoints.shape[0] and used != SKETCH_POINTS:
        raise ValueError("midpoints must be empty with a partial sketch")
    check_indices("midpoints", midpoints, SKETCH_POINTS - 1, "a sketch's gaps")
    check_buffer("out", out, (count,), "f")
    _sketch_chamfer(sample, levels, sketches, rows, variants, used, midpoints, out)


def path_to_query_bounds(table: np.ndarray, points: np.ndarray, out: np.ndarray) -> None:
    """out (P, 4): a lower bound of the path-to-query half of the chamfer distance of each
    path of `points` (P, T, 2) in each variant, from the query's `distance_table` `table`
    (TABLE_NODES, TABLE_NODES)."""
    check_buffer("table", table, (TABLE_NODES, TABLE_NODES), "f")
    count, _ = _check_paths("points", points)
    check_buffer("out", out, (count, 4), "f")
    _path_to_query_bounds(table, points, out)


def nearest_node_bounds(tables: np.ndarray, points: np.ndarray, out: np.ndarray) -> None:
    """out (P, 4, Q): `path_to_query_bounds` of each path of `points` (P, T, 2) for each of Q
    queries at once, from their distance tables `tables` (N, N, Q) (`_nearest_node_bounds`)."""
    check_buffer("tables", tables, (None, None, None), "f")
    nodes, queries = tables.shape[0], tables.shape[2]
    if nodes < 2 or tables.shape[1] != nodes:
        raise ValueError(f"tables must be square, at least 2 nodes a side, got {tables.shape}")
    count, _ = _check_paths("points", points)
    check_buffer("out", out, (count, 4, queries), "f")
    _nearest_node_bounds(tables, points, out)


def sample_to_path_sums(
    sample: np.ndarray, points: np.ndarray, rows: np.ndarray, variants: np.ndarray, out: np.ndarray
) -> None:
    """out[r]: the summed distance of the query points `sample` (S, 2) to path rows[r] of
    `points` (P, T, 2) as variant variants[r]."""
    check_buffer("sample", sample, (None, 2), "f")
    paths, _ = _check_paths("points", points)
    check_buffer("rows", rows, (None,), "iu")
    check_indices("rows", rows, paths, "the paths of points")
    check_buffer("variants", variants, (rows.shape[0],), "iu")
    check_buffer("out", out, (rows.shape[0],), "f")
    _sample_to_path_sums(sample, points, rows, variants, out)
