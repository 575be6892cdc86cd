"""Drawings to build a mechanism from: SVG, DXF and a table of link lengths, in millimetres.

A mechanism's positions have no unit; a drawing gets one from the crank: the user picks the
crank's length (joint 0 to joint 1) in millimetres, and every position is scaled by the same
factor, with joint 0 (the crank's pivot) at the origin and y up. The SVG's user unit is one
millimetre (its width and height are given in mm), and the DXF (ASCII, R12, written here)
declares millimetres (`$INSUNITS` 4). Both hold one layer per kind of part: the crank, the
other links (centre lines), the ground pivots and the moving joints (holes of `HOLE_MM`), the
joints' labels and, if asked for, the path a joint traces over a crank turn.

Pure numpy: no numba of its own (the traced path is simulated by `engine.solver`), no files.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from links_ray.engine.inputs import (
    DEFAULT_CRANK_MM,
    DEFAULT_STEPS,
    FIXED,
    MAX_DRAWING_MM,
    InvalidMechanismError,
    as_crank_mm,
    as_int,
    as_positions,
    as_steps,
    check_positions,
)
from links_ray.engine.mechanism import analyze_topology
from links_ray.engine.solver import simulate

#: Diameter of the hole drawn at each joint, in millimetres (an M3 pin's clearance).
HOLE_MM = 3.0
#: Width of a link's centre line in the SVG, and the height of the labels, in millimetres.
STROKE_MM, TEXT_MM = 0.5, 2.5
#: White space around the drawing, in millimetres: room for a hole and a label at the edge.
MARGIN_MM = HOLE_MM + 2 * TEXT_MM
#: Layers of the DXF (and ids of the SVG's groups), each with an AutoCAD colour number.
LAYERS = {"CRANK": 1, "LINKS": 7, "GROUND": 5, "JOINTS": 3, "LABELS": 8, "PATH": 6}


@dataclass(frozen=True)
class Link:
    """One link (a bar between two joints): its joints (i < j), length in mm and kind:
    "crank" (joints 0 and 1), "ground" (to a fixed joint) or "coupler"."""

    joints: tuple[int, int]
    length_mm: float
    kind: str


@dataclass(frozen=True, eq=False)
class Fabrication:
    """A mechanism in millimetres: joint 0 at the origin, y up, the crank `crank_mm` long.

    `scale` is the millimetres per unit of the mechanism's positions; `joints_mm` (n, 2) the
    joints' initial positions in mm; `path_mm` (steps, 2) the path joint `path_joint` traces
    over a crank turn, in mm, or None.
    """

    crank_mm: float
    scale: float
    node_types: np.ndarray
    joints_mm: np.ndarray
    links: tuple[Link, ...]
    path_joint: int | None = None
    path_mm: np.ndarray | None = None

    @property
    def ground_pivots(self) -> list[tuple[int, float, float]]:
        """(joint, x mm, y mm) of each fixed joint, in joint order."""
        fixed = np.flatnonzero(self.node_types == FIXED)
        return [(int(j), float(self.joints_mm[j, 0]), float(self.joints_mm[j, 1])) for j in fixed]

    def bounds(self) -> tuple[float, float, float, float]:
        """(min x, min y, max x, max y) in mm of the joints and the path, margin included."""
        points = (
            self.joints_mm if self.path_mm is None else np.vstack([self.joints_mm, self.path_mm])
        )
        low, high = points.min(axis=0) - MARGIN_MM, points.max(axis=0) + MARGIN_MM
        return float(low[0]), float(low[1]), float(high[0]), float(high[1])

    def table(self) -> dict[str, Any]:
        """The link lengths and ground pivots as a JSON-ready dict."""
        kinds = {FIXED: "fixed", 1: "simple", 2: "actuated"}
        return {
            "crank_mm": self.crank_mm,
            "mm_per_unit": self.scale,
            "links": [
                {"joints": list(link.joints), "length_mm": link.length_mm, "kind": link.kind}
                for link in self.links
            ],
            "ground_pivots": [{"joint": j, "x_mm": x, "y_mm": y} for j, x, y in self.ground_pivots],
            "joints": [
                {"joint": j, "type": kinds[int(t)], "x_mm": float(x), "y_mm": float(y)}
                for j, (t, (x, y)) in enumerate(zip(self.node_types, self.joints_mm, strict=True))
            ],
            "path_joint": self.path_joint,
        }

    def table_text(self) -> str:
        """The link lengths and ground pivots as a plain-text table."""
        n, count = len(self.node_types), len(self.links)
        lines = [
            f"{n} joints, {count} links; crank {self.crank_mm:g} mm "
            f"({self.scale:.6g} mm per unit); positions from joint 0, y up",
            "",
            f"{'link':>4}  {'joints':>7}  {'length mm':>12}  kind",
        ]
        for k, link in enumerate(self.links, 1):
            i, j = link.joints
            lines.append(f"{k:>4}  {f'{i} - {j}':>7}  {link.length_mm:>12.3f}  {link.kind}")
        lines += ["", f"{'ground pivot':>12}  {'x mm':>12}  {'y mm':>12}"]
        for j, x, y in self.ground_pivots:
            lines.append(f"{j:>12}  {x:>12.3f}  {y:>12.3f}")
        return "\n".join(lines) + "\n"

    def svg(self) -> str:
        """An SVG drawing at 1:1: one user unit is one millimetre, y up."""
        min_x, min_y, max_x, max_y = self.bounds()
        width, height = max_x - min_x, max_y - min_y
        # Drawn in mm with y up inside a group that flips y; labels outside it, so they read.
        parts = [
            '<?xml version="1.0" encoding="UTF-8"?>',
            f'<svg xmlns="http://www.w3.org/2000/svg" width="{_num(width)}mm" '
            f'height="{_num(height)}mm" viewBox="{_num(min_x)} {_num(-max_y)} {_num(width)} '
            f'{_num(height)}">',
            f"<title>links-ray mechanism: {len(self.node_types)} joints, crank "
            f"{self.crank_mm:g} mm</title>",
            "<desc>1 user unit = 1 mm; y up; joint 0, the crank's pivot, at the origin</desc>",
            '<g id="drawing" transform="scale(1 -1)" fill="none" stroke="#000000" '
            f'stroke-width="{_num(STROKE_MM / 2)}" stroke-linecap="round">',
        ]
        if self.path_mm is not None:
            points = " ".join(f"{_num(x)},{_num(y)}" for x, y in self.path_mm)
            parts += [
                '<g id="PATH" stroke="#c2255c">',
                f'<polygon class="path" data-joint="{self.path_joint}" points="{points}"/>',
                "</g>",
            ]
        for layer, kinds in (("LINKS", ("ground", "coupler")), ("CRANK", ("crank",))):
            parts.append(f'<g id="{layer}" stroke-width="{_num(STROKE_MM)}">')
            for link in self.links:
                if link.kind in kinds:
                    (x1, y1), (x2, y2) = self.joints_mm[list(link.joints)]
                    parts.append(
                        f'<line class="link {link.kind}" data-joints="{link.joints[0]} '
                        f'{link.joints[1]}" data-length-mm="{_num(link.length_mm)}" '
                        f'x1="{_num(x1)}" y1="{_num(y1)}" x2="{_num(x2)}" y2="{_num(y2)}"/>'
                    )
            parts.append("</g>")
        for layer, fixed in (("GROUND", True), ("JOINTS", False)):
            parts.append(f'<g id="{layer}">')
            for j, (x, y) in enumerate(self.joints_mm):
                if (self.node_types[j] == FIXED) == fixed:
                    parts.append(
                        f'<circle class="{"pivot" if fixed else "joint"}" data-joint="{j}" '
                        f'cx="{_num(x)}" cy="{_num(y)}" r="{_num(HOLE_MM / 2)}"/>'
                    )
            parts.append("</g>")
        parts += ["</g>", f'<g id="LABELS" font-family="sans-serif" font-size="{_num(TEXT_MM)}">']
        for j, (x, y) in self._label_positions():
            parts.append(f'<text data-joint="{j}" x="{_num(x)}" y="{_num(-y)}">J{j}</text>')
        parts += ["</g>", "</svg>"]
        return "\n".join(parts) + "\n"

    def dxf(self) -> str:
        """An ASCII DXF (R12) in millimetres: LINE links, CIRCLE holes, TEXT labels, and the
        path as a closed POLYLINE, a layer per kind."""
        min_x, min_y, max_x, max_y = self.bounds()
        out = _Dxf()
        out.section("HEADER")
        out.pairs((9, "$ACADVER"), (1, "AC1009"), (9, "$INSUNITS"), (70, 4))
        out.pairs((9, "$EXTMIN"), (10, min_x), (20, min_y), (30, 0.0))
        out.pairs((9, "$EXTMAX"), (10, max_x), (20, max_y), (30, 0.0))
        out.end()
        out.section("TABLES")
        out.pairs((0, "TABLE"), (2, "LTYPE"), (70, 1))
        out.pairs((0, "LTYPE"), (2, "CONTINUOUS"), (70, 0), (3, "Solid line"))
        out.pairs((72, 65), (73, 0), (40, 0.0), (0, "ENDTAB"))
        out.pairs((0, "TABLE"), (2, "LAYER"), (70, len(LAYERS)))
        for name, colour in LAYERS.items():
            out.pairs((0, "LAYER"), (2, name), (70, 0), (62, colour), (6, "CONTINUOUS"))
        out.pairs((0, "ENDTAB"))
        out.end()
        out.section("ENTITIES")
        for link in self.links:
            (x1, y1), (x2, y2) = self.joints_mm[list(link.joints)]
            layer = "CRANK" if link.kind == "crank" else "LINKS"
            out.pairs((0, "LINE"), (8, layer), (10, x1), (20, y1), (30, 0.0))
            out.pairs((11, x2), (21, y2), (31, 0.0))
        for j, (x, y) in enumerate(self.joints_mm):
            layer = "GROUND" if self.node_types[j] == FIXED else "JOINTS"
            out.pairs((0, "CIRCLE"), (8, layer), (10, x), (20, y), (30, 0.0), (40, HOLE_MM / 2))
        for j, (x, y) in self._label_positions():
            out.pairs((0, "TEXT"), (8, "LABELS"), (10, x), (20, y), (30, 0.0))
            out.pairs((40, TEXT_MM), (1, f"J{j}"))
        if self.path_mm is not None:
            # 66: vertices follow; 70 bit 1: closed.
            out.pairs((0, "POLYLINE"), (8, "PATH"), (66, 1), (70, 1))
            out.pairs((10, 0.0), (20, 0.0), (30, 0.0))
            for x, y in self.path_mm:
                out.pairs((0, "VERTEX"), (8, "PATH"), (10, x), (20, y), (30, 0.0))
            out.pairs((0, "SEQEND"), (8, "PATH"))
        out.end()
        out.pairs((0, "EOF"))
        return out.text()

    def _label_positions(self) -> list[tuple[int, tuple[float, float]]]:
        """Where each joint's label goes: up and right of its hole."""
        offset = HOLE_MM / 2 + 0.5
        return [
            (j, (float(x) + offset, float(y) + offset)) for j, (x, y) in enumerate(self.joints_mm)
        ]


