"""Fabrication drawings (engine/fabrication/drawings.py, written by interop/drawings.py): SVG, DXF
and the link table in millimetres.

The files are read back independently of the writer (the SVG with `xml.etree`, the DXF with
ezdxf, the traced path of both with `read_curve`) and checked against the mechanism's own
geometry, scaled here from the raw positions so that the crank is exactly the length asked
for, and against a re-simulation for the traced path.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import links_ray
from links_ray.engine.fabrication.drawings import HOLE_MM, TEXT_MM, fabrication
from links_ray.engine.inputs import InvalidMechanismError
from links_ray.engine.kinematics.mechanism import LockingError
from links_ray.engine.kinematics.paths import even_along
from links_ray.interop.curve_files import read_curve
from links_ray.interop.drawings import LAYERS, PATH_ID, dxf_drawing, svg_drawing
from tests.support.drawings import dxf_parts, read_dxf
from tests.support.serving import FOUR_BAR, LOCKING_FOUR_BAR

SVG = "{http://www.w3.org/2000/svg}"
TOL_MM = 2e-9  # the SVG holds coordinates to the nanometre, the DXF as they are


def random_mechanism(seed: int) -> dict[str, Any]:
    adjacency, node_types = links_ray.random_topology(seed)
    positions = links_ray.sample_positions(adjacency, node_types, count=1, seed=seed)[0]
    return {"adjacency": adjacency, "node_types": node_types, "positions": positions}


MECHANISMS = [FOUR_BAR, random_mechanism(3), random_mechanism(11)]


def expected(mech: dict[str, Any], crank_mm: float) -> tuple[np.ndarray, dict, list[int]]:
    """The truth, from the raw arrays: joints in mm from joint 0, link lengths, fixed joints."""
    pos = np.asarray(mech["positions"], dtype=float)
    adjacency = np.asarray(mech["adjacency"])
    scale = crank_mm / math.dist(pos[0], pos[1])
    joints = (pos - pos[0]) * scale
    lengths = {
        (i, j): math.dist(pos[i], pos[j]) * scale
        for i in range(len(pos))
        for j in range(i + 1, len(pos))
        if adjacency[i, j]
    }
    fixed = [j for j, t in enumerate(mech["node_types"]) if t == 0]
    return joints, lengths, fixed


# -- SVG ----------------------------------------------------------------------------------------


def floats(element: ET.Element, *names: str) -> list[float]:
    return [float(element.get(name)) for name in names]


@pytest.mark.parametrize("crank_mm", [20.0, 7.5, 1234.0])
@pytest.mark.parametrize("which", range(len(MECHANISMS)))
def test_svg_is_at_scale_in_millimetres(which: int, crank_mm: float) -> None:
    mech = MECHANISMS[which]
    joints, lengths, fixed = expected(mech, crank_mm)
    root = ET.fromstring(svg_drawing(fabrication(**mech, crank_mm=crank_mm)))

    # One user unit is one millimetre: the size in mm equals the viewBox's.
    _, _, box_w, box_h = map(float, root.get("viewBox").split())
    assert root.get("width") == f"{box_w!r}mm" and root.get("height") == f"{box_h!r}mm"
    drawing = root.find(f"{SVG}g[@id='drawing']")
    assert drawing.get("transform") == "scale(1 -1)"  # y up, as the mechanism's

    lines = drawing.findall(f".//{SVG}line")
    assert len(lines) == len(lengths)
    seen = set()
    for line in lines:
        i, j = map(int, line.get("data-joints").split())
        x1, y1, x2, y2 = floats(line, "x1", "y1", "x2", "y2")
        np.testing.assert_allclose([x1, y1], joints[i], atol=TOL_MM, rtol=0)
        np.testing.assert_allclose([x2, y2], joints[j], atol=TOL_MM, rtol=0)
        assert math.hypot(x2 - x1, y2 - y1) == pytest.approx(lengths[i, j], abs=3 * TOL_MM)
        assert float(line.get("data-length-mm")) == pytest.approx(lengths[i, j], abs=TOL_MM)
        seen.add((i, j))
    assert seen == set(lengths)
    crank = drawing.find(f"{SVG}g[@id='CRANK']/{SVG}line")
    x1, y1, x2, y2 = floats(crank, "x1", "y1", "x2", "y2")
    assert math.hypot(x2 - x1, y2 - y1) == pytest.approx(crank_mm, abs=3 * TOL_MM)

    pivots = drawing.findall(f"{SVG}g[@id='GROUND']/{SVG}circle")
    assert [int(c.get("data-joint")) for c in pivots] == fixed
    for circle in pivots:
        cx, cy, r = floats(circle, "cx", "cy", "r")
        np.testing.assert_allclose([cx, cy], joints[int(circle.get("data-joint"))], atol=TOL_MM)
        assert r == HOLE_MM / 2
    assert floats(pivots[0], "cx", "cy") == [0.0, 0.0]  # the crank's pivot at the origin
    moving = drawing.findall(f"{SVG}g[@id='JOINTS']/{SVG}circle")
    assert len(pivots) + len(moving) == len(joints)

    # Everything drawn lies inside the viewBox (y flipped by the group).
    min_x, min_y = map(float, root.get("viewBox").split()[:2])
    assert np.all(joints[:, 0] - HOLE_MM / 2 >= min_x)
    assert np.all(joints[:, 0] + HOLE_MM / 2 <= min_x + box_w)
    assert np.all(-joints[:, 1] - HOLE_MM / 2 >= min_y)
    assert np.all(-joints[:, 1] + HOLE_MM / 2 <= min_y + box_h)
    labels = root.findall(f"{SVG}g[@id='LABELS']/{SVG}text")
    assert [t.text for t in labels] == [f"J{j}" for j in range(len(joints))]


@pytest.mark.parametrize("which", range(len(MECHANISMS)))
def test_svg_path_is_the_simulated_path(which: int) -> None:
    mech = MECHANISMS[which]
    joint = len(mech["node_types"]) - 1
    crank_mm = 25.0
    root = ET.fromstring(svg_drawing(fabrication(**mech, crank_mm=crank_mm, path_joint=joint)))
    polygon = root.find(f".//{SVG}g[@id='PATH']/{SVG}polygon")
    assert int(polygon.get("data-joint")) == joint
    points = np.array([p.split(",") for p in polygon.get("points").split()], dtype=float)
    pos = np.asarray(mech["positions"], dtype=float)
    truth = links_ray.simulate(**mech)[joint]
    scale = crank_mm / math.dist(pos[0], pos[1])
    np.testing.assert_allclose(points, (truth - pos[0]) * scale, atol=TOL_MM, rtol=0)
    # The viewBox holds the path too.
    min_x, min_y, w, h = map(float, root.get("viewBox").split())
    assert points[:, 0].min() >= min_x and points[:, 0].max() <= min_x + w
    assert -points[:, 1].max() >= min_y and -points[:, 1].min() <= min_y + h


# -- DXF ----------------------------------------------------------------------------------------


def traced(mech: dict[str, Any], joint: int, crank_mm: float) -> np.ndarray:
    """The path `joint` traces, re-simulated, in mm from joint 0 (y up)."""
    pos = np.asarray(mech["positions"], dtype=float)
    scale = crank_mm / math.dist(pos[0], pos[1])
    return (links_ray.simulate(**mech)[joint] - pos[0]) * scale


@pytest.mark.parametrize("with_path", [True, False])
@pytest.mark.parametrize("which", range(len(MECHANISMS)))
def test_dxf_declares_millimetres_and_passes_the_audit(which: int, with_path: bool) -> None:
    mech = MECHANISMS[which]
    joint = len(mech["node_types"]) - 1 if with_path else None
    text = dxf_drawing(fabrication(**mech, crank_mm=20.0, path_joint=joint))
    assert text.isascii()  # the same bytes in any encoding a reader assumes
    doc = read_dxf(text)  # nothing to recover
    audit = doc.audit()
    assert (audit.errors, audit.fixes) == ([], [])
    assert doc.dxfversion == "AC1024"  # R2010: R2000 and later hold $INSUNITS, R12 does not
    assert doc.header["$INSUNITS"] == 4  # millimetres
    assert doc.header["$MEASUREMENT"] == 1  # metric

    colours = {layer.dxf.name: layer.dxf.color for layer in doc.layers}
    assert {name: colours.get(name) for name in LAYERS} == LAYERS
    used = {entity.dxf.layer for entity in doc.modelspace()}
    assert used == set(LAYERS) - ({"PATH"} if joint is None else set())


@pytest.mark.parametrize("crank_mm", [20.0, 3.0])
@pytest.mark.parametrize("which", range(len(MECHANISMS)))
def test_dxf_lines_are_the_links_in_millimetres(which: int, crank_mm: float) -> None:
    mech = MECHANISMS[which]
    joints, lengths, fixed = expected(mech, crank_mm)
    joint = len(joints) - 1
    doc = read_dxf(dxf_drawing(fabrication(**mech, crank_mm=crank_mm, path_joint=joint)))
    parts = dxf_parts(doc)
    assert {kind for kind, _, _ in parts} == {"LINE", "CIRCLE", "TEXT", "LWPOLYLINE"}

    lines = [(layer, drawn) for kind, layer, drawn in parts if kind == "LINE"]
    assert len(lines) == len(lengths)
    found = []
    for layer, (x1, y1, x2, y2) in lines:
        found.append(math.hypot(x2 - x1, y2 - y1))
        ends = [int(np.argmin(np.hypot(*(joints - p).T))) for p in ([x1, y1], [x2, y2])]
        i, j = sorted(ends)
        assert found[-1] == pytest.approx(lengths[i, j], abs=3 * TOL_MM)
        assert layer == ("CRANK" if (i, j) == (0, 1) else "LINKS")
    assert sorted(found) == pytest.approx(sorted(lengths.values()), abs=3 * TOL_MM)

    circles = [(layer, drawn) for kind, layer, drawn in parts if kind == "CIRCLE"]
    centres = np.array([[x, y] for layer, (x, y, _) in circles if layer == "GROUND"])
    np.testing.assert_allclose(centres, joints[fixed], atol=TOL_MM, rtol=0)
    moving = np.array([[x, y] for layer, (x, y, _) in circles if layer == "JOINTS"])
    moved = [j for j in range(len(joints)) if j not in fixed]
    np.testing.assert_allclose(moving, joints[moved], atol=TOL_MM, rtol=0)
    assert all(r == HOLE_MM / 2 for _, (_, _, r) in circles)
    texts = [(layer, drawn) for kind, layer, drawn in parts if kind == "TEXT"]
    assert [(layer, text, height) for layer, (text, _, _, height) in texts] == [
        ("LABELS", f"J{j}", TEXT_MM) for j in range(len(joints))
    ]

    # The path: one closed LWPOLYLINE, the re-simulated path vertex for vertex.
    [(layer, (closed, vertices))] = [(la, d) for kind, la, d in parts if kind == "LWPOLYLINE"]
    assert layer == "PATH" and closed
    points = np.array(vertices)
    np.testing.assert_allclose(points, traced(mech, joint, crank_mm), atol=TOL_MM, rtol=0)
    # The extents hold the path and every hole.
    low, high = (np.asarray(doc.header[name])[:2] for name in ("$EXTMIN", "$EXTMAX"))
    assert np.all(low <= points.min(axis=0)) and np.all(points.max(axis=0) <= high)
    assert np.all(low <= joints.min(axis=0) - HOLE_MM / 2)
    assert np.all(joints.max(axis=0) + HOLE_MM / 2 <= high)


# -- the traced path, read back ---------------------------------------------------------------


@pytest.mark.parametrize("which", range(len(MECHANISMS)))
def test_traced_path_reads_back_from_svg_and_dxf(which: int, tmp_path: Path) -> None:
    """`read_curve` gives the path in the frame it was drawn in: mm, joint 0 at the origin, y
    up. (The SVG draws it inside a group that flips y; read_curve applies that transform and
    negates SVG's y-down, which brings it back.) It samples a curve evenly by arc length, so the
    truth is the re-simulated path sampled so."""
    mech = MECHANISMS[which]
    joint, crank_mm, count = len(mech["node_types"]) - 1, 25.0, 400
    drawing = fabrication(**mech, crank_mm=crank_mm, path_joint=joint)
    (tmp_path / "m.dxf").write_text(dxf_drawing(drawing), encoding="utf-8")
    (tmp_path / "m.svg").write_text(svg_drawing(drawing), encoding="utf-8")
    truth = even_along(traced(mech, joint, crank_mm), count, closed=True)
    # The DXF holds the path's coordinates as they are; the SVG to the nanometre.
    for target, tolerance in [
        ("m.dxf#PATH", 1e-9),
        ("m.dxf", 1e-9),  # the only polyline: read without naming it
        (f"m.svg#{PATH_ID}", 1e-6),
        ("m.svg", 1e-6),  # the first shape
    ]:
        curve = read_curve(tmp_path / target, points=count)
        assert curve.closed, target
        np.testing.assert_allclose(curve.points, truth, atol=tolerance, rtol=0, err_msg=target)


# -- the table --------------------------------------------------------------------------------


def test_table_of_a_four_bar_in_closed_form() -> None:
    # Crank 0.05 long made 20 mm: 400 mm per unit.
    table = fabrication(**FOUR_BAR, crank_mm=20).table()
    assert table["mm_per_unit"] == pytest.approx(400)
    assert [(tuple(link["joints"]), link["kind"]) for link in table["links"]] == [
        ((0, 1), "crank"),
        ((1, 3), "coupler"),
        ((2, 3), "ground"),
    ]
    lengths = [link["length_mm"] for link in table["links"]]
    assert lengths == pytest.approx([20, 400 * math.hypot(0.05, 0.2), 400 * math.hypot(0.2, 0.2)])
    assert table["ground_pivots"] == [
        {"joint": 0, "x_mm": 0.0, "y_mm": 0.0},
        {"joint": 2, "x_mm": pytest.approx(120.0), "y_mm": 0.0},
    ]
    text = fabrication(**FOUR_BAR, crank_mm=20).table_text()
    assert "crank 20 mm" in text
    rows = [line.split() for line in text.splitlines()]
    assert ["3", "2", "-", "3", f"{400 * math.hypot(0.2, 0.2):.3f}", "ground"] in rows
    assert ["2", "120.000", "0.000"] in rows


def test_the_drawings_own_frame_keeps_the_positions_as_millimetres() -> None:
    """crank_mm=None: every position as it is, a unit a millimetre, joint 0 where it lies; the
    path in the same frame; the SVG and the table say so."""
    mech = MECHANISMS[1]
    pos = np.asarray(mech["positions"]) * 300 + [12.5, -40]
    joint = int(np.flatnonzero(np.asarray(mech["node_types"]) != 0)[-1])
    drawing = fabrication(**{**mech, "positions": pos}, crank_mm=None, path_joint=joint)
    assert (drawing.frame, drawing.scale) == ("drawing", 1.0)
    np.testing.assert_array_equal(drawing.joints_mm, pos)
    assert drawing.crank_mm == pytest.approx(math.dist(pos[0], pos[1]))
    truth = links_ray.simulate(mech["adjacency"], mech["node_types"], pos)[joint]
    np.testing.assert_allclose(drawing.path_mm, truth, atol=1e-9)
    assert "the drawing's own frame" in ET.fromstring(svg_drawing(drawing)).find(f"{SVG}desc").text
    assert "positions in the drawing's own frame" in drawing.table_text().splitlines()[0]
    assert drawing.table()["frame"] == "drawing"
    assert fabrication(**mech).table()["frame"] == "crank"
    far = {**FOUR_BAR, "positions": np.asarray(FOUR_BAR["positions"]) * 1e7}
    with pytest.raises(ValueError, match="read as millimetres; choose a crank_mm"):
        fabrication(**far, crank_mm=None)


# -- bad input ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("crank_mm", "message"),
    [
        (0, "crank_mm must be more than 0"),
        (-5.0, "crank_mm must be more than 0"),
        (math.nan, "crank_mm must be more than 0"),
        (math.inf, "crank_mm must be more than 0"),
        (2e5, "at most 100000 mm"),
        (True, "crank_mm must be a number"),
        ("20", "crank_mm must be a number"),
    ],
)
def test_bad_crank_lengths_are_refused(crank_mm: object, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        fabrication(**FOUR_BAR, crank_mm=crank_mm)


def test_bad_mechanisms_and_paths_are_refused() -> None:
    no_crank = {**FOUR_BAR, "adjacency": np.array(FOUR_BAR["adjacency"]) * 0}
    with pytest.raises(InvalidMechanismError, match="no crank"):
        fabrication(**no_crank)
    with pytest.raises(InvalidMechanismError, match="positions must have shape"):
        fabrication(**{**FOUR_BAR, "positions": FOUR_BAR["positions"][:3]})
    with pytest.raises(InvalidMechanismError, match="path_joint 2 is fixed"):
        fabrication(**FOUR_BAR, path_joint=2)
    with pytest.raises(InvalidMechanismError, match="path_joint must be from 0 to 3"):
        fabrication(**FOUR_BAR, path_joint=4)
    # A locking mechanism draws, but has no path to trace.
    assert len(fabrication(**LOCKING_FOUR_BAR).links) == 3
    with pytest.raises(LockingError, match="locks at step"):
        fabrication(**LOCKING_FOUR_BAR, path_joint=3)
    # A crank a millionth of the other links: 20 mm would make a drawing kilometres wide.
    tiny = {**FOUR_BAR, "positions": [[0, 0], [1e-7, 0], [0.3, 0], [0.1, 0.2]]}
    with pytest.raises(ValueError, match="the drawing would span"):
        fabrication(**tiny, crank_mm=20)
