"""Facts of the LINKS release's own files that links-ray's import and export share.

The release simulates every mechanism at the absolute crank angles `release_angles()`:
`numpy.linspace(0, 2*pi, RELEASE_STEPS)`, both ends included (so its last point repeats its
first), with joint 1 placed at x0[0] + r (cos theta, sin theta), r the crank's length: the
crank starts along +x, not where x0 has it. links-ray starts the crank at its initial angle and
steps 2*pi*t/steps for t < steps. Each dyad keeps, at every angle, the side of its two parents
it has in x0, as links-ray's solver does; so `release_trajectories` is links-ray's solver on
the release's angles (relative to the crank's initial angle), and equals the release's own
trajectories up to rounding.

The release normalizes curves its own way (`release_normalize`, not links-ray's
`normalize_path`) and classifies them arc first (`release_arcs`, then `release_circles` for
the others only, on `release_circle_variance`).

Pure numpy: the solver is the engine's. No Ray, no files.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from links_ray.engine.kinematics.mechanism import Topology, analyze_topology
from links_ray.engine.kinematics.paths import CIRCLE_VARIANCE_THRESHOLD
from links_ray.engine.kinematics.solver import simulate_one

__all__ = [
    "RELEASE_CIRCLE_VARIANCE",
    "RELEASE_FILES",
    "RELEASE_MIDDLE_POINTS",
    "RELEASE_STEPS",
    "RELEASE_TIE",
    "release_angles",
    "release_arcs",
    "release_circle_variance",
    "release_circles",
    "release_crank",
    "release_normalize",
    "release_normalize_many",
    "release_trajectories",
    "release_trajectories_many",
    "release_turn",
]

#: Points of every curve the release holds.
RELEASE_STEPS = 200
#: The release's four files, in the names it was published under: mechanisms, simulations,
#: normalized curves and curated curves.
RELEASE_FILES = ("dataset", "simulation_dataset", "normalized_dataset", "curated_dataset")
#: How many points nearest x = 0.5 decide between a turn and the turn 180 degrees more.
RELEASE_MIDDLE_POINTS = 5
#: Heights of the two turns (`release_normalize_many`, step 3) closer than this share of the
#: curve's width are a tie, and the first turn is kept: the release compares them in float32,
#: where such a difference is rounding's (a circle's two turns, whose highest middle points
#: are both its top, differ by nothing else).
RELEASE_TIE = 1e-6
#: The circle test's bound on `release_circle_variance`. The release's own bound is not known
#: here, so it is links-ray's curation bound (`engine.kinematics.paths.CIRCLE_VARIANCE_THRESHOLD`).
RELEASE_CIRCLE_VARIANCE = CIRCLE_VARIANCE_THRESHOLD
#: Curves normalized at once: bounds the float64 scratch (about 30 KB a curve).
_NORMALIZE_BLOCK = 8192


def release_angles() -> np.ndarray:
    """(RELEASE_STEPS,) the release's absolute crank angles, 0 to 2 pi, both included."""
    return np.linspace(0.0, 2.0 * np.pi, RELEASE_STEPS)


def release_crank(positions: np.ndarray) -> np.ndarray:
    """(RELEASE_STEPS, 2) cos and sin of the release's angles relative to the crank's initial
    angle in `positions` (n, 2): the crank table the engine's solver turns through."""
    start = np.arctan2(positions[1, 1] - positions[0, 1], positions[1, 0] - positions[0, 0])
    relative = release_angles() - start
    return np.ascontiguousarray(np.stack([np.cos(relative), np.sin(relative)], axis=1))


def release_turn(
    topology: Topology, positions: np.ndarray, out: np.ndarray | None = None
) -> tuple[np.ndarray, tuple[int, int]]:
    """`release_trajectories` of an analyzed topology and float64 positions (n, 2), into
    `out` (n, RELEASE_STEPS, 2) if given: the one call of the solver at the release's angles."""
    if out is None:
        out = np.empty((topology.n_joints, RELEASE_STEPS, 2))
    geometry = np.empty((len(topology.order), 3))
    step, joint = simulate_one(
        topology.order,
        topology.fixed_joints,
        positions,
        release_crank(positions),
        True,
        out,
        geometry,
    )
    return out, (int(step), int(joint))


def release_trajectories(
    adjacency: ArrayLike, node_types: ArrayLike, positions: ArrayLike
) -> tuple[np.ndarray, tuple[int, int]]:
    """(trajectories (n, RELEASE_STEPS, 2), lock) of a mechanism in links-ray's conventions
    (node types FIXED/SIMPLE/ACTUATED, joint 1 the crank's tip) at the release's angles;
    lock is (-1, -1), or the (step, joint) where it first cannot be assembled (only the
    release's steps are checked, as the release checks them; the trajectories are then
    meaningless from that step on). Raises InvalidMechanismError for a malformed mechanism."""
    topology = analyze_topology(adjacency, node_types)
    pos = np.ascontiguousarray(positions, dtype=np.float64)
    if pos.shape != (topology.n_joints, 2):
        raise ValueError(f"positions must be ({topology.n_joints}, 2), got {pos.shape}")
    return release_turn(topology, pos)


