"""The curve set of `links bench synthesize --set` (links_ray.bench.curves.curve_set): its size,
names, families, halves fixed by name, even spacing, closure, letters read from two different fonts,
random curves that never cross themselves, self-crossing curves that cross as their kind says,
traced curves that their mechanisms trace again, GCP-HOLO's curves held out, and determinism."""

from __future__ import annotations

import random
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from links_ray.bench.curves.curve_set import (
    CURVE_POINTS,
    FONTS,
    LETTERS,
    SetCurve,
    crosses_itself,
    curve_set,
    font_file,
    half_of,
    letter_outlines,
)
from links_ray.bench.targets import target_curves
from links_ray.engine.kinematics.paths import chamfer

FAMILIES = {
    "letter_outline",
    "letter_stroke",
    "gait",
    "cam",
    "random_smooth",
    "self_crossing",
    "traced",
    "gcp_holo_test",
    "gcp_holo_gait",
}
#: The families drawn from the seed.
SEEDED = {"random_smooth", "self_crossing", "traced"}
#: The set's own closed curves that never cross themselves, drawn counter-clockwise.
SIMPLE_CLOSED = {"letter_outline", "gait", "cam", "random_smooth"}


@pytest.fixture(scope="module")
def curves() -> list[SetCurve]:
    """The set as the bench draws it (seed 0)."""
    return curve_set()


def gaps(curve: SetCurve) -> np.ndarray:
    """Distances between consecutive points, the closing one included for a closed curve."""
    points = curve.points if curve.partial else np.concatenate([curve.points, curve.points[:1]])
    return np.linalg.norm(np.diff(points, axis=0), axis=1)


