"""Target curves read from drawings (links_ray.interop.curve_files), in Python and on the CLI:
against circles, hand-applied transforms, ezdxf's own evaluation and `even_along` of the same
polylines."""

from __future__ import annotations

import json
import math
from pathlib import Path

import ezdxf
import numpy as np
import pytest

from links_ray.engine.kinematics.paths import even_along
from links_ray.interop.curve_files import read_curve
from links_ray.interop.curve_limits import MAX_CURVE_FILE_BYTES
from tests.support.cli import links

SVG = '<svg xmlns="http://www.w3.org/2000/svg"{attrs}>{body}</svg>'


def svg_file(folder: Path, body: str, name: str = "drawing.svg", attrs: str = "") -> Path:
    path = folder / name
    path.write_text(SVG.format(attrs=attrs, body=body))
    return path


def spacings(points: np.ndarray, closed: bool) -> np.ndarray:
    ring = np.concatenate([points, points[:1]]) if closed else points
    return np.linalg.norm(np.diff(ring, axis=0), axis=1)


def distance_to_polyline(points: np.ndarray, line: np.ndarray) -> np.ndarray:
    """Each point's distance to the polyline `line` (its segments, exactly)."""
    a, b = line[:-1], line[1:]
    ab = b - a
    t = np.einsum("pij,ij->pi", points[:, None] - a, ab) / np.einsum("ij,ij->i", ab, ab)
    nearest = a + np.clip(t, 0, 1)[..., None] * ab
    return np.linalg.norm(points[:, None] - nearest, axis=2).min(axis=1)


# -- SVG -------------------------------------------------------------------------------------

CX, CY, R = 12.0, -3.0, 7.5
ARCS = (
    f"M {CX + R} {CY} A {R} {R} 0 0 1 {CX} {CY + R} A {R} {R} 0 0 1 {CX - R} {CY} "
    f"A {R} {R} 0 0 1 {CX} {CY - R} A {R} {R} 0 0 1 {CX + R} {CY} Z"
)


@pytest.mark.parametrize(
    "shape",
    [f'<path id="ring" d="{ARCS}"/>', f'<circle id="ring" cx="{CX}" cy="{CY}" r="{R}"/>'],
    ids=["four-arcs", "circle"],
)
@pytest.mark.parametrize("count", [400, 97])
def test_an_svg_circle_reads_back_on_its_radius_evenly_spaced_and_closed(
    tmp_path: Path, shape: str, count: int
) -> None:
    curve = read_curve(f"{svg_file(tmp_path, shape)}#ring", points=count)
    assert curve.closed and curve.points.shape == (count, 2)
    radius = np.linalg.norm(curve.points - [CX, -CY], axis=1)  # y flipped: the centre too
    np.testing.assert_allclose(radius, R, rtol=1e-6)
    steps = spacings(curve.points, closed=True)
    assert steps.max() / steps.min() - 1 < 1e-3
    np.testing.assert_allclose(steps, 2 * R * math.sin(math.pi / count), rtol=1e-4)  # chords


def test_transforms_of_the_element_and_its_parents_are_applied(tmp_path: Path) -> None:
    """The points equal the untransformed read's, put through the transforms by hand (in SVG's
    y-down frame); a similarity keeps arc-length spacing, so point for point."""
    d = "M 0 0 C 10 20 30 -10 40 5 L 35 -12 Q 20 -25 4 -6 Z"
    plain_file = svg_file(tmp_path, f'<path id="a" d="{d}"/>', "plain.svg")
    plain = read_curve(f"{plain_file}#a")
    moved = svg_file(
        tmp_path,
        '<g transform="translate(30,-5) rotate(25) scale(1.5)">'
        f'<path id="a" transform="translate(2,3)" d="{d}"/></g>',
        "moved.svg",
    )
    turn = math.radians(25)
    rotation = np.array([[math.cos(turn), -math.sin(turn)], [math.sin(turn), math.cos(turn)]])

    def by_hand(points: np.ndarray, scale: np.ndarray) -> np.ndarray:
        drawn = points * [1, -1]  # back to SVG's frame
        return ((drawn + np.array([2.0, 3.0])) * scale @ rotation.T + [30, -5]) * [1, -1]

    got = read_curve(f"{moved}#a")
    assert got.closed
    np.testing.assert_allclose(got.points, by_hand(plain.points, np.array([1.5, 1.5])), atol=1e-6)
    # A scale that is not uniform moves points along the curve: every point on it, then.
    skewed = svg_file(
        tmp_path,
        f'<g transform="rotate(-40) scale(2, 0.5)"><path id="a" d="{d}"/></g>',
        "skewed.svg",
    )
    truth = read_curve(f"{tmp_path / 'plain.svg'}#a", points=10_000).points
    turn = math.radians(-40)
    rotation = np.array([[math.cos(turn), -math.sin(turn)], [math.sin(turn), math.cos(turn)]])
    line = ((truth * [1, -1]) * [2, 0.5] @ rotation.T) * [1, -1]
    points = read_curve(f"{skewed}#a").points
    assert distance_to_polyline(points, np.concatenate([line, line[:1]])).max() < 1e-4