def release_trajectories_many(
    adjacency: ArrayLike, node_types: ArrayLike, positions: ArrayLike
) -> tuple[np.ndarray, np.ndarray]:
    """`release_trajectories` of M mechanisms of one joint count: adjacency (M, n, n),
    node_types (M, n), positions (M, n, 2) -> (trajectories (M, n, RELEASE_STEPS, 2) float64,
    lock_step (M,) int64, -1 where the mechanism turns through every one of the release's
    angles). Consecutive rows of one topology share its analysis."""
    adjacency = np.asarray(adjacency)
    node_types = np.asarray(node_types)
    pos = np.ascontiguousarray(positions, dtype=np.float64)
    rows, n = node_types.shape
    if adjacency.shape != (rows, n, n) or pos.shape != (rows, n, 2):
        raise ValueError(
            f"adjacency, node_types and positions must be (M, n, n), (M, n) and (M, n, 2), "
            f"got {adjacency.shape}, {node_types.shape} and {pos.shape}"
        )
    out = np.empty((rows, n, RELEASE_STEPS, 2))
    locks = np.full(rows, -1, dtype=np.int64)
    topology = None
    for row in range(rows):
        if row == 0 or not (
            np.array_equal(adjacency[row], adjacency[row - 1])
            and np.array_equal(node_types[row], node_types[row - 1])
        ):
            topology = analyze_topology(adjacency[row], node_types[row])
        _, (locks[row], _) = release_turn(topology, pos[row], out[row])
    return out, locks


def release_normalize(curve: ArrayLike) -> np.ndarray:
    """(RELEASE_STEPS, 2) float64: one curve (points, 2) normalized by the release's rule
    (`release_normalize_many`)."""
    points = np.asarray(curve)
    if not np.issubdtype(points.dtype, np.floating):
        points = points.astype(np.float64)
    if points.ndim != 2 or points.shape[1] != 2 or len(points) < RELEASE_MIDDLE_POINTS:
        raise ValueError(
            f"curve must be (points, 2) with at least {RELEASE_MIDDLE_POINTS} points, "
            f"got {points.shape}"
        )
    return release_normalize_many(points[None])[0]


def release_normalize_many(curves: ArrayLike) -> np.ndarray:
    """(P, points, 2) float64: curves (P, points, 2) normalized by the release's rule.

    1. The longest chord, by farthest-point hops: from point 0 hop to the point farthest
       from the current one, until the farthest point from the current one is the one just
       left (a pair each farthest from the other), or after `points` hops; the chord runs
       from the point left to the current one. Ties go to the lowest index. Distances are
       measured as the release's code measures them, in the curves' own float dtype (float32
       for the release's files): the square root of the summed squares, rounded there. A
       circle's diameters are all nearly the longest, and float64 would pick another.
    2. The turn by the smaller angle (at most 90 degrees either way) that makes this chord
       horizontal, and that turn plus 180 degrees (rotations; the centre does not matter,
       step 3 translates).
    3. Each turned curve is translated so its least x and least y are 0 (the translation
       comes before the choice, so that x = 0.5 means the same for every placement of a
       curve; there is no scaling yet, so x = 0.5 is in the curve's own units). Of the two,
       the kept one is that whose RELEASE_MIDDLE_POINTS points nearest x = 0.5 (ties to the
       lower index) have the lower highest y, as the release's `get_oriented` compares them
       (not their mean, nor their least y); on a tie (heights within RELEASE_TIE of the
       curve's width) the first turn, as the release keeps it on equal heights.
    4. Both coordinates are divided by the x extent, so x spans [0, 1] and y starts at 0.

    A curve holding NaN or infinity, or with no x extent (one point repeated), becomes zeros.
    Steps 2 to 4 are in float64. The release computes them in the curves' dtype, so on a tie
    its own choice is float32 rounding's, and may be either turn: about one curve in 150 of
    generated mechanisms (mostly circles) is such a tie.
    """
    c = np.asarray(curves)
    if not np.issubdtype(c.dtype, np.floating):
        c = c.astype(np.float64)
    if c.ndim != 3 or c.shape[2] != 2 or c.shape[1] < RELEASE_MIDDLE_POINTS:
        raise ValueError(
            f"curves must be (P, points, 2) with at least {RELEASE_MIDDLE_POINTS} points, "
            f"got {c.shape}"
        )
    out = np.empty(c.shape)
    for start in range(0, len(c), _NORMALIZE_BLOCK):
        block = slice(start, start + _NORMALIZE_BLOCK)
        out[block] = _normalize_block(c[block])
    return out