def segments_cross(p: np.ndarray, q: np.ndarray, r: np.ndarray, s: np.ndarray) -> bool:
    """Whether segments pq and rs share a point (orientation tests, collinear overlap too)."""

    def orient(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> float:
        return float((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]))

    def within(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> bool:
        return min(a[0], b[0]) <= c[0] <= max(a[0], b[0]) and min(a[1], b[1]) <= c[1] <= max(
            a[1], b[1]
        )

    d1, d2, d3, d4 = orient(p, q, r), orient(p, q, s), orient(r, s, p), orient(r, s, q)
    if ((d1 > 0 > d2) or (d1 < 0 < d2)) and ((d3 > 0 > d4) or (d3 < 0 < d4)):
        return True
    return any(
        d == 0 and within(a, b, c)
        for d, a, b, c in ((d1, p, q, r), (d2, p, q, s), (d3, r, s, p), (d4, r, s, q))
    )


def brute_force_crosses(loop: np.ndarray) -> bool:
    """Whether any two non-adjacent edges of the closed polyline `loop` share a point."""
    n = len(loop)
    for i in range(n):
        for j in range(i + 2, n):
            if i == 0 and j == n - 1:
                continue
            if segments_cross(loop[i], loop[(i + 1) % n], loop[j], loop[(j + 1) % n]):
                return True
    return False


def test_set_holds_named_finite_curves_of_nine_families(curves: list[SetCurve]) -> None:
    assert len(curves) >= 100
    names = [curve.name for curve in curves]
    assert len(set(names)) == len(names)
    assert {curve.family for curve in curves} == FAMILIES
    for curve in curves:
        assert curve.points.shape == (CURVE_POINTS, 2), curve.name
        assert np.isfinite(curve.points).all(), curve.name
        assert curve.partial == (curve.family == "letter_stroke"), curve.name
    # Both fonts give every letter, as an outline and as a stroke.
    counts = Counter(curve.family for curve in curves)
    assert counts["letter_outline"] == counts["letter_stroke"] == len(FONTS) * len(LETTERS)


def test_every_family_is_in_both_halves_but_the_fields_benchmark(
    curves: list[SetCurve],
) -> None:
    for family in FAMILIES - {"gcp_holo_test", "gcp_holo_gait"}:
        halves = Counter(curve.half for curve in curves if curve.family == family)
        assert halves["tuning"] > 0 and halves["held-out"] > 0, (family, halves)
        assert set(halves) == {"tuning", "held-out"}
    # The field's benchmark is never tuned on.
    field = [curve for curve in curves if curve.family.startswith("gcp_holo")]
    assert len(field) == 12 and {curve.half for curve in field} == {"held-out"}


def test_half_is_fixed_by_name_whatever_the_order_or_seed(curves: list[SetCurve]) -> None:
    names = [curve.name for curve in curves]
    shuffled = names[:]
    random.Random(7).shuffle(shuffled)
    assert {name: half_of(name) for name in shuffled} == {c.name: c.half for c in curves}
    # Another seed draws other random curves under the same names, in the same halves.
    other = {c.name: c.half for c in curve_set(seed=1)}
    assert other == {c.name: c.half for c in curves}
    # A letter's curves, in both fonts, outline and stroke, are in one half.
    for letter in LETTERS:
        halves = {
            c.half for c in curves if c.family.startswith("letter") and f"_{letter}_" in c.name
        }
        assert len(halves) == 1, letter
    # The split is pinned: a change that moves a curve to the other half fails here.
    assert [half_of(name) for name in ("sans_E_outline", "serif_Z_stroke", "gait_low")] == [
        "tuning",
        "held-out",
        "tuning",
    ]


def test_points_are_evenly_spaced_by_arc_length(curves: list[SetCurve]) -> None:
    for curve in curves:
        step = gaps(curve)
        median = np.median(step)
        # Chords are shorter than the arc only where a corner falls between two points.
        assert step.max() <= 1.001 * median, curve.name
        assert np.mean(np.abs(step / median - 1) < 0.01) >= 0.9, curve.name


def test_closed_curves_close_and_strokes_stay_open(curves: list[SetCurve]) -> None:
    for curve in curves:
        step = np.linalg.norm(np.diff(curve.points, axis=0), axis=1)
        ends = float(np.linalg.norm(curve.points[-1] - curve.points[0]))
        if curve.partial:
            assert ends > 10 * np.median(step), curve.name
        else:
            assert ends <= 1.001 * np.median(step), curve.name
            if curve.family in SIMPLE_CLOSED:
                x, y = curve.points[:, 0], curve.points[:, 1]
                area = np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))
                assert area > 0, f"{curve.name} is not counter-clockwise"


def test_random_smooth_curves_never_cross_themselves(curves: list[SetCurve]) -> None:
    random_curves = [curve for curve in curves if curve.family == "random_smooth"]
    assert len(random_curves) >= 6
    for curve in random_curves:
        assert not brute_force_crosses(curve.points), curve.name


def test_crossing_check_agrees_with_brute_force() -> None:
    eight = target_curves(120)["figure_eight"]
    ellipse = target_curves(120)["ellipse"]
    bowtie = np.array([[0.0, 0.0], [1.0, 1.0], [1.0, 0.0], [0.0, 1.0]])
    square = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    for loop, crosses in ((eight, True), (ellipse, False), (bowtie, True), (square, False)):
        assert brute_force_crosses(loop) is crosses
        assert crosses_itself(loop) is crosses


def test_letters_come_from_two_different_fonts(curves: list[SetCurve]) -> None:
    by_name = {curve.name: curve.points for curve in curves}
    for letter in LETTERS:
        sans, serif = by_name[f"sans_{letter}_outline"], by_name[f"serif_{letter}_outline"]
        # Framed to a box of side 2: a serif moves the outline by well over a point's spacing.
        assert chamfer(sans, serif) > 0.02, letter
    # Different letters of one font differ too (the glyph looked up is the letter's).
    assert chamfer(by_name["sans_E_outline"], by_name["sans_S_outline"]) > 0.1