def test_svg_user_units_are_kept_whatever_the_viewport(tmp_path: Path) -> None:
    plain = read_curve(svg_file(tmp_path, f'<path d="{ARCS}"/>', "plain.svg"))
    sized = svg_file(
        tmp_path,
        f'<path d="{ARCS}"/>',
        "sized.svg",
        ' width="100mm" height="80mm" viewBox="-5 -20 40 30"',
    )
    np.testing.assert_allclose(read_curve(sized).points, plain.points, atol=1e-9)


def test_selection_by_id_the_first_shape_without_one_and_open_paths(tmp_path: Path) -> None:
    leg = np.array([[0.0, 0.0], [4.0, 3.0], [4.0, 9.0], [-2.0, 9.0]])
    drawing = svg_file(
        tmp_path,
        '<text id="title">a leg</text>'
        f'<path id="body" d="{ARCS}"/>'
        f'<polyline id="leg" points="{" ".join(f"{x},{y}" for x, y in leg)}"/>'
        '<path id="stroke" d="M 1 2 L 5 2 L 5 8"/>',
    )
    first = read_curve(drawing)
    assert first.closed and first.source == f"{drawing}#body"
    np.testing.assert_allclose(first.points, read_curve(f"{drawing}#body").points)
    got = read_curve(f"{drawing}#leg", points=50)
    assert not got.closed
    np.testing.assert_allclose(got.points, even_along(leg * [1, -1], 50, closed=False), atol=1e-9)
    stroke = read_curve(f"{drawing}#stroke", points=11)
    assert not stroke.closed
    np.testing.assert_allclose(stroke.points[[0, -1]], [[1, -2], [5, -8]], atol=1e-9)
    np.testing.assert_allclose(spacings(stroke.points, closed=False), 1.0, rtol=1e-9)


# -- DXF -------------------------------------------------------------------------------------

FRAME = np.array([[0.0, 0.0], [40.0, 0.0], [48.0, 22.0], [20.0, 35.0], [-6.0, 18.0]])
CONTROL = [(0.0, 0.0), (10.0, 25.0), (30.0, -10.0), (45.0, 15.0), (60.0, 5.0)]


def dxf_file(folder: Path) -> Path:
    doc = ezdxf.new()
    modelspace = doc.modelspace()
    for layer in ("FRAME", "CURVE", "ROUND", "OLD"):
        doc.layers.add(layer)
    modelspace.add_line((0, 0), (9, 9), dxfattribs={"layer": "FRAME"})  # not a curve
    modelspace.add_lwpolyline(FRAME.tolist(), close=True, dxfattribs={"layer": "FRAME"})
    modelspace.add_spline(CONTROL, dxfattribs={"layer": "CURVE"})
    # A circle of radius 5 about (1, 2) as two half-circle bulges (bulge 1 = 180 degrees).
    modelspace.add_lwpolyline(
        [(-4, 2, 0, 0, 1), (6, 2, 0, 0, 1)],
        format="xyseb",
        close=True,
        dxfattribs={"layer": "ROUND"},
    )
    modelspace.add_polyline2d(FRAME[:4].tolist(), dxfattribs={"layer": "OLD"})
    path = folder / "part.dxf"
    doc.saveas(path)
    return path


def test_dxf_entities_by_layer_against_even_along_and_ezdxf(tmp_path: Path) -> None:
    part = dxf_file(tmp_path)
    frame = read_curve(f"{part}#FRAME")
    assert frame.closed and frame.source == f"{part}#FRAME (LWPOLYLINE)"
    np.testing.assert_allclose(frame.points, even_along(FRAME, 400, closed=True), atol=1e-9)
    np.testing.assert_allclose(read_curve(part).points, frame.points)  # the first in modelspace
    assert read_curve(f"{part}#frame").source == frame.source  # DXF layer names ignore case
    old = read_curve(f"{part}#OLD", points=60)
    assert not old.closed
    np.testing.assert_allclose(old.points, even_along(FRAME[:4], 60, closed=False), atol=1e-9)

    spline = read_curve(f"{part}#CURVE")
    assert not spline.closed
    tool = ezdxf.readfile(part).modelspace().query("SPLINE")[0].construction_tool()
    dense = np.array([(v.x, v.y) for v in tool.points(np.linspace(0, tool.max_t, 200_001))])
    np.testing.assert_allclose(spline.points, even_along(dense, 400, closed=False), atol=1e-6)

    round_ = read_curve(f"{part}#ROUND")
    assert round_.closed
    np.testing.assert_allclose(np.linalg.norm(round_.points - [1, 2], axis=1), 5, rtol=1e-6)
    steps = spacings(round_.points, closed=True)
    assert steps.max() / steps.min() - 1 < 1e-3


