"""A mechanism's fabrication drawing (`engine.fabrication.drawings.Fabrication`) as SVG and DXF
text.

Both hold the same parts in millimetres, y up (joint 0 at the origin, or the drawing's own frame:
`engine.fabrication.drawings.FRAMES`), one layer (an SVG group) per kind of part: `LAYERS`. The SVG
is written here as text, its user unit one millimetre; the DXF is built with ezdxf (imported when
one is written) as an R2010 file that declares millimetres (`$INSUNITS` 4,
`$MEASUREMENT` metric). The traced path is a closed polygon (SVG, id `PATH_ID`) or a closed
LWPOLYLINE (DXF, layer PATH), so `read_curve` reads it back from either file
(`drawing.svg#traced-path`, `drawing.dxf#PATH`).
"""

from __future__ import annotations

import io

from links_ray.engine.fabrication.drawings import HOLE_MM, TEXT_MM, Fabrication
from links_ray.engine.node_kinds import FIXED

__all__ = ["DXF_VERSION", "LAYERS", "PATH_ID", "dxf_drawing", "svg_drawing"]

#: Layers of the DXF (and ids of the SVG's groups), each with an AutoCAD colour number.
LAYERS = {"CRANK": 1, "LINKS": 7, "GROUND": 5, "JOINTS": 3, "LABELS": 8, "PATH": 6}
#: Width of a link's centre line in the SVG, in millimetres.
STROKE_MM = 0.5
#: The SVG id of the traced path's polygon (inside the group PATH).
PATH_ID = "traced-path"
#: The DXF version written: one that holds the drawing's unit (R12 cannot), read by current
#: CAD and laser-cutter programs.
DXF_VERSION = "R2010"


def svg_drawing(drawing: Fabrication) -> str:
    """An SVG drawing at 1:1: one user unit is one millimetre, y up."""
    min_x, min_y, max_x, max_y = drawing.bounds()
    width, height = max_x - min_x, max_y - min_y
    # Drawn in mm with y up inside a group that flips y; labels outside it, so they read.
    parts = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{_num(width)}mm" '
        f'height="{_num(height)}mm" viewBox="{_num(min_x)} {_num(-max_y)} {_num(width)} '
        f'{_num(height)}">',
        f"<title>links-ray mechanism: {len(drawing.node_types)} joints, crank "
        f"{drawing.crank_mm:g} mm</title>",
        f"<desc>1 user unit = 1 mm; y up; {_origin_words(drawing)}</desc>",
        '<g id="drawing" transform="scale(1 -1)" fill="none" stroke="#000000" '
        f'stroke-width="{_num(STROKE_MM / 2)}" stroke-linecap="round">',
    ]
    if drawing.path_mm is not None:
        points = " ".join(f"{_num(x)},{_num(y)}" for x, y in drawing.path_mm)
        parts += [
            '<g id="PATH" stroke="#c2255c">',
            f'<polygon id="{PATH_ID}" class="path" data-joint="{drawing.path_joint}" '
            f'points="{points}"/>',
            "</g>",
        ]
    for layer, kinds in (("LINKS", ("ground", "coupler")), ("CRANK", ("crank",))):
        parts.append(f'<g id="{layer}" stroke-width="{_num(STROKE_MM)}">')
        for link in drawing.links:
            if link.kind in kinds:
                (x1, y1), (x2, y2) = drawing.joints_mm[list(link.joints)]
                parts.append(
                    f'<line class="link {link.kind}" data-joints="{link.joints[0]} '
                    f'{link.joints[1]}" data-length-mm="{_num(link.length_mm)}" '
                    f'x1="{_num(x1)}" y1="{_num(y1)}" x2="{_num(x2)}" y2="{_num(y2)}"/>'
                )
        parts.append("</g>")
    for layer, fixed in (("GROUND", True), ("JOINTS", False)):
        parts.append(f'<g id="{layer}">')
        for j, (x, y) in enumerate(drawing.joints_mm):
            if (drawing.node_types[j] == FIXED) == fixed:
                parts.append(
                    f'<circle class="{"pivot" if fixed else "joint"}" data-joint="{j}" '
                    f'cx="{_num(x)}" cy="{_num(y)}" r="{_num(HOLE_MM / 2)}"/>'
                )
        parts.append("</g>")
    parts += ["</g>", f'<g id="LABELS" font-family="sans-serif" font-size="{_num(TEXT_MM)}">']
    for j, (x, y) in drawing.label_positions():
        parts.append(f'<text data-joint="{j}" x="{_num(x)}" y="{_num(-y)}">J{j}</text>')
    parts += ["</g>", "</svg>"]
    return "\n".join(parts) + "\n"


def dxf_drawing(drawing: Fabrication) -> str:
    """An ASCII DXF (DXF_VERSION) in millimetres: a LINE per link, a CIRCLE per hole, a TEXT
    label per joint and the path as a closed LWPOLYLINE, each on its layer of LAYERS.

    The text is ASCII, so its bytes are the same in UTF-8 (which R2007 and later files use)."""
    import ezdxf
    from ezdxf import units

    doc = ezdxf.new(DXF_VERSION, units=units.MM)  # $INSUNITS 4 and $MEASUREMENT 1 (metric)
    for name, colour in LAYERS.items():
        doc.layers.add(name, color=colour)
    space = doc.modelspace()
    for link in drawing.links:
        (x1, y1), (x2, y2) = drawing.joints_mm[list(link.joints)]
        layer = "CRANK" if link.kind == "crank" else "LINKS"
        space.add_line((x1, y1), (x2, y2), dxfattribs={"layer": layer})
    for j, (x, y) in enumerate(drawing.joints_mm):
        layer = "GROUND" if drawing.node_types[j] == FIXED else "JOINTS"
        space.add_circle((x, y), HOLE_MM / 2, dxfattribs={"layer": layer})
    for j, (x, y) in drawing.label_positions():
        space.add_text(f"J{j}", height=TEXT_MM, dxfattribs={"layer": "LABELS"}).set_placement(
            (x, y)
        )
    if drawing.path_mm is not None:
        space.add_lwpolyline(
            drawing.path_mm.tolist(), format="xy", close=True, dxfattribs={"layer": "PATH"}
        )
    # The extents (margin included) and the first view: the whole drawing in sight.
    min_x, min_y, max_x, max_y = drawing.bounds()
    space.dxf.extmin, space.dxf.extmax = (min_x, min_y, 0.0), (max_x, max_y, 0.0)
    doc.set_modelspace_vport(max_y - min_y, center=((min_x + max_x) / 2, (min_y + max_y) / 2))
    stream = io.StringIO()
    doc.write(stream)
    return stream.getvalue()


def _origin_words(drawing: Fabrication) -> str:
    """Where the drawing's origin is, for the SVG's description."""
    if drawing.frame == "drawing":
        return "the drawing's own frame, a unit a millimetre"
    return "joint 0, the crank's pivot, at the origin"


def _num(value: float) -> str:
    """A coordinate in mm for the SVG: to the nanometre, shortest form, no negative zero."""
    rounded = round(float(value), 9)
    return repr(rounded + 0.0)  # + 0.0 turns -0.0 into 0.0