def test_outline_spans_the_glyph_bounds_the_font_gives() -> None:
    from fontTools.pens.boundsPen import BoundsPen
    from fontTools.ttLib import TTFont

    for filename in FONTS.values():
        path = font_file(filename)
        font = TTFont(str(path))
        glyphs, cmap = font.getGlyphSet(), font.getBestCmap()
        for letter, outline in letter_outlines(path).items():
            pen = BoundsPen(glyphs)
            glyphs[cmap[ord(letter)]].draw(pen)
            low = outline.min(axis=0)
            high = outline.max(axis=0)
            # The outer contour encloses the others, so its extent is the glyph's.
            assert np.allclose([*low, *high], pen.bounds, atol=0.5), (filename, letter)


def test_same_seed_same_arrays_and_seed_moves_only_random_curves(
    curves: list[SetCurve],
) -> None:
    again = curve_set()
    other = {curve.name: curve.points for curve in curve_set(seed=1)}
    for first, second in zip(curves, again, strict=True):
        assert first.name == second.name
        assert np.array_equal(first.points, second.points), first.name
        moved = not np.array_equal(first.points, other[first.name])
        assert moved == (first.family in SEEDED), first.name


def test_missing_font_names_the_package(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="fonts-liberation"):
        curve_set(font_dirs=(tmp_path,))


def test_set_groups_sum_up_by_half_and_family() -> None:
    from links_ray.bench.synthesis_report import set_groups

    def row(family: str, half: str, retrieved: float, refined: float, seconds: float) -> dict:
        return {"family": family, "half": half, "retrieved": retrieved, "refined": refined,
                "seconds": seconds}  # fmt: skip

    rows = [
        row("gait", "tuning", 0.02, 0.01, 1.0),
        row("gait", "tuning", 0.06, 0.03, 3.0),
        row("cam", "held-out", 0.04, 0.02, 2.0),
        row("letter_outline", "held-out", 0.10, 0.04, 4.0),
    ]
    groups = {(g["half"], g["family"]): g for g in set_groups(rows)}
    gait = groups["tuning", "gait"]
    assert gait["curves"] == 2 and gait["mean_refined"] == pytest.approx(0.02)
    assert gait["ratio"] == pytest.approx(0.5) and gait["worst_seconds"] == 3.0
    assert gait["median_seconds"] == pytest.approx(2.0)
    smooth = groups["all", "smooth_closed"]
    assert smooth["curves"] == 3 and smooth["mean_refined"] == pytest.approx(0.02)
    held = groups["held-out", "all"]
    assert held["curves"] == 2 and held["mean_retrieved"] == pytest.approx(0.07)
    assert held["median_refined"] == pytest.approx(0.03)
    assert ("tuning", "cam") not in groups  # no curves, no group
    assert groups["all", "all"]["curves"] == 4


def test_even_reference_of_a_stroke_stays_on_the_stroke() -> None:
    from links_ray.bench.synthesis import even_reference
    from links_ray.engine.kinematics.paths import even_along

    corner = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0]])
    stroke = even_along(corner, 200, closed=False)
    # Open, the even points lie on the stroke; closed, a third of them run back across it.
    assert even_reference(stroke, closed=False) < 0.01
    assert even_reference(stroke, closed=True) > 0.05


def test_a_set_curve_frame_depends_on_its_name_and_seed_only() -> None:
    from links_ray.bench.synthesis import name_rng
    from links_ray.bench.targets import placed

    curve = target_curves(50)["bean"]
    first = placed(curve, name_rng(0, "cam_dwell"))
    assert np.array_equal(first, placed(curve, name_rng(0, "cam_dwell")))
    assert not np.allclose(first, placed(curve, name_rng(0, "cam_short")))
    assert not np.allclose(first, placed(curve, name_rng(1, "cam_dwell")))


