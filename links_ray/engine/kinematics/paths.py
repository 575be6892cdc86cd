"""Coupler-path normalization, circle detection, bidirectional chamfer distance, and points
evenly spaced along a polyline.

Pure numpy/numba: no Ray and no other ``links_ray`` module, so it can run in any worker.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from links_ray.engine.buffers import check_buffer

__all__ = [
    "CIRCLE_VARIANCE_THRESHOLD",
    "chamfer",
    "chamfer_to_many",
    "circle_variance",
    "circle_variances",
    "even_along",
    "is_circle",
    "longest_chord",
    "normalization",
    "normalize_path",
    "normalize_paths",
]

CIRCLE_VARIANCE_THRESHOLD = 5e-4

# Points per bounding box in the longest-chord search: consecutive path or hull points are close
# together, so small boxes give tight bounds.
_BLOCK = 16

# Relative error bound of a floating-point 2-D orientation test (Shewchuk's ccwerrboundA is
# about 3.3e-16), with margin.
_ORIENT_EPS = 1e-15


# --------------------------------------------------------------------------- validation


def _as_float_array(value: object, name: str) -> np.ndarray:
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a numeric array: {exc}") from None
    if arr.dtype.kind not in "iuf":
        raise ValueError(f"{name} must be numeric, got dtype {arr.dtype}")
    return arr


def _count(points: int) -> str:
    return "1 point" if points == 1 else f"{points} points"


def _as_points(points: object, name: str, min_points: int) -> np.ndarray:
    arr = _as_float_array(points, name)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"{name} must have shape (T, 2), got {arr.shape}")
    if arr.shape[0] < min_points:
        raise ValueError(f"{name} must have at least {_count(min_points)}, got {arr.shape[0]}")
    arr = np.ascontiguousarray(arr, dtype=np.float64)
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} must be finite (found NaN or inf)")
    return arr


def _as_batch(paths: object, name: str, min_points: int) -> np.ndarray:
    arr = _as_float_array(paths, name)
    if arr.ndim != 3 or arr.shape[2] != 2:
        raise ValueError(f"{name} must have shape (P, T, 2), got {arr.shape}")
    if arr.shape[1] < min_points:
        raise ValueError(
            f"{name} must have at least {_count(min_points)} per path, got {arr.shape[1]}"
        )
    # float32 (as stored in Parquet) is read as is: converting it is exact, copying it is not free.
    dtype = np.float32 if arr.dtype == np.float32 else np.float64
    return np.ascontiguousarray(arr, dtype=dtype)


# --------------------------------------------------------------------------- kernels


@numba.njit(cache=True, nogil=True)
def _prescale_into(src: np.ndarray, dst: np.ndarray) -> bool:
    """Copy src to dst times a power of two, max |coordinate| in [0.5, 1); False if not finite."""
    m = 0.0
    for k in range(src.shape[0]):
        x = src[k, 0]
        y = src[k, 1]
        if not (math.isfinite(x) and math.isfinite(y)):
            return False
        m = max(m, abs(x), abs(y))
    # Power-of-two scaling is exact, so the result is unchanged while squares cannot overflow.
    e = math.frexp(m)[1]
    if -1021 <= e <= 1021:
        # A product with a normal power of two rounds as ldexp does, at a fraction of its cost.
        factor = math.ldexp(1.0, -e)
        for k in range(src.shape[0]):
            dst[k, 0] = src[k, 0] * factor
            dst[k, 1] = src[k, 1] * factor
    else:
        for k in range(src.shape[0]):
            dst[k, 0] = math.ldexp(src[k, 0], -e)
            dst[k, 1] = math.ldexp(src[k, 1], -e)
    return True


@numba.njit(cache=True, nogil=True)
def _sq_dist(pts: np.ndarray, i: int, j: int) -> float:
    """Squared distance; the same value whichever way round i and j are."""
    dx = pts[j, 0] - pts[i, 0]
    dy = pts[j, 1] - pts[i, 1]
    return dx * dx + dy * dy


@numba.njit(cache=True, nogil=True)
def _farthest(pts: np.ndarray, idx: np.ndarray, start: int) -> int:
    """Position in idx of the point farthest from pts[start]."""
    best = -1.0
    pos = 0
    for k in range(idx.shape[0]):
        d = _sq_dist(pts, start, idx[k])
        if d > best:
            best = d
            pos = k
    return pos


@numba.njit(cache=True, nogil=True)
def _longest_chord(pts: np.ndarray, idx: np.ndarray) -> tuple[int, int]:
    """(i, j), i < j, of the farthest pair among pts[idx]; the lowest (i, j) on ties."""
    n = idx.shape[0]
    nb = (n + _BLOCK - 1) // _BLOCK
    box = np.empty((nb, 4))  # xmin, xmax, ymin, ymax per block
    box[:, 0] = np.inf
    box[:, 1] = -np.inf
    box[:, 2] = np.inf
    box[:, 3] = -np.inf
    for k in range(n):
        b = k // _BLOCK
        x = pts[idx[k], 0]
        y = pts[idx[k], 1]
        box[b, 0] = min(box[b, 0], x)
        box[b, 1] = max(box[b, 1], x)
        box[b, 2] = min(box[b, 2], y)
        box[b, 3] = max(box[b, 3], y)
    # A near-diameter pair up front lets the box bound skip most block pairs; the sentinel
    # indices make the scan below re-find the lowest pair at that distance.
    f1 = _farthest(pts, idx, idx[0])
    f2 = _farthest(pts, idx, idx[f1])
    best = _sq_dist(pts, idx[f1], idx[f2])
    lo = hi = pts.shape[0]
    for a in range(nb):
        for b in range(a, nb):
            # Rounding is monotone, so this bound is never below a pair's computed distance.
            dx = max(box[b, 1] - box[a, 0], box[a, 1] - box[b, 0])
            dy = max(box[b, 3] - box[a, 2], box[a, 3] - box[b, 2])
            if dx * dx + dy * dy < best:
                continue
            for u in range(a * _BLOCK, min(a * _BLOCK + _BLOCK, n)):
                iu = idx[u]
                # The same bound from one point to block b's box skips most points.
                ex = max(box[b, 1] - pts[iu, 0], pts[iu, 0] - box[b, 0])
                ey = max(box[b, 3] - pts[iu, 1], pts[iu, 1] - box[b, 2])
                if ex * ex + ey * ey < best:
                    continue
                for v in range(max(u + 1, b * _BLOCK), min(b * _BLOCK + _BLOCK, n)):
                    iv = idx[v]
                    d = _sq_dist(pts, iu, iv)
                    if d >= best:
                        i = min(iu, iv)
                        j = max(iu, iv)
                        if d > best or i < lo or (i == lo and j < hi):
                            best = d
                            lo = i
                            hi = j
    return lo, hi


@numba.njit(cache=True, nogil=True)
def _surely_not_left(pts: np.ndarray, o: int, a: int, b: int) -> bool:
    """True only if o -> a -> b is certainly a clockwise turn despite rounding."""
    left = (pts[a, 0] - pts[o, 0]) * (pts[b, 1] - pts[o, 1])
    right = (pts[a, 1] - pts[o, 1]) * (pts[b, 0] - pts[o, 0])
    return left - right < -_ORIENT_EPS * (abs(left) + abs(right))


@numba.njit(cache=True, nogil=True)
def _hull(pts: np.ndarray, order: np.ndarray) -> np.ndarray:
    """Convex hull indices, counter-clockwise, of distinct pts[order] sorted by (x, y).

    Points are popped only when certainly inside, so every true vertex is kept (and maybe a few
    nearly collinear extras): the chord search over the result is exact.
    """
    n = order.shape[0]
    hull = np.empty(2 * n, dtype=np.int64)
    k = 0
    for t in range(n):
        while k >= 2 and _surely_not_left(pts, hull[k - 2], hull[k - 1], order[t]):
            k -= 1
        hull[k] = order[t]
        k += 1
    lower = k + 1
    for t in range(n - 2, -1, -1):
        while k >= lower and _surely_not_left(pts, hull[k - 2], hull[k - 1], order[t]):
            k -= 1
        hull[k] = order[t]
        k += 1
    return hull[: k - 1]


@numba.njit(cache=True, nogil=True)
def _place(pts: np.ndarray, i: int, j: int, out: np.ndarray) -> None:
    """Write pts with chord (i, j) turned to +x, scaled to length 1 and the box centred at 0.5."""
    vx = pts[j, 0] - pts[i, 0]
    vy = pts[j, 1] - pts[i, 1]
    # Dividing by |v|^2 (not |v|) maps pts[j] - pts[i] to exactly (1, 0).
    l2 = vx * vx + vy * vy
    xmin = ymin = np.inf
    xmax = ymax = -np.inf
    for k in range(pts.shape[0]):
        qx = pts[k, 0] - pts[i, 0]
        qy = pts[k, 1] - pts[i, 1]
        x = (vx * qx + vy * qy) / l2
        y = (vx * qy - vy * qx) / l2
        out[k, 0] = x
        out[k, 1] = y
        xmin = min(xmin, x)
        xmax = max(xmax, x)
        ymin = min(ymin, y)
        ymax = max(ymax, y)
    sx = 0.5 - 0.5 * (xmin + xmax)
    sy = 0.5 - 0.5 * (ymin + ymax)
    for k in range(pts.shape[0]):
        out[k, 0] += sx
        out[k, 1] += sy


@numba.njit(cache=True, nogil=True)
def _has_extent(pts: np.ndarray) -> bool:
    """False if every point equals the first."""
    for k in range(1, pts.shape[0]):
        if pts[k, 0] != pts[0, 0] or pts[k, 1] != pts[0, 1]:
            return True
    return False


@numba.njit(cache=True, nogil=True)
def _normalize_batch(paths: np.ndarray, out: np.ndarray) -> int:
    """Normalize each path into out (NaN rows where no extent); index of a non-finite path or -1."""
    t = paths.shape[1]
    scaled = np.empty((t, 2))
    every = np.arange(t)
    for p in range(paths.shape[0]):
        if not _prescale_into(paths[p], scaled):
            return p
        if not _has_extent(scaled):
            out[p] = np.nan
            continue
        i, j = _longest_chord(scaled, every)
        _place(scaled, i, j, out[p])
    return -1


@numba.njit(cache=True, nogil=True)
def _circle_variances(paths: np.ndarray, out: np.ndarray) -> None:
    """out[p] = population variance of the distances of paths[p] from (0.5, 0.5)."""
    t = paths.shape[1]
    r = np.empty(t)
    for p in range(paths.shape[0]):
        s = 0.0
        for k in range(t):
            dx = paths[p, k, 0] - 0.5
            dy = paths[p, k, 1] - 0.5
            r[k] = math.sqrt(dx * dx + dy * dy)
            s += r[k]
        mean = s / t
        s = 0.0
        for k in range(t):
            s += (r[k] - mean) ** 2
        out[p] = s / t


@numba.njit(cache=True, nogil=True)
def _sweep(
    ax: np.ndarray,
    ay: np.ndarray,
    x: float,
    y: float,
    start: int,
    stop: int,
    step: int,
    best: float,
    arg: int,
) -> tuple[float, int]:
    """(least squared distance, its index) from (x, y) to a's points from `start` toward
    `stop`, starting from `best` at `arg`, until the x gap alone reaches the best."""
    for i in range(start, stop, step):
        dx = ax[i] - x
        if dx * dx >= best:
            break
        dy = ay[i] - y
        d = dx * dx + dy * dy
        if d < best:
            best, arg = d, i
    return best, arg


@numba.njit(cache=True, nogil=True)
def _nearest_sq(
    ax: np.ndarray,
    ay: np.ndarray,
    bx: np.ndarray,
    by: np.ndarray,
    bmin: np.ndarray,
    barg: np.ndarray,
) -> None:
    """bmin[j] = least squared distance from b[j] to any a point, barg[j] = that point's place
    in a; a is sorted by x.

    From b[j]'s place in a's x order outwards on both sides, stopping where the x gap alone
    reaches the best so far: no point past it is nearer. The least value is the one a
    comparison of every pair finds, bit for bit (the same differences, squared and summed).
    """
    n = ax.shape[0]
    for j in range(bx.shape[0]):
        x = bx[j]
        y = by[j]
        lo, hi = 0, n
        while lo < hi:
            middle = (lo + hi) >> 1
            if ax[middle] < x:
                lo = middle + 1
            else:
                hi = middle
        best, arg = _sweep(ax, ay, x, y, lo, n, 1, np.inf, 0)
        best, arg = _sweep(ax, ay, x, y, lo - 1, -1, -1, best, arg)
        bmin[j] = best
        barg[j] = arg


@numba.njit(cache=True, nogil=True)
def _sorted_by_x(points: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> bool:
    """Copy points (T, 2) into xs, ys in order of x; False if any coordinate is not finite."""
    order = np.argsort(points[:, 0])
    for k in range(order.shape[0]):
        xs[k] = points[order[k], 0]
        ys[k] = points[order[k], 1]
        if not (math.isfinite(xs[k]) and math.isfinite(ys[k])):
            return False
    return True


@numba.njit(cache=True, nogil=True)
def _mean_sqrt(v: np.ndarray) -> float:
    s = 0.0
    for k in range(v.shape[0]):
        s += math.sqrt(v[k])
    return s / v.shape[0]


@numba.njit(cache=True, nogil=True)
def _chamfer_to_many(query: np.ndarray, cands: np.ndarray, out: np.ndarray) -> int:
    """Chamfer from query to each candidate into out; index of a non-finite candidate or -1.

    Each side's nearest points are found in the other side sorted by x (`_nearest_sq`): a
    fraction of the work of comparing every pair, for the same sums in the same order.
    """
    tq = query.shape[0]
    t = cands.shape[1]
    qx = np.empty(tq)
    qy = np.empty(tq)
    _sorted_by_x(query, qx, qy)
    qmin = np.empty(tq)
    qarg = np.empty(tq, dtype=np.int64)
    cx = np.empty(t)
    cy = np.empty(t)
    cmin = np.empty(t)
    carg = np.empty(t, dtype=np.int64)
    # Each mean sums in the points' own order, as a plain loop over pairs would.
    query_x = np.empty(tq)
    query_y = np.empty(tq)
    for k in range(tq):
        query_x[k] = query[k, 0]
        query_y[k] = query[k, 1]
    path_x = np.empty(t)
    path_y = np.empty(t)
    for p in range(cands.shape[0]):
        if not _sorted_by_x(cands[p], cx, cy):
            return p
        for k in range(t):
            path_x[k] = cands[p, k, 0]
            path_y[k] = cands[p, k, 1]
        _nearest_sq(cx, cy, query_x, query_y, qmin, qarg)
        _nearest_sq(qx, qy, path_x, path_y, cmin, carg)
        out[p] = _mean_sqrt(qmin) + _mean_sqrt(cmin)
    return -1


# --------------------------------------------------------------------------- public API


def _distinct_sorted(pts: np.ndarray) -> np.ndarray:
    """Indices of pts sorted by (x, y), keeping the lowest index of each repeated point."""
    order = np.lexsort((pts[:, 1], pts[:, 0]))  # stable: equal points stay in index order
    s = pts[order]
    keep = np.ones(len(order), dtype=bool)
    keep[1:] = (s[1:] != s[:-1]).any(axis=1)
    return order[keep]


def _chord(points: object) -> tuple[np.ndarray, int, int]:
    """Validated points scaled by a power of two, and their longest chord (i, j)."""
    pts = _as_points(points, "points", 2)
    scaled = np.empty_like(pts)
    _prescale_into(pts, scaled)
    order = _distinct_sorted(scaled)
    if len(order) < 2:
        raise ValueError("points must not all be the same point (the path has no extent)")
    i, j = _longest_chord(scaled, _hull(scaled, order))
    return scaled, int(i), int(j)


def longest_chord(points: object) -> tuple[int, int]:
    """Indices (i, j), i < j, of the farthest pair of points; the lowest (i, j) on ties.

    Raises ValueError for input that is not T >= 2 finite points with some extent.
    """
    _, i, j = _chord(points)
    return i, j


def normalization(points: object) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`normalize_path` and the similarity that does it: (normalized, matrix, offset).

    `points @ matrix.T + offset` equals `normalized` up to rounding; `normalized` is exactly
    `normalize_path(points)`. The map turns, scales and moves, never mirrors, so a mechanism
    mapped by it traces the mapped path. Raises ValueError as `normalize_path` does.
    """
    pts = _as_points(points, "points", 2)
    scaled, i, j = _chord(pts)
    normalized = np.empty_like(scaled)
    _place(scaled, i, j, normalized)
    # The kernel worked on the points times 2**-e (as _prescale_into scaled them), so the
    # matrix takes that power of two in; multiplying by it rounds nothing.
    power = math.ldexp(1.0, -math.frexp(float(np.abs(pts).max()))[1])
    vx, vy = scaled[j] - scaled[i]
    matrix = np.array([[vx, vy], [-vy, vx]]) * (power / (vx * vx + vy * vy))
    # _place sends points[i] to the box shift itself, so normalized[i] is the offset there.
    offset = normalized[i] - pts[i] @ matrix.T
    return normalized, matrix, offset