# -- CSV and JSON ----------------------------------------------------------------------------

LINE = np.array([[0.0, 0.0], [3.0, 1.0], [3.5, 4.0], [1.0, 6.25], [-2.0, 5.0]])


def test_csv_and_json_round_trips(tmp_path: Path) -> None:
    expected_open = even_along(LINE, 40, closed=False)
    expected_closed = even_along(LINE, 40, closed=True)
    csv = tmp_path / "pts.csv"
    csv.write_text("x, y\n" + "\n".join(f"{x!r},{y!r}" for x, y in LINE.tolist()) + "\n\n")
    got = read_curve(csv, points=40)
    assert not got.closed and got.source == str(csv)
    np.testing.assert_allclose(got.points, expected_open, atol=1e-12)
    ring = tmp_path / "ring.csv"  # no header; the last point repeats the first: closed
    ring.write_text("\n".join(f"{x},{y}" for x, y in [*LINE, LINE[0]]))
    got = read_curve(ring, points=40)
    assert got.closed
    np.testing.assert_allclose(got.points, expected_closed, atol=1e-12)
    for name, value, closed in (
        ("list.json", LINE.tolist(), False),
        ("object.json", {"points": LINE.tolist()}, False),
        ("said.json", {"points": LINE.tolist(), "closed": True}, True),
        ("ring.json", [*LINE.tolist(), LINE[0].tolist()], True),
    ):
        path = tmp_path / name
        path.write_text(json.dumps(value))
        got = read_curve(path, points=40)
        assert got.closed is closed, name
        np.testing.assert_allclose(got.points, expected_closed if closed else expected_open)


# -- bad files -------------------------------------------------------------------------------


def bad_files(folder: Path) -> list[tuple[str, str]]:
    """(target, the whole message) for each kind of bad file."""
    svg_file(folder, f'<path id="body" d="{ARCS}"/><path id="leg" d="M 0 0 L 1 1"/>')
    svg_file(folder, "<text>no shapes</text>", "empty.svg")
    svg_file(folder, '<path id="two" d="M 0 0 L 1 1 M 5 5 L 6 7"/>', "two.svg")
    (folder / "broken.svg").write_text("<svg><path d='M 0 0'")
    doc = ezdxf.new()
    doc.layers.add("FRAME")
    doc.modelspace().add_lwpolyline(FRAME.tolist(), dxfattribs={"layer": "FRAME"})
    doc.saveas(folder / "part.dxf")
    (folder / "broken.dxf").write_text("not a drawing\n")
    (folder / "pts.csv").write_text("x,y\n0,0\n1,1\n1.0;2.0\n")
    (folder / "one.csv").write_text("1,2\n1,2\n1,2\n")
    (folder / "one.json").write_text("[[1, 2]]")
    (folder / "broken.json").write_text("[[1, 2], [3,")
    (folder / "words.json").write_text('{"points": "a circle"}')
    (folder / "curve.txt").write_text("0,0\n1,1\n")
    with open(folder / "huge.csv", "wb") as stream:  # sparse: no disk written
        stream.truncate(MAX_CURVE_FILE_BYTES + 1)
    f = str(folder)
    return [
        (f"{f}/drawing.svg#wing", f"{f}/drawing.svg: no element with id 'wing' (ids: body, leg)"),
        (
            f"{f}/empty.svg",
            f"{f}/empty.svg: no path, polyline, polygon, rect, circle, ellipse or line in it",
        ),
        (f"{f}/two.svg", f"{f}/two.svg: #two holds 2 separate curves (subpaths): one is read"),
        (
            f"{f}/broken.svg",
            f"{f}/broken.svg: not a readable SVG (ParseError: unclosed token: line 1, column 5)",
        ),
        (
            f"{f}/part.dxf#CURVE",
            f"{f}/part.dxf: no LWPOLYLINE, POLYLINE or SPLINE on layer 'CURVE' "
            "(layers: 0, Defpoints, FRAME)",
        ),
        (f"{f}/broken.dxf", f"{f}/broken.dxf: not a readable DXF ("),
        (f"{f}/pts.csv", f"{f}/pts.csv line 4: expected two numbers, got '1.0;2.0'"),
        (f"{f}/pts.csv#a", f"{f}/pts.csv: a CSV file holds one curve, there is no #a"),
        (f"{f}/one.csv", f"{f}/one.csv: a single point, there is no curve"),
        (f"{f}/one.json", f"{f}/one.json: a single point, there is no curve"),
        (f"{f}/broken.json", f"{f}/broken.json: not valid JSON ("),
        (
            f"{f}/words.json",
            f'{f}/words.json: expected [[x, y], ...] or {{"points": [[x, y], ...]}}',
        ),
        (
            f"{f}/curve.txt",
            f"{f}/curve.txt: unknown extension '.txt' (read: .csv, .dxf, .json, .svg)",
        ),
        (f"{f}/missing.svg", f"{f}/missing.svg: No such file or directory"),
        (
            f"{f}/huge.csv",
            f"{f}/huge.csv: larger than {MAX_CURVE_FILE_BYTES:,} bytes, "
            "the most a curve file may be",
        ),
    ]