def test_a_bench_row_of_counted_work_is_reproduced_bit_for_bit(
    dataset: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Deterministic mode: a row of `links bench synthesize --set --iterations N` is the same
    whether run with the others or alone (`--curve`), and whatever the threads."""
    from links_ray.bench.synthesis import bench_synthesize
    from links_ray.engine import cpus

    # An open stroke and a closed curve, the latter's row after the other's in the first run.
    names = ("sans_M_stroke", "cam_dwell")

    def rows(only: tuple[str, ...], given: float | None) -> dict[str, dict]:
        monkeypatch.setattr(cpus, "_given", given)
        result = bench_synthesize(root=dataset, use_set=True, only=only, iterations=60, seed=4)
        assert [row["curve"] for row in result["curves"]] == [n for n in names if n in only]
        for row in result["curves"]:
            assert row.pop("seconds") > 0  # the one field that measures the machine
        return {row["curve"]: row for row in result["curves"]}

    together = rows(names, None)
    alone = rows(names[1:], 1.0)
    assert together[names[1]] == alone[names[1]]
    assert together[names[0]]["partial"] and not together[names[1]]["partial"]
    # Counted work is not idle: the rows moved from their retrieval.
    assert all(row["refined"] < row["retrieved"] for row in together.values())
    with pytest.raises(ValueError, match="no curve named nope"):
        bench_synthesize(root=dataset, use_set=True, only=("nope",), iterations=1)


def brute_force_crossings(loop: np.ndarray) -> int:
    """How many pairs of non-adjacent edges of the closed polyline `loop` share a point."""
    n = len(loop)
    return sum(
        segments_cross(loop[i], loop[(i + 1) % n], loop[j], loop[(j + 1) % n])
        for i in range(n)
        for j in range(i + 2, n)
        if not (i == 0 and j == n - 1)
    )


def test_self_crossing_curves_cross_as_often_as_their_kind(curves: list[SetCurve]) -> None:
    """Counted on the set's evenly spaced points, pair by pair, apart from the generator's own
    count: an eight, a dual loop and an hourglass cross once, a trefoil three times."""
    from links_ray.bench.curves.crossing import KIND_CROSSINGS, crossings

    crossing = [curve for curve in curves if curve.family == "self_crossing"]
    assert {curve.name.rsplit("_", 1)[0] for curve in crossing} == {
        f"crossing_{kind}" for kind in KIND_CROSSINGS
    }
    for curve in crossing:
        kind = curve.name.removeprefix("crossing_").rsplit("_", 1)[0]
        assert brute_force_crossings(curve.points) == KIND_CROSSINGS[kind], curve.name
        assert crossings(curve.points) == KIND_CROSSINGS[kind], curve.name
    # And the generator's count is the brute force's on shapes known by heart.
    bowtie = np.array([[0.0, 0.0], [1.0, 1.0], [1.0, 0.0], [0.0, 1.0]])
    pentagram = np.exp(2j * np.pi * np.arange(5) * 2 / 5)
    star = np.column_stack([pentagram.real, pentagram.imag])
    assert crossings(bowtie) == brute_force_crossings(bowtie) == 1
    assert crossings(star) == brute_force_crossings(star) == 5


def test_traced_curves_are_traced_again_by_their_mechanisms() -> None:
    """Each traced curve is the path of a valid mechanism of 6-12 joints: simulated again, the
    mechanism draws it exactly; the joint is not linked to a fixed one (no arc), and the curve
    is neither a circle nor a swing to and fro."""
    from links_ray.bench.curves.traced import (
        TRACED_JOINTS,
        TRACED_STEPS,
        retraces,
        traced_curves,
    )
    from links_ray.engine.kinematics.mechanism import FIXED
    from links_ray.engine.kinematics.paths import is_circle, normalize_path
    from links_ray.engine.kinematics.solver import simulate

    traced = traced_curves(seed=0, count=6)
    assert list(traced) == [f"traced_{i:02d}" for i in range(6)]
    for name, curve in traced.items():
        n = len(curve.node_types)
        assert TRACED_JOINTS[0] <= n <= TRACED_JOINTS[1], name
        again = simulate(curve.adjacency, curve.node_types, curve.positions, TRACED_STEPS)
        again = again[curve.joint]
        np.testing.assert_array_equal(again, curve.points, err_msg=name)
        neighbours = np.flatnonzero(curve.adjacency[curve.joint])
        assert curve.node_types[curve.joint] != FIXED, name
        assert np.all(curve.node_types[neighbours] != FIXED), name
        normalized = normalize_path(curve.points)
        assert not is_circle(normalized) and not retraces(normalized), name
    # Curve i depends on (seed, i) alone.
    assert np.array_equal(
        traced_curves(seed=0, count=3)["traced_02"].points, traced["traced_02"].points
    )
    # A swing to and fro is caught: an arc out and back.
    angle = np.concatenate([np.linspace(0, 1, 100), np.linspace(1, 0, 100)])
    assert retraces(normalize_path(np.column_stack([np.cos(angle), np.sin(angle)])))


def test_gcp_holo_curves_are_stored_with_their_source() -> None:
    """The field's benchmark: GCP-HOLO's eight test curves (as many points as published) and
    four foot paths, closed, their source named."""
    from links_ray.bench.curves.gcp_holo import gcp_holo_curves, gcp_holo_source

    curves = gcp_holo_curves()
    sizes = {name: len(points) for name, points in curves["test"].items()}
    assert sizes == {
        "holo_dualloop": 86,
        "holo_eight": 50,
        "holo_hourglass": 93,
        "holo_letterB": 74,
        "holo_moon": 62,
        "holo_outerTrifoil": 77,
        "holo_triangle": 55,
        "holo_trifoil": 96,
    }
    assert sorted(curves["gait"]) == [
        f"holo_gait_{g}" for g in ("jansen", "klann", "strider", "trot")
    ]
    for family in curves.values():
        for name, points in family.items():
            steps = np.linalg.norm(np.diff(points, axis=0), axis=1)
            # Closed, the first point not repeated: the closing step is an ordinary one.
            assert 0 < np.linalg.norm(points[-1] - points[0]) < 2 * steps.max(), name
    source = gcp_holo_source()
    assert source["repository"].endswith("gcp_holo") and len(source["commit"]) == 40
    assert "noncommercial" in source["license"]
    # The eight, the hourglass, the trefoils and the dual loop cross themselves; the moon not.
    from links_ray.bench.curves.crossing import crossings

    assert crossings(curves["test"]["holo_eight"]) >= 1
    assert crossings(curves["test"]["holo_moon"]) == 0


def test_the_time_dial_reports_each_family_at_each_budget(dataset: str) -> None:
    """`bench_dial` runs the set at every budget and gives each half and family's mean and
    median at each: the same figures as the run at that budget."""
    from links_ray.bench.synthesis import bench_dial
    from links_ray.bench.synthesis_report import format_dial

    names = ("cam_dwell", "crossing_eight_0")
    result = bench_dial(budgets=(0.2, 0.5), root=dataset, use_set=True, only=names)
    assert result["budgets_s"] == [0.2, 0.5] and len(result["runs"]) == 2
    entries = {(e["half"], e["family"]): e for e in result["dial"]}
    assert {("tuning", "self_crossing"), ("tuning", "cam"), ("all", "all")} <= set(entries)
    for run, budget in zip(result["runs"], ("0.2", "0.5"), strict=True):
        assert run["budget_s"] == float(budget)
        for group in run["groups"]:
            at = entries[group["half"], group["family"]]["by_budget"][budget]
            assert at["mean_refined"] == group["mean_refined"]
            assert at["median_refined"] == group["median_refined"]
    table = format_dial(result)
    assert "| 0.2 s | 0.5 s |" in table and "self_crossing" in table


def test_the_dial_refuses_its_own_budget_in_one_line() -> None:
    import subprocess
    import sys

    done = subprocess.run(
        [sys.executable, "-m", "links_ray.cli", "bench", "synthesize", "--dial", "--seconds", "3"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode != 0
    assert done.stderr.strip().count("\n") == 0 and "--dial runs its own budgets" in done.stderr
