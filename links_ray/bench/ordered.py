"""The ordered distance between a closed drawing and a closed path: how far apart they are when
the drawing's points are matched to the path's in order, not to their nearest neighbours.

Both are taken evenly spaced by arc length: the drawing's T points as given (the caller spaces
them, `paths.even_along`), the path resampled at T * OVERSAMPLE points round its polyline. The
drawing's point i is matched to the path's point (start + direction * OVERSAMPLE * i), modulo
the count, for the start and the direction (+1 along the path, -1 against it) whose mean
squared distance is least; the ordered distance is the root of that mean. Where a curve
crosses itself or two strands pass close, nearest neighbours pair points of different
strands; matched in order, strands pair with strands.

`links bench synthesize` reports the ordered distance beside the chamfer:
a path can lie on a drawing's strands (a small chamfer) yet run along them in another order.

Pure numpy/numba: no Ray.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from links_ray.engine.kinematics.paths import even_along

__all__ = ["OVERSAMPLE", "OrderedMatch", "ordered_match"]

#: Path points per drawn point: the match's start moves in steps of 1 / OVERSAMPLE of the
#: drawing's spacing, so rounding the start costs little.
OVERSAMPLE = 4


@dataclass(frozen=True)
class OrderedMatch:
    """The best ordered match of a drawing's T points to a path."""

    distance: float  # root mean squared distance of the matched pairs
    start: int  # the first drawn point's match, among the T * OVERSAMPLE resampled points
    direction: int  # +1: the drawing runs along the path; -1: against it


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


def ordered_match(drawn: np.ndarray, path: np.ndarray) -> OrderedMatch:
    """The best ordered match of the closed drawing's points `drawn` (T, 2), evenly spaced by
    arc length, to the closed path `path` (S, 2) (see the module's docstring). ValueError for
    bad shapes or values."""
    drawn = np.ascontiguousarray(drawn, dtype=np.float64)
    if drawn.ndim != 2 or drawn.shape[1] != 2 or len(drawn) < 3:
        raise ValueError(f"drawn must have shape (T, 2) with T >= 3, got {drawn.shape}")
    if not np.isfinite(drawn).all():
        raise ValueError("drawn must be finite")
    path = np.asarray(path, dtype=np.float64)
    if path.ndim != 2 or path.shape[1] != 2 or len(path) < 2:
        raise ValueError(f"path must have shape (S, 2) with S >= 2, got {path.shape}")
    if not np.isfinite(path).all():
        raise ValueError("path must be finite")
    even = np.ascontiguousarray(even_along(path, len(drawn) * OVERSAMPLE, closed=True))
    out = np.empty(3)
    _best_match(drawn, even, out)
    return OrderedMatch(distance=math.sqrt(out[0]), start=int(out[1]), direction=int(out[2]))
