"""A mechanism in millimetres, the geometry of the drawings to build it from.

A mechanism's positions have no unit; a drawing gets one in one of two frames (`FRAMES`). In
the "crank" frame the user picks the crank's length (joint 0 to joint 1) in millimetres, and
every position is scaled by the same factor, with joint 0 (the crank's pivot) at the origin and
y up. In the "drawing" frame the positions are kept as they are, their unit read as a
millimetre: a synthesis result lies where its curve was drawn, in the drawing's units.
`Fabrication` holds what the drawings show: the links (centre lines), the ground pivots and
the moving joints (holes of `HOLE_MM`), where the joints' labels go, the drawing's bounds
and, if asked for, the path a joint traces over a crank turn; and the table of link lengths
and ground pivots.
`interop.drawings` writes it as SVG and DXF.

Pure numpy: no numba of its own (the traced path is simulated by `engine.kinematics.solver`), no
files.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from links_ray.engine.fabrication.limits import DEFAULT_CRANK_MM, MAX_DRAWING_MM, as_crank_mm
from links_ray.engine.inputs import (
    DEFAULT_STEPS,
    InvalidMechanismError,
    as_int,
    as_positions,
    as_steps,
    check_positions,
)
from links_ray.engine.kinematics.mechanism import analyze_topology
from links_ray.engine.kinematics.solver import simulate
from links_ray.engine.node_kinds import FIXED

#: Diameter of the hole drawn at each joint, in millimetres (an M3 pin's clearance).
HOLE_MM = 3.0
#: Height of the joints' labels, in millimetres.
TEXT_MM = 2.5
#: White space around the drawing, in millimetres: room for a hole and a label at the edge.
MARGIN_MM = HOLE_MM + 2 * TEXT_MM
#: Where a drawing's millimetres come from: "crank", the positions scaled so that the crank is
#: `crank_mm` long with joint 0 at the origin; "drawing", the positions as they are, a unit a
#: millimetre.
FRAMES = ("crank", "drawing")


@dataclass(frozen=True)
class Link:
    """One link (a bar between two joints): its joints (i < j), length in mm and kind:
    "crank" (joints 0 and 1), "ground" (to a fixed joint) or "coupler"."""

    joints: tuple[int, int]
    length_mm: float
    kind: str


@dataclass(frozen=True, eq=False)
class Fabrication:
    """A mechanism in millimetres, y up, in the frame `frame` (`FRAMES`): the crank `crank_mm`
    long with joint 0 at the origin, or the positions' own, the crank as long as it is there.

    `scale` is the millimetres per unit of the mechanism's positions (1 in the drawing's
    frame) and `origin` (2,) the point of the positions put at (0, 0): joint 0's, or (0, 0) in
    the drawing's frame; `joints_mm` (n, 2) the joints' initial positions in mm; `path_mm`
    (steps, 2) the path joint `path_joint` traces over a crank turn, in mm, or None.
    """

    crank_mm: float
    scale: float
    frame: str
    origin: np.ndarray
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
            "frame": self.frame,
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
            f"{n} joints, {count} links; crank {self.crank_mm:g} mm{self.frame_words}",
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

    @property
    def frame_words(self) -> str:
        """The frame, said after the crank's length in a table's first line."""
        if self.frame == "drawing":
            return "; positions in the drawing's own frame, a unit a millimetre, y up"
        return f" ({self.scale:.6g} mm per unit); positions from joint 0, y up"

    def label_positions(self) -> list[tuple[int, tuple[float, float]]]:
        """(joint, (x mm, y mm)) of each joint's label: up and right of its hole."""
        offset = HOLE_MM / 2 + 0.5
        return [
            (j, (float(x) + offset, float(y) + offset)) for j, (x, y) in enumerate(self.joints_mm)
        ]


def fabrication(
    adjacency: ArrayLike,
    node_types: ArrayLike,
    positions: ArrayLike,
    crank_mm: float | None = DEFAULT_CRANK_MM,
    path_joint: int | None = None,
    steps: int = DEFAULT_STEPS,
) -> Fabrication:
    """The mechanism in millimetres, its crank `crank_mm` long with joint 0 at the origin
    (None: the positions as they are, a unit a millimetre); with `path_joint`, also the path
    that joint traces over a crank turn of `steps` steps.

    Raises `ValueError` naming the problem: a malformed mechanism (`InvalidMechanismError`),
    a crank length that is not a positive number up to MAX_CRANK_MM, a drawing that would span
    more than MAX_DRAWING_MM, a path joint that does not exist or is fixed, or (only when a
    path is asked for) a mechanism that locks (`LockingError`).
    """
    topology = analyze_topology(adjacency, node_types)
    n = topology.n_joints
    pos = as_positions(positions, n)
    check_positions(topology.adjacency, pos)
    crank = float(np.hypot(*(pos[1] - pos[0])))
    if crank_mm is None:
        frame, crank_mm, scale, origin = "drawing", crank, 1.0, np.zeros(2)
    else:
        crank_mm = as_crank_mm(crank_mm)
        frame, scale, origin = "crank", crank_mm / crank, pos[0].copy()
    joints_mm = (pos - origin) * scale
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
        path = (trajectories[path_joint] - origin) * scale
    drawn = joints_mm if path is None else np.vstack([joints_mm, path])
    extent = float(np.ptp(drawn, axis=0).max())
    if extent > MAX_DRAWING_MM:
        advice = (
            f"the crank is short beside the other links; choose a shorter crank_mm than "
            f"{crank_mm:g}"
            if frame == "crank"
            else "its positions are read as millimetres; choose a crank_mm to scale it"
        )
        raise ValueError(
            f"the drawing would span {extent:.3g} mm, more than {MAX_DRAWING_MM:g} mm: {advice}"
        )
    return Fabrication(
        crank_mm=crank_mm,
        scale=scale,
        frame=frame,
        origin=origin,
        node_types=topology.node_types.astype(np.int64),
        joints_mm=joints_mm,
        links=tuple(links),
        path_joint=path_joint,
        path_mm=path,
    )