def test_a_bad_file_is_a_value_error_naming_the_file_and_the_problem(tmp_path: Path) -> None:
    for target, message in bad_files(tmp_path):
        with pytest.raises(ValueError) as caught:
            read_curve(target)
        said = str(caught.value)
        assert "\n" not in said
        assert said == message if not message.endswith("(") else said.startswith(message), said
    with pytest.raises(ValueError, match=r"^points must be"):
        read_curve(f"{tmp_path}/drawing.svg", points=2)


def test_the_cli_says_what_is_wrong_in_one_line(tmp_path: Path) -> None:
    """Read before any dataset is opened: the root need not exist."""
    cases = bad_files(tmp_path)
    for command, (target, message) in zip(
        ("retrieve", "synthesize", "retrieve"), (cases[0], cases[4], cases[6]), strict=True
    ):
        done = links(command, str(tmp_path / "no-data"), "--curve", target)
        assert done.returncode == 2
        assert done.stderr == f"links {command}: error: {message}\n"
    both = links("retrieve", str(tmp_path), "--curve", "a.svg", "--points", "a.json")
    assert both.returncode == 2 and "not allowed with argument" in both.stderr


# -- the CLI on a dataset --------------------------------------------------------------------


def test_links_retrieve_and_synthesize_take_a_curve_as_they_take_its_points(
    dataset: str, tmp_path: Path
) -> None:
    """`--curve` answers as `--points` given the same points; an open curve is synthesized as
    `--partial` is."""
    angle = np.linspace(0, 2 * np.pi, 9)[:-1]
    corners = np.column_stack([3 * np.cos(angle), 2 * np.sin(angle) + 0.4 * np.cos(2 * angle)])
    outline = " ".join(f"{x:.6f},{y:.6f}" for x, y in corners)
    drawing = svg_file(
        tmp_path,
        f'<polygon id="bean" points="{outline}"/><polyline id="stroke" points="{outline}"/>',
    )
    for shape in ("bean", "stroke"):
        curve = read_curve(f"{drawing}#{shape}")
        points = tmp_path / f"{shape}.json"
        points.write_text(json.dumps(curve.points.tolist()))
        as_curve = links("retrieve", dataset, "--curve", f"{drawing}#{shape}", "-k", "2", "--json")
        as_points = links("retrieve", dataset, "--points", str(points), "-k", "2", "--json")
        assert as_curve.returncode == 0, as_curve.stderr
        assert as_points.returncode == 0, as_points.stderr
        results, expected = (json.loads(done.stdout)["results"] for done in (as_curve, as_points))
        ranked = [
            [(r["path_id"], r["joint"], r["chamfer"]) for r in rs] for rs in (results, expected)
        ]
        assert len(results) == 2 and ranked[0] == ranked[1]
        assert results == expected
    fixed = ["-k", "1", "--iterations", "20", "--seed", "3", "--json"]
    stroke = links("synthesize", dataset, "--curve", f"{drawing}#stroke", *fixed)
    partial = links(
        "synthesize", dataset, "--points", str(tmp_path / "stroke.json"), "--partial", *fixed
    )
    whole = links("synthesize", dataset, "--points", str(tmp_path / "stroke.json"), *fixed)
    for done in (stroke, partial, whole):
        assert done.returncode == 0, done.stderr
    answer = json.loads(stroke.stdout)["results"]
    assert len(answer) == 1 and answer == json.loads(partial.stdout)["results"]
    assert answer != json.loads(whole.stdout)["results"]