def normalize_path(points: object) -> np.ndarray:
    """Normalize a path: longest chord horizontal with length 1, bounding box centred at 0.5.

    The chord points from its lower-index end to its higher-index end along +x; on ties the
    lowest index pair is used. Returns float64 (T, 2) in the input point order. Raises
    ValueError for input that is not T >= 2 finite points with some extent.
    """
    return normalization(points)[0]


def normalize_paths(paths: object) -> np.ndarray:
    """normalize_path over a batch (P, T, 2) -> float64 (P, T, 2).

    A path whose points are all the same has no extent and gives an all-NaN row instead of
    raising. Raises ValueError for a bad shape, T < 2 or any non-finite value.
    """
    arr = _as_batch(paths, "paths", 2)
    out = np.empty(arr.shape, dtype=np.float64)
    bad = _normalize_batch(arr, out)
    if bad >= 0:
        raise ValueError(f"paths must be finite (path {bad} has NaN or inf)")
    return out


def circle_variance(normalized_points: object) -> float:
    """Population variance of the distances of the points from (0.5, 0.5)."""
    pts = _as_points(normalized_points, "normalized_points", 1)
    out = np.empty(1)
    _circle_variances(pts[None], out)
    return float(out[0])


def circle_variances(paths: object) -> np.ndarray:
    """circle_variance of each path of a batch (P, T, 2) -> float64 (P,).

    Rows containing NaN (such as normalize_paths' no-extent rows) give NaN.
    """
    arr = _as_batch(paths, "paths", 1)
    out = np.empty(arr.shape[0])
    _circle_variances(arr, out)
    return out