class _Dxf:
    """DXF group codes and values, one per line each."""

    def __init__(self) -> None:
        self.lines: list[str] = []

    def pairs(self, *pairs: tuple[int, object]) -> None:
        for code, value in pairs:
            shown = _num(value) if isinstance(value, float | np.floating) else str(value)
            self.lines += [f"{code:>3}", shown]

    def section(self, name: str) -> None:
        self.pairs((0, "SECTION"), (2, name))

    def end(self) -> None:
        self.pairs((0, "ENDSEC"))

    def text(self) -> str:
        return "\n".join(self.lines) + "\n"


def _num(value: float) -> str:
    """A coordinate in mm for a file: to the nanometre, shortest form, no negative zero."""
    rounded = round(float(value), 9)
    return repr(rounded + 0.0)  # + 0.0 turns -0.0 into 0.0


def fabrication(
    adjacency: ArrayLike,
    node_types: ArrayLike,
    positions: ArrayLike,
    crank_mm: float = DEFAULT_CRANK_MM,
    path_joint: int | None = None,
    steps: int = DEFAULT_STEPS,
) -> Fabrication:
    """The mechanism in millimetres, its crank `crank_mm` long; with `path_joint`, also the
    path that joint traces over a crank turn of `steps` steps.

    Raises `ValueError` naming the problem: a malformed mechanism (`InvalidMechanismError`),
    a crank length that is not a positive number up to MAX_CRANK_MM, a drawing that would span
    more than MAX_DRAWING_MM, a path joint that does not exist or is fixed, or (only when a
    path is asked for) a mechanism that locks (`LockingError`).
    """
    topology = analyze_topology(adjacency, node_types)
    n = topology.n_joints
    pos = as_positions(positions, n)
    check_positions(topology.adjacency, pos)
    crank_mm = as_crank_mm(crank_mm)
    scale = crank_mm / float(np.hypot(*(pos[1] - pos[0])))
    joints_mm = (pos - pos[0]) * scale
    links = []
    fixed = topology.node_types == FIXED
    for i, j in zip(*np.nonzero(np.triu(topology.adjacency, 1)), strict=True):
        kind = "crank" if (i, j) == (0, 1) else "ground" if fixed[i] or fixed[j] else "coupler"
        length = float(np.hypot(*(joints_mm[j] - joints_mm[i])))
        links.append(Link((int(i), int(j)), length, kind))
    path = None
    if path_joint is not None:
        path_joint = as_int("path_joint", path_joint, 0, n - 1, InvalidMechanismError)
        if fixed[path_joint]:
            raise InvalidMechanismError(f"path_joint {path_joint} is fixed: it traces no path")
        trajectories = simulate(topology.adjacency, topology.node_types, pos, as_steps(steps))
        path = (trajectories[path_joint] - pos[0]) * scale
    drawn = joints_mm if path is None else np.vstack([joints_mm, path])
    extent = float(np.ptp(drawn, axis=0).max())
    if extent > MAX_DRAWING_MM:
        raise ValueError(
            f"the drawing would span {extent:.3g} mm, more than {MAX_DRAWING_MM:g} mm: the crank "
            f"is short beside the other links; choose a shorter crank_mm than {crank_mm:g}"
        )
    return Fabrication(
        crank_mm=crank_mm,
        scale=scale,
        node_types=topology.node_types.astype(np.int64),
        joints_mm=joints_mm,
        links=tuple(links),
        path_joint=path_joint,
        path_mm=path,
    )
