"""Path normalization, circle detection and chamfer distance (docs/reference/contract.md, Paths).

Everything is checked against independent brute-force numpy computations or exact geometric
facts: the longest chord against an O(T^2) search, normalization by its invariance under
rotation, scaling and translation, chamfer against broadcast distances.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from links_ray.engine.kinematics.paths import (
    CIRCLE_VARIANCE_THRESHOLD,
    chamfer,
    chamfer_to_many,
    circle_variance,
    circle_variances,
    is_circle,
    longest_chord,
    normalization,
    normalize_path,
    normalize_paths,
)

SETTINGS = settings(max_examples=60, deadline=None)

coords = st.floats(-10, 10, allow_nan=False, allow_infinity=False)


# A 0.01 grid: repeated points are common, distinct ones are far apart (no underflow).
grid_coords = st.integers(-1000, 1000).map(lambda k: k / 100)


def point_sets(
    min_size: int = 5, max_size: int = 60, elements: st.SearchStrategy[float] = coords
) -> st.SearchStrategy[np.ndarray]:
    shape = st.tuples(st.integers(min_size, max_size), st.just(2))
    return hnp.arrays(np.float64, shape, elements=elements, fill=st.nothing())


# --------------------------------------------------------------------------- references


def brute_chord(pts: np.ndarray) -> tuple[int, int, float]:
    """Lowest (i, j), i < j, at the maximal squared distance, by checking every pair."""
    x, y = pts[:, 0], pts[:, 1]
    n = len(pts)
    best, pair = -1.0, (0, 0)
    for start in range(0, n, 512):
        rows = np.arange(start, min(start + 512, n))
        dx = x[None, :] - x[rows, None]
        dy = y[None, :] - y[rows, None]
        d = dx * dx + dy * dy
        d[np.arange(n)[None, :] <= rows[:, None]] = -1.0
        k = int(np.argmax(d))  # first maximum in row-major order: the lowest (i, j)
        if d.flat[k] > best:
            best, pair = float(d.flat[k]), (int(rows[k // n]), k % n)
    return pair[0], pair[1], best


def pairwise(pts: np.ndarray) -> np.ndarray:
    return np.linalg.norm(pts[:, None, :] - pts[None, :, :], axis=-1)


def brute_chamfer(a: np.ndarray, b: np.ndarray) -> float:
    d = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=-1)
    return float(d.min(axis=1).mean() + d.min(axis=0).mean())


def unique_chord(pts: np.ndarray, rel_gap: float = 1e-6) -> bool:
    """True if every pair within rel_gap of the longest chord joins the same two locations."""
    d = pairwise(pts)
    i, j = np.nonzero(np.triu(d >= d.max() * (1 - rel_gap), 1))
    return len(np.unique(np.concatenate([pts[i], pts[j]]), axis=0)) == 2


def rotate(pts: np.ndarray, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return pts @ np.array([[c, s], [-s, c]])


def ring(n: int, radii: np.ndarray | float, centre: tuple[float, float] = (0.5, 0.5)) -> np.ndarray:
    t = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    return np.c_[centre[0] + radii * np.cos(t), centre[1] + radii * np.sin(t)]


def coupler_curves(count: int, steps: int = 200, seed: int = 0) -> np.ndarray:
    """Coupler, rocker and crank paths of random Grashof four-bars, randomly placed."""
    rng = np.random.default_rng(seed)
    th = np.linspace(0, 2 * np.pi, steps, endpoint=False)
    out: list[np.ndarray] = []
    while len(out) < count:
        crank, ground, coupler, rocker = rng.uniform([0.05, 0.3, 0.2, 0.2], [0.3, 1, 1.2, 1.2])
        a = np.c_[crank * np.cos(th), crank * np.sin(th)]
        d = np.linalg.norm(a - [ground, 0.0], axis=1)
        if np.any(d > coupler + rocker) or np.any(d < abs(coupler - rocker)):
            continue
        along = (coupler**2 - rocker**2 + d**2) / (2 * d)
        up = np.sqrt(np.maximum(coupler**2 - along**2, 0))
        u = ([ground, 0.0] - a) / d[:, None]
        b = a + along[:, None] * u + up[:, None] * np.c_[-u[:, 1], u[:, 0]]
        e = b - a
        off = rng.normal(size=2)
        c = a + off[0] * e + off[1] * np.c_[-e[:, 1], e[:, 0]]
        path = (c, b, a)[len(out) % 3]
        out.append(
            rotate(path, rng.uniform(0, 2 * np.pi)) * rng.uniform(0.5, 2) + rng.normal(size=2)
        )
    return np.array(out)


# --------------------------------------------------------------------------- normalize_path


def check_normalized(pts: np.ndarray, out: np.ndarray) -> None:
    assert out.shape == pts.shape and out.dtype == np.float64
    i, j = longest_chord(pts)
    assert i < j
    assert out[i, 1] == out[j, 1]  # exactly horizontal
    assert out[j, 0] - out[i, 0] == pytest.approx(1.0, abs=1e-12)  # lower index -> higher: +x
    assert pairwise(out).max() == pytest.approx(1.0, abs=1e-12)
    lo, hi = out.min(axis=0), out.max(axis=0)
    np.testing.assert_allclose((lo + hi) / 2, [0.5, 0.5], atol=1e-12)


@SETTINGS
@given(point_sets())
def test_normalize_path_chord_and_box(pts: np.ndarray) -> None:
    assume(pairwise(pts).max() >= 1.0)
    check_normalized(pts, normalize_path(pts))


def test_normalize_path_examples() -> None:
    for pts in [*coupler_curves(6), np.random.default_rng(1).normal(size=(500, 2))]:
        check_normalized(pts, normalize_path(pts))
    np.testing.assert_array_equal(normalize_path([[3, 4], [1, 4]]), [[0, 0.5], [1, 0.5]])
    np.testing.assert_array_equal(normalize_path([[0, 0], [0, 2]]), [[0, 0.5], [1, 0.5]])


@SETTINGS
@given(
    point_sets(),
    st.floats(0, 2 * np.pi),
    st.floats(-3, 3),
    st.tuples(st.floats(-100, 100), st.floats(-100, 100)),
)
def test_normalize_path_similarity_invariant(
    pts: np.ndarray, angle: float, log_scale: float, shift: tuple[float, float]
) -> None:
    assume(pairwise(pts).max() >= 1.0 and unique_chord(pts))
    moved = rotate(pts, angle) * 10.0**log_scale + np.array(shift)
    np.testing.assert_allclose(normalize_path(moved), normalize_path(pts), rtol=0, atol=1e-9)


def test_normalize_path_extreme_scales() -> None:
    pts = coupler_curves(1, seed=3)[0]
    ref = normalize_path(pts)
    for factor in (1e-300, 1e-150, 1e150, 1e300):
        np.testing.assert_allclose(normalize_path(pts * factor), ref, rtol=0, atol=1e-12)


@SETTINGS
@given(point_sets(), st.floats(-6, 6), st.tuples(st.floats(-100, 100), st.floats(-100, 100)))
def test_normalization_is_normalize_path_and_the_similarity_that_does_it(
    pts: np.ndarray, log_scale: float, shift: tuple[float, float]
) -> None:
    """normalization gives normalize_path's points exactly, and a matrix and offset that map
    the input onto them: a turn and a uniform scale (never a mirror) plus a shift."""
    assume(pairwise(pts).max() >= 1.0)
    moved = pts * 10.0**log_scale + np.array(shift)
    normalized, matrix, offset = normalization(moved)
    np.testing.assert_array_equal(normalized, normalize_path(moved))
    i, j = longest_chord(moved)
    # Checked against the chord: it goes to a unit vector along +x.
    np.testing.assert_allclose((moved[j] - moved[i]) @ matrix.T, [1.0, 0.0], atol=1e-12)
    assert matrix[0, 0] == matrix[1, 1] and matrix[0, 1] == -matrix[1, 0]
    assert np.linalg.det(matrix) > 0
    # Relative to the input's own size: the shift may be far larger than the path.
    size = np.abs(moved).max() / np.ptp(moved, axis=0).max()
    np.testing.assert_allclose(moved @ matrix.T + offset, normalized, rtol=0, atol=1e-12 * size)


def test_normalization_at_extreme_scales() -> None:
    pts = coupler_curves(1, seed=3)[0]
    for factor in (1e-300, 1e-150, 1e150, 1e300):
        normalized, matrix, offset = normalization(pts * factor)
        np.testing.assert_array_equal(normalized, normalize_path(pts * factor))
        np.testing.assert_allclose(pts * factor @ matrix.T + offset, normalized, atol=1e-12)


def test_normalize_path_index_direction() -> None:
    pts = coupler_curves(1, seed=5)[0]
    assert unique_chord(pts)
    # Reversing the point order swaps the chord's ends: a half turn about (0.5, 0.5).
    np.testing.assert_allclose(normalize_path(pts[::-1])[::-1], 1 - normalize_path(pts), atol=1e-12)


def test_longest_chord_ties_take_lowest_index_pair() -> None:
    assert longest_chord([[0, 0], [1, 0], [1, 1], [0, 1]]) == (0, 2)
    assert longest_chord([[1, 1], [0, 0], [0, 1], [1, 0]]) == (0, 1)
    assert longest_chord([[0, 1], [1, 0], [1, 1], [0, 0]]) == (0, 1)
    assert longest_chord([[3, 0], [0, 0], [3, 0], [0, 0]]) == (0, 1)
    assert longest_chord([[0.5, 0], [0, 0], [1, 0], [0, 0], [1, 0]]) == (1, 2)
    # Regular hexagon: three diameters of (numerically) equal length.
    hexagon = ring(6, 1.0, (0.0, 0.0))[[3, 1, 4, 0, 2, 5]]
    assert longest_chord(hexagon) == brute_chord(hexagon)[:2]


@functools.cache
def random_sets() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(7)
    t = rng.uniform(-1, 1, 3000)
    line = np.c_[t, 0.3 * t + 0.1]
    line[rng.integers(0, 3000, 500)] = line[rng.integers(0, 3000, 500)]  # duplicates
    angles = rng.uniform(0, 2 * np.pi, 10_000)
    return {
        "uniform_10k": rng.uniform(-5, 5, (10_000, 2)),
        "circle_10k": np.c_[np.cos(angles), np.sin(angles)],
        "disk_2k": ring(2000, np.sqrt(rng.random(2000))),
        "gaussian_2k": rng.normal(size=(2000, 2)),
        "collinear_dupes": line,
        "vertical_line": np.c_[np.zeros(400), rng.permutation(400) % 37],
        "near_collinear": np.c_[t, 2 * t + rng.normal(scale=1e-13, size=3000)],
        "integer_grid_ties": rng.integers(0, 6, (300, 2)).astype(float),
        "two_locations": np.array([[2.0, 1.0], [-1.0, 5.0]])[rng.integers(0, 2, 50)],
        "coupler_curve": coupler_curves(1, seed=11)[0],
    }


@pytest.mark.parametrize("name", random_sets())
def test_longest_chord_equals_brute_force(name: str) -> None:
    pts = random_sets()[name]
    assert longest_chord(pts) == brute_chord(pts)[:2]


@SETTINGS
@given(
    hnp.arrays(np.float64, st.tuples(st.integers(2, 40), st.just(2)), elements=st.integers(-4, 4))
)
def test_longest_chord_equals_brute_force_with_ties(pts: np.ndarray) -> None:
    assume(np.ptp(pts, axis=0).any())
    assert longest_chord(pts) == brute_chord(pts)[:2]


# --------------------------------------------------------------------------- normalize_paths


def test_normalize_paths_equals_normalize_path() -> None:
    batch = coupler_curves(60)
    batch[7] = np.random.default_rng(2).integers(0, 4, (200, 2))  # many tied chords
    batch[8] = batch[8][::-1]
    out = normalize_paths(batch)
    assert out.shape == batch.shape and out.dtype == np.float64
    for path, row in zip(batch, out, strict=True):
        np.testing.assert_array_equal(row, normalize_path(path))
    single = normalize_paths(batch.astype(np.float32))
    for path, row in zip(batch.astype(np.float32), single, strict=True):
        np.testing.assert_array_equal(row, normalize_path(path))


def test_normalize_paths_ignores_exact_powers_of_two() -> None:
    """Scaling by 2**k rounds nothing, so the normalized rows are the same bits, at the
    extremes of the exponent range too (where the kernel scales another way)."""
    batch = coupler_curves(20, seed=4)
    batch[3] = np.random.default_rng(6).integers(0, 4, (200, 2))  # many tied chords
    # Every coordinate in [0.5, 1): scaled by 2**-1021 they stay normal numbers.
    low, high = batch.min(axis=(1, 2), keepdims=True), batch.max(axis=(1, 2), keepdims=True)
    batch = 0.5 + 0.4 * (batch - low) / (high - low)
    reference = normalize_paths(batch)
    for k in (-1021, -600, -1, 1, 600, 1021, 1022):
        np.testing.assert_array_equal(normalize_paths(batch * 2.0**k), reference)


def test_normalize_paths_places_the_brute_force_chord() -> None:
    """The batch kernel's chord (pruned by box bounds) is every-pair search's: its ends land
    1 apart on one horizontal line."""
    rng = np.random.default_rng(9)
    batch = np.concatenate([coupler_curves(40, seed=8), rng.integers(-3, 4, (20, 200, 2))])
    for path, row in zip(batch, normalize_paths(batch), strict=True):
        i, j, _ = brute_chord(path.astype(np.float64))
        assert row[j, 1] == row[i, 1] and row[j, 0] - row[i, 0] == pytest.approx(1.0, abs=1e-12)


def test_normalize_paths_no_extent_gives_nan_rows() -> None:
    batch = coupler_curves(3)
    batch[1] = [2.5, -1.0]
    out = normalize_paths(batch)
    assert np.isnan(out[1]).all()
    np.testing.assert_array_equal(out[0], normalize_path(batch[0]))
    np.testing.assert_array_equal(out[2], normalize_path(batch[2]))
    assert normalize_paths(np.zeros((0, 200, 2))).shape == (0, 200, 2)


# --------------------------------------------------------------------------- circles


def test_circle_is_circle_and_ellipse_is_not() -> None:
    circle = normalize_path(ring(200, 3.0, (7.0, -2.0)))
    assert circle_variance(circle) < 1e-20
    assert is_circle(circle)
    ellipse = normalize_path(ring(200, 3.0, (7.0, -2.0)) * [1.0, 0.5])
    assert circle_variance(ellipse) > 10 * CIRCLE_VARIANCE_THRESHOLD
    assert not is_circle(ellipse)
    wobbly = normalize_path(ring(200, 1.0 + 0.01 * np.sin(np.linspace(0, 14 * np.pi, 200))))
    assert is_circle(wobbly)


@pytest.mark.parametrize("factor", [0.999, 0.999999, 1.000001, 1.001])
def test_circle_threshold_boundary(factor: float) -> None:
    # Alternating radii 0.5 +- delta: mean 0.5, population variance delta**2.
    delta = math.sqrt(CIRCLE_VARIANCE_THRESHOLD * factor)
    pts = ring(400, 0.5 + delta * (-1.0) ** np.arange(400))
    variance = circle_variance(pts)
    assert variance == pytest.approx(CIRCLE_VARIANCE_THRESHOLD * factor, rel=1e-9)
    assert is_circle(pts) is (factor < 1)


def test_circle_variance_is_population_variance() -> None:
    pts = np.random.default_rng(4).random((37, 2))
    expected = np.var(np.linalg.norm(pts - 0.5, axis=1))
    assert circle_variance(pts) == pytest.approx(expected, rel=1e-12)
    assert circle_variance([[0.5, 0.9]]) == 0.0


def test_circle_variances_equals_circle_variance() -> None:
    batch = normalize_paths(coupler_curves(30))
    values = circle_variances(batch)
    assert values.shape == (30,) and values.dtype == np.float64
    np.testing.assert_array_equal(values, [circle_variance(p) for p in batch])
    np.testing.assert_array_equal(
        circle_variances(batch.astype(np.float32)),
        [circle_variance(p) for p in batch.astype(np.float32)],
    )
    batch[3] = np.nan
    assert np.isnan(circle_variances(batch)[3])
    assert (circle_variances(batch)[:3] == values[:3]).all()
    # Every third four-bar path is a crank circle.
    assert all(is_circle(p) for p in batch[2::3])


# --------------------------------------------------------------------------- chamfer


@pytest.mark.parametrize("sizes", [(1, 1), (1, 7), (13, 200), (200, 200), (257, 31)])
def test_chamfer_equals_brute_force(sizes: tuple[int, int]) -> None:
    rng = np.random.default_rng(sum(sizes))
    a, b = rng.normal(size=(sizes[0], 2)), rng.random((sizes[1], 2))
    assert chamfer(a, b) == pytest.approx(brute_chamfer(a, b), rel=1e-12)
    assert chamfer(a, b) == chamfer(b, a)


@SETTINGS
@given(point_sets(1, 30, grid_coords), point_sets(1, 30, grid_coords))
def test_chamfer_properties(a: np.ndarray, b: np.ndarray) -> None:
    value = chamfer(a, b)
    assert value == pytest.approx(brute_chamfer(a, b), rel=1e-12, abs=1e-12)
    assert value == chamfer(b, a)
    assert chamfer(a, a) == 0.0
    assert chamfer(a, a[np.random.default_rng(len(a)).permutation(len(a))]) == 0.0
    same = {tuple(p) for p in a} == {tuple(p) for p in b}
    assert (value == 0.0) is same


def test_chamfer_to_many_equals_chamfer() -> None:
    rng = np.random.default_rng(9)
    query = rng.random((150, 2))
    candidates = normalize_paths(coupler_curves(40))
    expected = [chamfer(query, c) for c in candidates]
    np.testing.assert_array_equal(chamfer_to_many(query, candidates), expected)
    out = np.full(40, -1.0)
    assert chamfer_to_many(query, candidates, out=out) is out
    np.testing.assert_array_equal(out, expected)
    as32 = candidates.astype(np.float32)
    np.testing.assert_array_equal(
        chamfer_to_many(query, as32), [chamfer(query, c.astype(np.float64)) for c in as32]
    )
    assert chamfer_to_many(query, np.zeros((0, 200, 2))).shape == (0,)


# --------------------------------------------------------------------------- bad input

NAN_POINTS = [[0.0, 0.0], [1.0, np.nan], [2.0, 1.0]]
BAD_POINTS = [
    (np.zeros((3, 3)), r"shape \(T, 2\)"),
    (np.zeros(5), r"shape \(T, 2\)"),
    (np.zeros((2, 2, 2)), r"shape \(T, 2\)"),
    ([[1.0, 2.0], [3.0]], "numeric array"),
    ([["a", "b"], ["c", "d"]], "numeric"),
    (np.ones((3, 2), dtype=bool), "numeric"),
    (np.ones((3, 2), dtype=complex), "numeric"),
    (None, "numeric"),
    (NAN_POINTS, "finite"),
    ([[0.0, 0.0], [np.inf, 1.0]], "finite"),
]


@pytest.mark.parametrize("func", [normalize_path, longest_chord])
@pytest.mark.parametrize(
    ("points", "match"),
    [
        *BAD_POINTS,
        ([[1.0, 2.0]], "at least 2 points"),
        (np.zeros((0, 2)), "at least 2 points"),
        ([[1.5, 2.0]] * 4, "same point"),
    ],
)
def test_normalize_path_bad_input(func: object, points: object, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        func(points)  # type: ignore[operator]


@pytest.mark.parametrize(
    ("paths", "match"),
    [
        (np.zeros((4, 2)), r"shape \(P, T, 2\)"),
        (np.zeros((2, 5, 3)), r"shape \(P, T, 2\)"),
        (np.zeros((2, 1, 2)), "at least 2 points"),
        ([[["a", "b"], ["c", "d"]]], "numeric"),
        (np.array([[[0.0, 0.0], [1.0, 1.0]], NAN_POINTS[:2]]), r"finite \(path 1"),
    ],
)
def test_normalize_paths_bad_input(paths: object, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        normalize_paths(paths)


@pytest.mark.parametrize(("points", "match"), [*BAD_POINTS, (np.zeros((0, 2)), "at least 1 point")])
def test_circle_variance_bad_input(points: object, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        circle_variance(points)
    with pytest.raises(ValueError, match=match):
        is_circle(points)


def test_circle_variances_bad_input() -> None:
    with pytest.raises(ValueError, match=r"shape \(P, T, 2\)"):
        circle_variances(np.zeros((5, 2)))
    with pytest.raises(ValueError, match="at least 1 point"):
        circle_variances(np.zeros((3, 0, 2)))
    with pytest.raises(ValueError, match="numeric"):
        circle_variances([[["x", "y"]]])


@pytest.mark.parametrize(("points", "match"), [*BAD_POINTS, (np.zeros((0, 2)), "at least 1 point")])
def test_chamfer_bad_input(points: object, match: str) -> None:
    good = [[0.0, 0.0], [1.0, 1.0]]
    calls = {
        "a": lambda: chamfer(points, good),
        "b": lambda: chamfer(good, points),
        "query": lambda: chamfer_to_many(points, np.zeros((1, 2, 2))),
    }
    for name, call in calls.items():
        with pytest.raises(ValueError, match=match) as info:
            call()
        assert str(info.value).startswith(f"{name} ")


def test_chamfer_to_many_bad_input() -> None:
    query = np.random.default_rng(0).random((10, 2))
    cands = np.random.default_rng(1).random((3, 20, 2))
    with pytest.raises(ValueError, match=r"candidates must have shape \(P, T, 2\)"):
        chamfer_to_many(query, cands[0])
    with pytest.raises(ValueError, match="candidates must have at least 1 point"):
        chamfer_to_many(query, np.zeros((3, 0, 2)))
    with pytest.raises(ValueError, match="candidates must be numeric"):
        chamfer_to_many(query, cands.astype(complex))
    bad = cands.copy()
    bad[2, 5, 0] = np.inf
    with pytest.raises(ValueError, match=r"finite \(candidate 2"):
        chamfer_to_many(query, bad)
    for out in (np.empty(2), np.empty(3, dtype=np.float32), np.empty(6)[::2], [0.0] * 3):
        with pytest.raises(ValueError, match=r"out must be .* shape \(3,\)"):
            chamfer_to_many(query, cands, out=out)  # type: ignore[arg-type]
    frozen = np.empty(3)
    frozen.flags.writeable = False
    with pytest.raises(ValueError, match="out must be a writeable"):
        chamfer_to_many(query, cands, out=frozen)
