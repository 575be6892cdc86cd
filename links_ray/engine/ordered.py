"""The ordered distance between a closed drawing and a closed path: how far apart they are when
the drawing's points are matched to the path's in order, not to their nearest neighbours.

Both are taken evenly spaced by arc length: the drawing's T points as given (the caller spaces
them, `paths.even_along`), the path resampled at T * OVERSAMPLE points round its polyline. The
drawing's point i is matched to the path's point (start + direction * OVERSAMPLE * i), modulo
the count, for the start and the direction (+1 along the path, -1 against it) whose mean
squared distance is least; the ordered distance is the root of that mean. Where a curve
crosses itself or two strands pass close, nearest neighbours pair points of different
strands; matched in order, strands pair with strands.

`arc_positions` gives where on the path's steps each resampled point lies (step and share of
the way to the next). `links bench synthesize` reports the ordered distance beside the chamfer:
a path can lie on a drawing's strands (a small chamfer) yet run along them in another order.

Pure numpy/numba: no Ray.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

__all__ = ["OVERSAMPLE", "OrderedMatch", "arc_positions", "ordered_match"]

#: Path points per drawn point: the match's start moves in steps of 1 / OVERSAMPLE of the
#: drawing's spacing, so rounding the start costs little.
OVERSAMPLE = 4


@dataclass(frozen=True)
class OrderedMatch:
    """The best ordered match of a drawing's T points to a path's steps."""

    distance: float  # root mean squared distance of the matched pairs
    step: np.ndarray  # (T,) int64: drawn point i lies matched between path step[i] ...
    share: np.ndarray  # (T,) float64: ... and the next step (cyclically), this share along
    start: int  # the first drawn point's match, among the T * OVERSAMPLE resampled points
    direction: int  # +1: the drawing runs along the path; -1: against it


@numba.njit(cache=True, nogil=True)
def _arc_positions(path: np.ndarray, count: int, step: np.ndarray, share: np.ndarray) -> None:
    """`count` positions evenly spaced by arc length round the closed polyline `path`, starting
    at its first point: the step each falls after, and its share of the way to the next."""
    steps = path.shape[0]
    total = 0.0
    for k in range(steps):
        total += math.hypot(
            path[(k + 1) % steps, 0] - path[k, 0], path[(k + 1) % steps, 1] - path[k, 1]
        )
    k = 0
    before = 0.0  # arc length at the start of segment k
    length = math.hypot(path[1 % steps, 0] - path[0, 0], path[1 % steps, 1] - path[0, 1])
    for i in range(count):
        at = total * i / count
        while k < steps - 1 and before + length <= at:
            before += length
            k += 1
            length = math.hypot(
                path[(k + 1) % steps, 0] - path[k, 0], path[(k + 1) % steps, 1] - path[k, 1]
            )
        step[i] = k
        share[i] = min(1.0, (at - before) / length) if length > 0 else 0.0


@numba.njit(cache=True, nogil=True)
def _best_match(drawn: np.ndarray, even: np.ndarray, out: np.ndarray) -> None:
    """out = (least mean squared distance, start, direction) over every start in `even`
    (T * OVERSAMPLE resampled path points) and both directions; ties to the lower start,
    then forward."""
    t = drawn.shape[0]
    m = even.shape[0]
    stride = m // t
    best = np.inf
    best_start = 0
    best_direction = 1
    for direction in (1, -1):
        for start in range(m):
            s = 0.0
            for i in range(t):
                j = (start + direction * stride * i) % m
                dx = drawn[i, 0] - even[j, 0]
                dy = drawn[i, 1] - even[j, 1]
                s += dx * dx + dy * dy
                if s >= best * t:  # already worse than the best: stop early
                    break
            if s < best * t:
                best = s / t
                best_start = start
                best_direction = direction
    out[0] = best
    out[1] = best_start
    out[2] = best_direction


def arc_positions(path: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """(step (count,) int64, share (count,) float64): `count` points evenly spaced by arc length
    round the closed polyline `path` (S, 2), from its first point, each between step[i] and the
    next step (cyclically), share[i] of the way. ValueError for a bad path or count."""
    path = np.ascontiguousarray(path, dtype=np.float64)
    if path.ndim != 2 or path.shape[1] != 2 or len(path) < 2:
        raise ValueError(f"path must have shape (S, 2) with S >= 2, got {path.shape}")
    if not np.isfinite(path).all():
        raise ValueError("path must be finite")
    if not 1 <= count <= 1 << 24:
        raise ValueError(f"count must be from 1 to {1 << 24}, got {count}")
    step = np.empty(count, dtype=np.int64)
    share = np.empty(count, dtype=np.float64)
    _arc_positions(path, count, step, share)
    return step, share


def ordered_match(drawn: np.ndarray, path: np.ndarray) -> OrderedMatch:
    """The best ordered match of the closed drawing's points `drawn` (T, 2), evenly spaced by
    arc length, to the closed path `path` (S, 2) (see the module's docstring). ValueError for
    bad shapes or values."""
    drawn = np.ascontiguousarray(drawn, dtype=np.float64)
    if drawn.ndim != 2 or drawn.shape[1] != 2 or len(drawn) < 3:
        raise ValueError(f"drawn must have shape (T, 2) with T >= 3, got {drawn.shape}")
    if not np.isfinite(drawn).all():
        raise ValueError("drawn must be finite")
    count = len(drawn) * OVERSAMPLE
    step, share = arc_positions(path, count)
    path = np.ascontiguousarray(path, dtype=np.float64)
    following = path[(step + 1) % len(path)]
    even = (1.0 - share)[:, None] * path[step] + share[:, None] * following
    out = np.empty(3)
    _best_match(drawn, even, out)
    start, direction = int(out[1]), int(out[2])
    chosen = (start + direction * OVERSAMPLE * np.arange(len(drawn))) % count
    return OrderedMatch(
        distance=math.sqrt(out[0]),
        step=step[chosen],
        share=share[chosen],
        start=start,
        direction=direction,
    )
