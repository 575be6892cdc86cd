"""Closed curves that cross themselves, for `links bench synthesize --set`: figure-eights, dual
loops, trefoils and hourglasses, drawn from a seed.

Each kind has a base shape with a known number of crossings, varied by its own parameter, a
stretch along x and a few random low harmonics. A drawn curve is kept only if it crosses
itself exactly as often as its kind does (`crossings`), and no two of its strands pass nearer
than `MIN_STRAND_GAP` away from a crossing: a bend that almost touches itself would make a
different, tangled shape. The points are dense (`POINTS`), in the curve's own order.

Pure numpy.
"""

from __future__ import annotations

import numpy as np

#: Curves of each kind, and the default seed.
PER_KIND = 3
CROSSING_SEED = 0
#: Draws of one curve before the generator gives up (a handful suffice).
MAX_DRAWS = 1000
#: Points a curve is drawn with (the set re-spaces them evenly by arc length).
POINTS = 600
#: The crossings each kind has.
KIND_CROSSINGS = {"eight": 1, "dual_loop": 1, "trefoil": 3, "hourglass": 1}
#: Amplitude of the random harmonics 2 to 4, relative to the base shape's size.
WOBBLE = 0.06
#: Least distance between strands away from the crossings, relative to the curve's size.
MIN_STRAND_GAP = 0.04


def crossing_curves(seed: int = CROSSING_SEED, per_kind: int = PER_KIND) -> dict[str, np.ndarray]:
    """`per_kind` curves of each kind of KIND_CROSSINGS, named `crossing_<kind>_<i>`, drawn
    from `seed`: each a (POINTS, 2) closed polyline not repeating its first point."""
    curves = {}
    for kind_index, (kind, expected) in enumerate(KIND_CROSSINGS.items()):
        for i in range(per_kind):
            rng = np.random.default_rng([seed, kind_index, i])
            for _ in range(MAX_DRAWS):
                loop = _wobbled(_base(kind, rng), rng)
                crossed = crossing_segments(loop)
                if len(crossed) == expected and _strands_apart(loop, crossed):
                    break
            else:
                raise ValueError(f"no {kind} of seed {seed} kept in {MAX_DRAWS} draws")
            curves[f"crossing_{kind}_{i}"] = loop
    return curves


def _base(kind: str, rng: np.random.Generator) -> np.ndarray:
    """One base shape of `kind`, its own parameter drawn, stretched along x."""
    t = np.linspace(0, 2 * np.pi, POINTS, endpoint=False)
    if kind == "eight":  # a Lissajous figure of frequencies 1 and 2
        z = np.sin(t) + 1j * rng.uniform(0.5, 1.1) * np.sin(2 * t)
    elif kind == "dual_loop":  # twice round, the radius swinging between the two loops
        z = np.exp(2j * t) * (1 + rng.uniform(0.3, 0.55) * np.cos(t))
    elif kind == "trefoil":  # a trefoil knot's shadow: three lobes, three crossings
        z = np.exp(1j * t) + rng.uniform(1.4, 2.4) * np.exp(-2j * t)
    elif kind == "hourglass":  # a bow tie: two flat sides joined by two crossing diagonals
        z = _rounded_polygon(np.array([-1 + 1j, 1 + 1j, -1 - 1j, 1 - 1j]), t, rng)
    else:
        raise ValueError(f"kind must be one of {', '.join(KIND_CROSSINGS)}, got {kind!r}")
    z = z.real * rng.uniform(0.7, 1.4) + 1j * z.imag
    return np.column_stack([z.real, z.imag])


def _rounded_polygon(corners: np.ndarray, t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The closed polygon through `corners` (each moved a little), sampled at `t` over a turn
    and its corners rounded by a short circular moving average."""
    corners = corners + rng.normal(scale=0.08, size=len(corners)) * (1 + 1j)
    sides = np.abs(np.roll(corners, -1) - corners)
    at = np.concatenate([[0.0], np.cumsum(sides)]) / sides.sum() * 2 * np.pi
    loop = np.concatenate([corners, corners[:1]])
    z = np.interp(t, at, loop.real) + 1j * np.interp(t, at, loop.imag)
    width = len(t) // 40
    kernel = np.ones(width) / width
    wrapped = np.concatenate([z[-width:], z, z[:width]])
    return np.convolve(wrapped, kernel, mode="same")[width:-width]


def _wobbled(loop: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """`loop` plus random harmonics 2 to 4 of amplitude about WOBBLE times its size."""
    t = np.linspace(0, 2 * np.pi, len(loop), endpoint=False)
    size = float(np.ptp(loop, axis=0).max())
    harmonics = np.array([2, 3, 4])
    c = rng.normal(size=(2, 3)) * WOBBLE * size / harmonics
    phase = rng.uniform(0, 2 * np.pi, size=(2, 3))
    return loop + np.column_stack(
        [np.sin(np.outer(t, harmonics) + phase[axis]) @ c[axis] for axis in range(2)]
    )


def crossings(loop: np.ndarray) -> int:
    """How many pairs of non-adjacent segments of the closed polyline `loop` cross properly
    (each strictly on both sides of the other)."""
    return len(crossing_segments(loop))


def crossing_segments(loop: np.ndarray) -> list[tuple[int, int]]:
    """The pairs (i, j), i < j, of non-adjacent segments of the closed polyline `loop` that
    cross properly; segment i runs from point i to point i + 1 (the last one back to 0)."""
    a, b = loop, np.roll(loop, -1, axis=0)
    n = len(loop)
    pairs = []
    for i in range(n - 2):  # a row at a time: the n**2 pairs are never held at once
        j = np.arange(i + 2, n if i > 0 else n - 1)
        d1 = _side(a[i], b[i], a[j])
        d2 = _side(a[i], b[i], b[j])
        d3 = _side(a[j], b[j], a[i])
        d4 = _side(a[j], b[j], b[i])
        pairs += [(i, int(k)) for k in j[(d1 * d2 < 0) & (d3 * d4 < 0)]]
    return pairs


def _side(p: np.ndarray, q: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Sign of the turn p -> q -> r, row by row (any of them one point)."""
    p, q, r = np.atleast_2d(p), np.atleast_2d(q), np.atleast_2d(r)
    return np.sign(
        (q[:, 0] - p[:, 0]) * (r[:, 1] - p[:, 1]) - (q[:, 1] - p[:, 1]) * (r[:, 0] - p[:, 0])
    )


def _strands_apart(loop: np.ndarray, crossed: list[tuple[int, int]]) -> bool:
    """Whether points of `loop` more than a tenth of it apart along the curve are at least
    MIN_STRAND_GAP of its size apart, but near its crossings `crossed` (where strands meet by
    design)."""
    n = len(loop)
    size = float(np.ptp(loop, axis=0).max())
    gaps = np.linalg.norm(loop[:, None, :] - loop[None, :, :], axis=-1)
    along = np.abs(np.arange(n)[:, None] - np.arange(n)[None, :])
    close = (gaps < MIN_STRAND_GAP * size) & (np.minimum(along, n - along) > n // 10)
    where = np.array([loop[i] for i, _ in crossed]).reshape(-1, 2)
    near = np.linalg.norm(loop[:, None, :] - where[None, :, :], axis=-1) < 3 * MIN_STRAND_GAP * size
    near = near.any(axis=1)
    return not np.any(close & ~near[:, None] & ~near[None, :])