def _farthest(c: np.ndarray, rows: np.ndarray, frm: np.ndarray) -> np.ndarray:
    """Per curve, the index of the point farthest from point `frm` (first on ties), the
    distances rounded in `c`'s dtype as `numpy.linalg.norm` rounds them: the release's
    measure, whose ties (two distances equal once rounded) it breaks the same way."""
    d = c - c[rows, frm][:, None, :]
    return np.argmax(np.sqrt(d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1]), axis=1)


def _normalize_block(given: np.ndarray) -> np.ndarray:
    bad = ~np.isfinite(given).all(axis=(1, 2))
    given = np.where(bad[:, None, None], given.dtype.type(0), given)
    c = given.astype(np.float64)
    rows = np.arange(len(c))
    left = np.zeros(len(c), dtype=np.int64)
    here = _farthest(given, rows, left)
    hopping = rows  # the curves whose last hop has not come back
    for _ in range(c.shape[1]):
        onward = _farthest(given[hopping], np.arange(len(hopping)), here[hopping])
        moving = onward != left[hopping]
        if not moving.any():
            break
        hopping = hopping[moving]
        left[hopping] = here[hopping]
        here[hopping] = onward[moving]
    chord = c[rows, here] - c[rows, left]
    # The release turns by -arctan(dy / dx): the chord's direction folded into (-90, 90]
    # degrees, so which of the two turns is "first" (kept on a tie) is the release's too.
    angle = np.arctan2(chord[:, 1], chord[:, 0])
    angle = np.where(angle > np.pi / 2, angle - np.pi, angle)
    angle = np.where(angle <= -np.pi / 2, angle + np.pi, angle)
    cos, sin = np.cos(angle)[:, None], np.sin(angle)[:, None]
    x = cos * c[..., 0] + sin * c[..., 1]
    y = cos * c[..., 1] - sin * c[..., 0]
    # The turn 180 degrees more is (-x, -y); each translated so its least x and y are 0.
    first = np.stack([x - x.min(axis=1)[:, None], y - y.min(axis=1)[:, None]], axis=2)
    second = np.stack([x.max(axis=1)[:, None] - x, y.max(axis=1)[:, None] - y], axis=2)
    width = x.max(axis=1) - x.min(axis=1)
    keep_second = _middle_height(second) < _middle_height(first) - RELEASE_TIE * width
    turned = np.where(keep_second[:, None, None], second, first)
    extent = turned[..., 0].max(axis=1)
    bad |= ~(extent > 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        turned = turned / extent[:, None, None]
    turned[bad] = 0.0
    return turned


def _middle_height(c: np.ndarray) -> np.ndarray:
    """Per curve, the highest y of its RELEASE_MIDDLE_POINTS points nearest x = 0.5."""
    nearest = np.argsort(np.abs(c[..., 0] - 0.5), axis=1, kind="stable")
    nearest = nearest[:, :RELEASE_MIDDLE_POINTS]
    return np.take_along_axis(c[..., 1], nearest, axis=1).max(axis=1)


def release_circle_variance(curves: ArrayLike) -> np.ndarray:
    """The variance of the distances of a normalized curve's points (..., points, 2) from
    (0.5, 0.5): a float for one curve, (P,) for P curves."""
    c = np.asarray(curves, dtype=np.float64)
    if c.ndim < 2 or c.shape[-1] != 2:
        raise ValueError(f"curves must be (..., points, 2), got {c.shape}")
    variance = np.linalg.norm(c - 0.5, axis=-1).var(axis=-1)
    return float(variance) if variance.ndim == 0 else variance


def release_arcs(adjacency: ArrayLike, fixed: ArrayLike) -> np.ndarray:
    """(..., n) bool: the release's first test, the moving joints linked to a fixed joint
    (the crank's tip among them), from adjacency (..., n, n) and fixed (..., n) bool (the
    release's node_type)."""
    fixed = np.asarray(fixed, dtype=bool)
    linked = ((np.asarray(adjacency) != 0) & fixed[..., None, :]).any(axis=-1)
    return linked & ~fixed


def release_circles(curves: ArrayLike, is_arc: ArrayLike) -> np.ndarray:
    """(P,) bool: the release's second test, for curves (P, points, 2) normalized by
    `release_normalize_many` that are not arcs (`is_arc` (P,)): circle variance below
    RELEASE_CIRCLE_VARIANCE. An arc is never a circle here: the release tests it first."""
    is_arc = np.asarray(is_arc, dtype=bool)
    variance = np.atleast_1d(release_circle_variance(curves))
    if variance.shape != is_arc.shape:
        raise ValueError(f"is_arc must be ({len(variance)},), got {is_arc.shape}")
    return ~is_arc & (variance < RELEASE_CIRCLE_VARIANCE)
