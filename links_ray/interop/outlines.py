"""What every reader of a drawing shares: the error a file past a limit raises, the check on
its coordinates, and segments flattened to a fixed budget of points.

The SVG and DXF readers (`interop.svg_curves`, `interop.dxf_curves`) trace a curve as segments
that `flatten` turns into one polyline of at most 3 x segments + FLAT_POINTS + 1 points, so a
curve's cost is bounded by its segment count, which each reader holds to MAX_CURVE_SEGMENTS.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from links_ray.engine.inputs import MAX_COORDINATE

#: Points the curved segments of a drawing (Béziers, arcs, splines) share by length before
#: the even resampling, two each at the least: a circle's chords then sag about 1e-8 of its
#: radius, far below the MAX_POINTS the curve is resampled to at the most.
FLAT_POINTS = 20_000


class CurveFileTooLarge(ValueError):
    """A drawing past a limit on what a curve file may hold (its bytes, an SVG's elements, a
    curve's segments, ...): `limit` is the name of the constant in interop/curve_limits.py. The
    HTTP API answers it with 413."""

    status = 413

    def __init__(self, message: str, limit: str) -> None:
        super().__init__(message)
        self.limit = limit


#: A curve as `flatten` takes it: its points at (segment index, t from 0 to 1) pairs, given
#: as two arrays, the indices in ascending order.
Along = Callable[[np.ndarray, np.ndarray], np.ndarray]

#: Where each segment's length is measured, before its share of FLAT_POINTS is set.
_COARSE = np.linspace(0.0, 1.0, 17)
#: Counts saturate here: a chain of SVG `<use>` multiplies them past any limit.
SATURATED_COUNT = 10**15


def flatten(file: str, along: Along, count: int, straight: np.ndarray) -> np.ndarray:
    """The `count` segments `along` traces as one polyline: each `straight` one by its end, the
    others sharing FLAT_POINTS by length, two each at the least; at most 3 x `count` +
    FLAT_POINTS + 1 points. Coordinates beyond MAX_COORDINATE are refused first."""
    segments = np.arange(count)
    coarse = along(np.repeat(segments, len(_COARSE)), np.tile(_COARSE, count))
    coarse = coarse.reshape(count, len(_COARSE), 2)
    check_coordinates(file, coarse)
    lengths = np.linalg.norm(np.diff(coarse, axis=1), axis=2).sum(axis=1)
    curved = float(lengths[~straight].sum())
    share = np.ceil(FLAT_POINTS * lengths / curved) if curved > 0 else np.zeros(count)
    steps = np.where(straight, 1, np.maximum(2, share)).astype(np.int64)
    index = np.repeat(segments, steps)
    taken = np.arange(int(steps.sum())) - np.repeat(np.cumsum(steps) - steps, steps)
    start = along(np.zeros(1, dtype=np.int64), np.zeros(1))
    return np.concatenate([start, along(index, (taken + 1) / steps[index])])


def too_many(file: str, count: int, limit: int, name: str, message: str) -> None:
    """Refuse `count` past `limit`, the constant `name`: `message` says what, {count} and
    {limit} in it standing for the two."""
    if count > limit:
        found = f"{count:,}" if count < SATURATED_COUNT else f"over {SATURATED_COUNT:.0e}"
        said = message.replace("{count}", found).replace("{limit}", f"{limit:,}")
        raise CurveFileTooLarge(f"{file}: {said}", name)


def check_coordinates(file: str, points: np.ndarray) -> None:
    """Refuse points that are not finite or lie beyond MAX_COORDINATE: lengths measured among
    them would overflow, and no drawn curve holds them."""
    if not np.all(np.isfinite(points)):
        raise ValueError(f"{file}: coordinates must be finite numbers")
    if points.size and (worst := float(np.abs(points).max())) > MAX_COORDINATE:
        raise ValueError(f"{file}: coordinates must lie within +-{MAX_COORDINATE:g}, got {worst:g}")
