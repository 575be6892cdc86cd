"""Design constraints on a mechanism in the drawing's frame: how far positions are from keeping
them, and the linearized rows that keep a refinement step inside them.

The constraints themselves (`Constraints`, validated by `as_constraints`) are a
pivot region (every fixed joint in a box), a footprint (every joint in a box over the whole
turn) and link lengths (every link between `min_link` and `max_link`, the longest at most
`max_link_ratio` times the shortest), and `max_layers` (at most that many layers as a kit at the
default sizes, `engine.synthesis.kit_layers`). A link is an edge of the mechanism's adjacency, the
crank included.

`violation` measures how far a mechanism is from keeping the geometric ones (all but
`max_layers`, which costs a layer plan and is kept at the answer, `engine.synthesis.kit_layers`):
each constraint's miss in its own units (lengths in the drawing's units, the ratio as a ratio)
and one merit that adds them up in chords, which refinement drives to zero before it may trade
any of it for a better fit.
`guard_rows` linearizes the constraints near their bounds as rows A d >= b of a step d of the
positions, as `refine_step.transmission_guards` does for the transmission margin.

Pure numpy: no numba, no Ray.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from links_ray.engine.inputs import (
    MAX_COORDINATE,
    MAX_DATASET_JOINTS,
    as_int,
    as_real_array,
    positive_at_most,
    shown,
)

__all__ = [
    "CONSTRAINT_NAMES",
    "MAX_LAYERS",
    "MAX_LINK_RATIO",
    "Constraints",
    "Violation",
    "as_constraints",
    "extent",
    "guard_rows",
    "joined",
    "link_lengths",
    "violation",
]

#: The design constraints a synthesis takes (`as_constraints`), in the drawing's units.
CONSTRAINT_NAMES = (
    "pivots",
    "footprint",
    "max_link_ratio",
    "min_link",
    "max_link",
    "max_layers",
)
#: The most `max_layers` may be: a plan needs no more layers than links (one each), and a
#: mechanism synthesis answers has at most MAX_DATASET_JOINTS joints, each of which adds at
#: most two links.
MAX_LAYERS = 2 * MAX_DATASET_JOINTS
#: The most `max_link_ratio` may be: far past any linkage a hand can build.
MAX_LINK_RATIO = 1e6


@dataclass(frozen=True)
class Constraints:
    """What a designer fixes, in the drawing's own units and frame (None: not constrained).

    `pivots` (xmin, ymin, xmax, ymax): every fixed joint inside this box. `footprint`: every
    joint inside this box through the whole crank turn. `max_link_ratio`: the longest link at
    most this many times the shortest. `min_link`, `max_link`: every link's length within.
    `max_layers`: at most this many layers as a kit at the default sizes scaled to its crank
    (`engine.synthesis.kit_layers`).
    """

    pivots: tuple[float, float, float, float] | None = None
    footprint: tuple[float, float, float, float] | None = None
    max_link_ratio: float | None = None
    min_link: float | None = None
    max_link: float | None = None
    max_layers: int | None = None

    def given(self) -> tuple[str, ...]:
        """The names of the constraints set."""
        return tuple(name for name in CONSTRAINT_NAMES if getattr(self, name) is not None)


def _as_box(value: object, name: str) -> tuple[float, float, float, float]:
    """[xmin, ymin, xmax, ymax] as four finite floats, each min below its max."""
    if isinstance(value, str | bytes | dict) or not hasattr(value, "__len__"):
        raise ValueError(f"{name} must be a box [xmin, ymin, xmax, ymax], got {shown(value)}")
    if isinstance(value, list | tuple) and len(value) != 4:  # before any entry is read
        raise ValueError(f"{name} must be four numbers [xmin, ymin, xmax, ymax]")
    box = as_real_array(name, value, "four numbers [xmin, ymin, xmax, ymax]")
    if box.shape != (4,) or any(isinstance(v, bool) for v in value):  # type: ignore[union-attr]
        raise ValueError(f"{name} must be four numbers [xmin, ymin, xmax, ymax]")
    if not np.all(np.isfinite(box)) or np.any(np.abs(box) > MAX_COORDINATE):
        raise ValueError(f"{name} must be finite numbers within +-{MAX_COORDINATE:g}")
    if not (box[0] < box[2] and box[1] < box[3]):
        raise ValueError(f"{name} must have xmin < xmax and ymin < ymax, got {box.tolist()}")
    xmin, ymin, xmax, ymax = (float(v) for v in box)
    return xmin, ymin, xmax, ymax


def as_constraints(value: object) -> Constraints | None:
    """Design constraints from a mapping of CONSTRAINT_NAMES (or a `Constraints`); None or an
    empty mapping gives None. Raises ValueError naming an unknown or bad constraint."""
    if value is None or isinstance(value, Constraints):
        return value if value is None or value.given() else None
    if not isinstance(value, dict):
        raise ValueError(f"constraints must be an object of {', '.join(CONSTRAINT_NAMES)}")
    for name in value:
        if name not in CONSTRAINT_NAMES:
            raise ValueError(
                f"unknown constraint {shown(name)}: constraints are {', '.join(CONSTRAINT_NAMES)}"
            )
    given = {name: v for name, v in value.items() if v is not None}
    boxes = {name: _as_box(given[name], name) for name in ("pivots", "footprint") if name in given}
    lengths = {
        name: positive_at_most(given[name], name, MAX_COORDINATE, "a length", "")
        for name in ("min_link", "max_link")
        if name in given
    }
    ratio = None
    if "max_link_ratio" in given:
        ratio = positive_at_most(
            given["max_link_ratio"], "max_link_ratio", MAX_LINK_RATIO, "a number", ""
        )
        if ratio < 1.0:
            raise ValueError(f"max_link_ratio must be at least 1, got {ratio:g}")
    low, high = lengths.get("min_link"), lengths.get("max_link")
    if low is not None and high is not None and low > high:
        raise ValueError(f"min_link ({low:g}) must not exceed max_link ({high:g})")
    layers = None
    if "max_layers" in given:
        layers = as_int("max_layers", given["max_layers"], 1, MAX_LAYERS)
    if not given:
        return None
    return Constraints(max_link_ratio=ratio, max_layers=layers, **boxes, **lengths)


#: Steps aim this share of the drawing's chord inside a bound (and a ratio this share of
#: itself): the footprint is kept between the simulation's steps too, and a step lands near,
#: not exactly on, its linearized bound.
CLEARANCE = 1e-3
#: Only bounds within this share of the chord (or of the ratio) of being reached give a row.
BAND = 0.05


@dataclass(frozen=True)
class Violation:
    """How far a mechanism is from its constraints: `total` adds every constraint's miss, in
    chords (the ratio's in multiples of the ratio); `name` and `by` are the largest miss,
    `by` in the constraint's own units; ("", 0.0) when every constraint is kept."""

    total: float
    name: str
    by: float

    @property
    def kept(self) -> bool:
        """Every constraint is kept."""
        return self.total <= 0.0


KEPT = Violation(0.0, "", 0.0)


def joined(first: Violation, second: Violation) -> Violation:
    """Both misses as one: their totals added, the name and `by` of the larger."""
    larger = first if first.total >= second.total else second
    return Violation(first.total + second.total, larger.name, larger.by)


def link_lengths(positions: np.ndarray, links: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """(E,) the length of each link (i, j) of `links` (`inputs.link_pairs`)."""
    i, j = links
    return np.hypot(*(positions[i] - positions[j]).T)


def extent(traj: np.ndarray) -> np.ndarray:
    """(4,) xmin, ymin, xmax, ymax over every joint's path, traj (n, steps, 2)."""
    # One coordinate at a time: numpy reduces a strided axis in one loop, where reducing axes
    # (0, 1) together runs its inner loop once per point over two values, many times slower;
    # this runs in every refinement trial's check.
    x, y = traj[..., 0], traj[..., 1]
    return np.array([x.min(), y.min(), x.max(), y.max()])


def _box_miss(box: tuple[float, float, float, float], low: np.ndarray, high: np.ndarray) -> float:
    """How far the range [low, high] (2,) of x and y reaches outside `box` (0 inside)."""
    lo, hi = np.array(box[:2]), np.array(box[2:])
    return float(max(0.0, (lo - low).max(), (high - hi).max()))


def violation(
    constraints: Constraints | None,
    positions: np.ndarray,
    fixed: np.ndarray,
    links: tuple[np.ndarray, np.ndarray],
    bounds: np.ndarray,
    chord: float,
) -> Violation:
    """How far `positions` (n, 2) are from `constraints` but `max_layers` (kept at the
    answer: `engine.synthesis.kit_layers`); `fixed` are the fixed joints' indices, `bounds` the
    `extent` of every joint over the turn, `chord` the drawing's."""
    if constraints is None:
        return KEPT
    misses: list[tuple[float, str, float]] = []  # (in chords, name, in its units)
    if constraints.pivots is not None:
        ground = positions[fixed]
        by = _box_miss(constraints.pivots, ground.min(axis=0), ground.max(axis=0))
        misses.append((by / chord, "pivots", by))
    if constraints.footprint is not None:
        by = _box_miss(constraints.footprint, bounds[:2], bounds[2:])
        misses.append((by / chord, "footprint", by))
    lengths = link_lengths(positions, links)
    if constraints.min_link is not None:
        by = max(0.0, constraints.min_link - float(lengths.min()))
        misses.append((by / chord, "min_link", by))
    if constraints.max_link is not None:
        by = max(0.0, float(lengths.max()) - constraints.max_link)
        misses.append((by / chord, "max_link", by))
    if constraints.max_link_ratio is not None:
        by = max(0.0, float(lengths.max() / lengths.min()) - constraints.max_link_ratio)
        misses.append((by / constraints.max_link_ratio, "max_link_ratio", by))
    total = sum(miss for miss, _, _ in misses)
    if total <= 0.0:
        return KEPT
    _, name, by = max(misses)
    return Violation(total, name, by)


def _box_rows(
    box: tuple[float, float, float, float],
    values: np.ndarray,
    gradients: np.ndarray,
    keep_low: np.ndarray,
    keep_high: np.ndarray,
    band: float,
    clearance: float,
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Rows keeping `values` (K, 2) inside `box`, with gradients (K, 2, P): a point's row for a
    side when it is within `band` of it and `keep_low`/`keep_high` (K, 2) say it may bind."""
    rows: list[np.ndarray] = []
    bounds: list[np.ndarray] = []
    lo, hi = np.array(box[:2]), np.array(box[2:])
    near_low = keep_low & (values < lo + band)
    near_high = keep_high & (values > hi - band)
    k, axis = np.nonzero(near_low)
    rows.append(gradients[k, axis])
    bounds.append(lo[axis] + clearance - values[k, axis])
    k, axis = np.nonzero(near_high)
    rows.append(-gradients[k, axis])
    bounds.append(values[k, axis] - hi[axis] + clearance)
    return rows, bounds


def guard_rows(
    constraints: Constraints | None,
    positions: np.ndarray,
    fixed: np.ndarray,
    links: tuple[np.ndarray, np.ndarray],
    traj: np.ndarray,
    dtraj: np.ndarray,
    chord: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Linearized constraints (A, b), A d >= b, for a step d (2n,) of `positions` (n, 2), from
    the turn's traj (n, steps, 2) and its derivatives dtraj (n, steps, 2, 2n): the rows of the
    bounds each constraint comes within BAND of (the missed ones among them), each aiming
    CLEARANCE inside."""
    cols = positions.size
    rows: list[np.ndarray] = [np.empty((0, cols))]
    bounds: list[np.ndarray] = [np.empty(0)]
    if constraints is None:
        return rows[0], bounds[0]
    band, clearance = BAND * chord, CLEARANCE * chord
    unit = np.eye(cols).reshape(-1, 2, cols)  # d position / d coordinates, per joint
    if constraints.pivots is not None:
        ground = np.ones((len(fixed), 2), dtype=bool)
        more = _box_rows(
            constraints.pivots, positions[fixed], unit[fixed], ground, ground, band, clearance
        )
        rows += more[0]
        bounds += more[1]
    if constraints.footprint is not None:
        moving = np.ones(len(positions), dtype=bool)
        moving[fixed] = False
        path = traj[moving]  # (M, steps, 2): only a path's extremes can bind
        before, after = np.roll(path, 1, axis=1), np.roll(path, -1, axis=1)
        lows = (path <= before) & (path <= after)
        highs = (path >= before) & (path >= after)
        values = np.concatenate([positions[fixed], path.reshape(-1, 2)])
        gradients = np.concatenate([unit[fixed], dtraj[moving].reshape(-1, 2, cols)])
        ground = np.ones((len(fixed), 2), dtype=bool)
        keep_low = np.concatenate([ground, lows.reshape(-1, 2)])
        keep_high = np.concatenate([ground, highs.reshape(-1, 2)])
        more = _box_rows(
            constraints.footprint, values, gradients, keep_low, keep_high, band, clearance
        )
        rows += more[0]
        bounds += more[1]
    lengths_given = (constraints.min_link, constraints.max_link, constraints.max_link_ratio)
    if any(value is not None for value in lengths_given):
        i, j = links
        lengths = link_lengths(positions, links)
        units = (positions[i] - positions[j]) / lengths[:, None]
        grads = np.zeros((len(lengths), cols))  # d length / d coordinates
        edge = np.arange(len(lengths))
        for c in range(2):
            grads[edge, 2 * i + c] = units[:, c]
            grads[edge, 2 * j + c] = -units[:, c]
        if constraints.min_link is not None:
            near = lengths < constraints.min_link + band
            rows.append(grads[near])
            bounds.append(constraints.min_link + clearance - lengths[near])
        if constraints.max_link is not None:
            near = lengths > constraints.max_link - band
            rows.append(-grads[near])
            bounds.append(lengths[near] - constraints.max_link + clearance)
        ratio = constraints.max_link_ratio
        if ratio is not None:
            # ratio x shortest - longest >= 0, for every pair that comes near it.
            slack = ratio * lengths[None, :] - lengths[:, None]  # [long, short]
            long_, short = np.nonzero(slack < BAND * ratio * lengths.min())
            rows.append(ratio * grads[short] - grads[long_])
            bounds.append(CLEARANCE * ratio * lengths[short] - slack[long_, short])
    return np.concatenate(rows), np.concatenate(bounds)