def is_circle(normalized_points: object) -> bool:
    """True if circle_variance is below CIRCLE_VARIANCE_THRESHOLD."""
    return circle_variance(normalized_points) < CIRCLE_VARIANCE_THRESHOLD


def chamfer(a: object, b: object) -> float:
    """Bidirectional chamfer distance: mean nearest-point distance from a to b plus from b to a."""
    pa = _as_points(a, "a", 1)
    pb = _as_points(b, "b", 1)
    out = np.empty(1)
    _chamfer_to_many(pa, pb[None], out)
    return float(out[0])


def chamfer_to_many(query: object, candidates: object, out: np.ndarray | None = None) -> np.ndarray:
    """Chamfer distance from query (Tq, 2) to each of candidates (P, T, 2) -> float64 (P,).

    Writes into and returns out if given (a writeable contiguous float64 array of shape (P,)).
    """
    q = _as_points(query, "query", 1)
    cands = _as_batch(candidates, "candidates", 1)
    n = cands.shape[0]
    if out is None:
        out = np.empty(n)
    else:
        check_buffer("out", out, (n,), contiguous=True, writeable=True)
    bad = _chamfer_to_many(q, cands, out)
    if bad >= 0:
        raise ValueError(f"candidates must be finite (candidate {bad} has NaN or inf)")
    return out


def even_along(
    outline: np.ndarray, count: int, closed: bool = True, share: float = 1.0
) -> np.ndarray:
    """`count` points evenly spaced along the polyline `outline`: around it when `closed`
    (its last point joined to its first), else from its first point to `share` of its length,
    both ends included."""
    if closed:
        outline = np.concatenate([outline, outline[:1]])
    lengths = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(outline, axis=0), axis=1))])
    if closed:
        at = np.linspace(0, lengths[-1], count, endpoint=False)
    else:
        at = np.linspace(0, share * lengths[-1], count)
    return np.column_stack(
        [np.interp(at, lengths, outline[:, 0]), np.interp(at, lengths, outline[:, 1])]
    )
