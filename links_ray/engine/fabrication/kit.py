"""A mechanism as a kit of printed parts: the options of a kit, where every part goes in the
assembly, and the bill of materials.

The parts. Every link is a bar `bar_width_mm` wide around its centre line with rounded ends and a
hole `hole_diameter_mm` across at each joint, `layer_thickness_mm` thick, on the layer
`engine.fabrication.layers` gives it. Every joint with links has a pin `pin_diameter_mm` across
through its span of layers. Where a pin passes a layer gap or a layer that holds none of its links,
a spacer (a tube `spacer_diameter_mm` outside, `hole_diameter_mm` inside) fills the pin between two
of its links, so that each link stays at its height. With `ground_on_base`, a base plate under layer
0 holds every fixed joint's pin (a post, `engine.fabrication.layers`), its holes the pins' diameter
across (a press fit), the plate as thick as a layer and reaching `bar_width_mm` beyond every joint's
path.

Heights, z up, T the layer thickness and g the layer gap. Layer l holds its bars from z = l (T
+ g) to l (T + g) + T; the base plate's top is at -g. A pin reaches half a gap past its
lowest and highest links (a post: from the plate's bottom), so its ends stay in the gaps,
clear of the links that pass over and under it on the next layers: heads, clips and nuts
beyond that are the builder's. Between two of a pin's links on layers a < b (for a post, the
plate below its lowest link as layer -1), a spacer (b - a) (T + g) - T long; none where that
is 0 (no gap, neighbouring layers).

Clearances. The layers are planned (`engine.fabrication.layers.plan_layers`) with the spacers'
diameter as the pins', the widest a pin is within its span: no two bars on a layer come within
`clearance_mm` of each other over the turn, and no bar on a layer within a pin's span comes within
it of that pin or its spacers. The parts of different layers are apart by the gap.

Frames. With `crank_mm`, the positions are scaled so that the crank is that long, joint 0 at the
origin (`engine.fabrication.drawings`); with None, they are kept as they are, their unit read as a
millimetre: the sizes are then in that unit. Each link's part is made along +x from its lower joint
at the origin (`Kit.bom` says where it goes: that joint's position and the link's angle, at its
layer's height).

Pure numpy: no numba of its own, no Ray, no files (`interop.parts` makes the meshes).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from links_ray.engine.fabrication.drawings import Fabrication, fabrication
from links_ray.engine.fabrication.layers import LayeringError, LayerPlan, plan_layers
from links_ray.engine.fabrication.limits import (
    DEFAULT_COLLISION_STEPS,
    DEFAULT_CRANK_MM,
    MAX_DRAWING_MM,
    as_crank_mm,
)
from links_ray.engine.inputs import as_flag, as_real, positive_at_most
from links_ray.engine.kinematics.solver import simulate
from links_ray.engine.node_kinds import FIXED

__all__ = [
    "ASSEMBLY_FILE",
    "BOM_FILE",
    "BasePlate",
    "Kit",
    "KitOptions",
    "Pin",
    "Placement",
    "Spacer",
    "kit_layers",
    "plan_kit",
]

#: The defaults, in millimetres: an 8 mm bar 3 mm thick is stiff for a few hundred millimetres
#: of printed plastic and leaves 2.3 mm of wall around a 3.4 mm hole, in which a 3 mm pin (a
#: steel rod, a screw's shank) turns freely on a printer that prints holes a little small; a
#: 6 mm spacer keeps 1.3 mm of wall; 1 mm clearance absorbs print tolerance and a bar's flex;
#: a 0.5 mm gap, kept by washers, stops bars on neighbouring layers rubbing as they cross.
DEFAULT_BAR_WIDTH_MM = 8.0
DEFAULT_HOLE_DIAMETER_MM = 3.4
DEFAULT_PIN_DIAMETER_MM = 3.0
DEFAULT_SPACER_DIAMETER_MM = 6.0
DEFAULT_CLEARANCE_MM = 1.0
DEFAULT_LAYER_THICKNESS_MM = 3.0
DEFAULT_LAYER_GAP_MM = 0.5
#: The files of a kit's folder, beside its parts' folder.
BOM_FILE, ASSEMBLY_FILE, PARTS_FOLDER = "bom.json", "assembly.glb", "parts"


@dataclass(frozen=True)
class KitOptions:
    """What a kit is asked for, checked when made (ValueError naming a bad field).

    `crank_mm`: the crank's length, joint 0 at the origin; None keeps the positions' frame,
    their unit read as a millimetre (the sizes are then in that unit). The sizes, each more
    than 0 and at most MAX_DRAWING_MM (the clearance and the gap may be 0), with the pin
    narrower than its hole, the hole than the spacer and the spacer than the bar.
    `ground_on_base`: fixed pins stand on a base plate.
    """

    crank_mm: float | None = DEFAULT_CRANK_MM
    bar_width_mm: float = DEFAULT_BAR_WIDTH_MM
    hole_diameter_mm: float = DEFAULT_HOLE_DIAMETER_MM
    pin_diameter_mm: float = DEFAULT_PIN_DIAMETER_MM
    spacer_diameter_mm: float = DEFAULT_SPACER_DIAMETER_MM
    clearance_mm: float = DEFAULT_CLEARANCE_MM
    layer_thickness_mm: float = DEFAULT_LAYER_THICKNESS_MM
    layer_gap_mm: float = DEFAULT_LAYER_GAP_MM
    ground_on_base: bool = False

    def __post_init__(self) -> None:
        checked: dict[str, Any] = {
            "crank_mm": None if self.crank_mm is None else as_crank_mm(self.crank_mm),
            "ground_on_base": as_flag(self.ground_on_base, "ground_on_base"),
        }
        for name in (
            "bar_width_mm",
            "hole_diameter_mm",
            "pin_diameter_mm",
            "spacer_diameter_mm",
            "layer_thickness_mm",
        ):
            checked[name] = _size(name, getattr(self, name))
        for name in ("clearance_mm", "layer_gap_mm"):
            checked[name] = _size(name, getattr(self, name), zero=True)
        for narrow, wide, why in (
            ("pin_diameter_mm", "hole_diameter_mm", "the pin turns in the hole"),
            ("hole_diameter_mm", "spacer_diameter_mm", "a spacer is a tube around the pin"),
            ("spacer_diameter_mm", "bar_width_mm", "a hole must leave its bar whole"),
        ):
            if not checked[narrow] < checked[wide]:
                raise ValueError(
                    f"{narrow} must be less than {wide} ({why}), got {checked[narrow]:g} and "
                    f"{checked[wide]:g}"
                )
        for name, value in checked.items():
            object.__setattr__(self, name, value)  # frozen: set once, here

    @property
    def pitch_mm(self) -> float:
        """From one layer's bottom to the next one's: a layer and a gap."""
        return self.layer_thickness_mm + self.layer_gap_mm

    def layer_bottom(self, layer: int) -> float:
        """The height of the bottom of `layer` (-1: the base plate, whose top is at -gap)."""
        return layer * self.pitch_mm


def _size(name: str, value: object, zero: bool = False) -> float:
    """A length of a kit in millimetres: more than 0 (or 0 with `zero`), at most
    MAX_DRAWING_MM; else ValueError naming `name`."""
    if not zero:
        return positive_at_most(value, name, MAX_DRAWING_MM, "a number of millimetres", " mm")
    number = as_real(name, value, "a number of millimetres")
    if not 0.0 <= number <= MAX_DRAWING_MM:  # written so that NaN fails too
        raise ValueError(f"{name} must be from 0 to {MAX_DRAWING_MM:g} mm, got {number:g}")
    return number


@dataclass(frozen=True)
class Pin:
    """A joint's pin: the layers [lo, hi] it runs through, its ends' heights (bottom, top)
    and whether it is a post standing in the base plate."""

    joint: int
    layers: tuple[int, int]
    z_mm: tuple[float, float]
    post: bool

    @property
    def length_mm(self) -> float:
        """How long the pin is cut."""
        return self.z_mm[1] - self.z_mm[0]

    @property
    def node(self) -> str:
        """Its name in the assembly, and its part's: `pin-J`."""
        return f"pin-{self.joint}"


@dataclass(frozen=True)
class Spacer:
    """A tube on a joint's pin between two of its links, on layers `between` (-1: the base
    plate), from height z_mm[0] to z_mm[1]."""

    joint: int
    between: tuple[int, int]
    z_mm: tuple[float, float]

    @property
    def length_mm(self) -> float:
        """How long the spacer is."""
        return self.z_mm[1] - self.z_mm[0]

    @property
    def node(self) -> str:
        """Its name in the assembly: `spacer-J-A-B`, A `base` for the plate."""
        below, above = ("base" if layer < 0 else str(layer) for layer in self.between)
        return f"spacer-{self.joint}-{below}-{above}"

    @property
    def part(self) -> str:
        """Its part's name: spacers of one length are one part, printed as many times."""
        return f"spacer-{self.length_mm:.6g}mm"


@dataclass(frozen=True)
class BasePlate:
    """The plate the posts stand in: its extent (min x, min y, max x, max y) and heights."""

    extent_mm: tuple[float, float, float, float]
    z_mm: tuple[float, float]
    posts: tuple[int, ...]


@dataclass(frozen=True)
class Placement:
    """One part placed in the assembly: its node's name, its part's name (its file's stem)
    and the 4 x 4 matrix that takes the part's own frame to the assembly's, in mm, z up."""

    node: str
    part: str
    matrix: np.ndarray


@dataclass(frozen=True, eq=False)
class Kit:
    """A mechanism as a kit of printed parts: its drawing in millimetres
    (`engine.fabrication.drawings`), its layer plan (`engine.fabrication.layers`), its pins, spacers
    and base plate, and the options."""

    options: KitOptions
    drawing: Fabrication
    plan: LayerPlan
    pins: tuple[Pin, ...]
    spacers: tuple[Spacer, ...]
    base: BasePlate | None

    def link_z(self, link: int) -> tuple[float, float]:
        """The heights of link `link`'s bottom and top (a row of `plan.links`)."""
        bottom = self.options.layer_bottom(int(self.plan.link_layer[link]))
        return bottom, bottom + self.options.layer_thickness_mm

    def placements(self, joints_mm: ArrayLike | None = None) -> list[Placement]:
        """Every part placed with the joints at `joints_mm` (n, 2) (default: the starting
        pose): a link's part turned to its angle about its lower joint, at its layer's
        height; pins and spacers at their joints; the base plate as it is made."""
        pose = self.drawing.joints_mm if joints_mm is None else np.asarray(joints_mm, float)
        placed = []
        for k, (i, j) in enumerate(self.plan.links.tolist()):
            dx, dy = pose[j] - pose[i]
            angle = math.atan2(dy, dx)
            matrix = _moved(pose[i, 0], pose[i, 1], self.link_z(k)[0], angle)
            placed.append(Placement(link_name(i, j), link_name(i, j), matrix))
        for pin in self.pins:
            x, y = pose[pin.joint]
            placed.append(Placement(pin.node, pin.node, _moved(x, y, pin.z_mm[0])))
        for spacer in self.spacers:
            x, y = pose[spacer.joint]
            placed.append(Placement(spacer.node, spacer.part, _moved(x, y, spacer.z_mm[0])))
        if self.base is not None:
            placed.append(Placement("base", "base", _moved(0.0, 0.0, self.base.z_mm[0])))
        return placed

    def bom(self) -> dict[str, Any]:
        """The bill of materials as a JSON-ready dict (docs/guides/building.md says each
        field): the options, the plan's layers, each link, pin and spacer, their parts' files
        and their nodes in the assembly."""
        options = asdict(self.options)
        options.pop("crank_mm")
        drawing, plan = self.drawing, self.plan
        lengths = {link.joints: link for link in drawing.links}
        joints = drawing.table()["joints"]
        links = []
        for k, (i, j) in enumerate(plan.links.tolist()):
            dx, dy = drawing.joints_mm[j] - drawing.joints_mm[i]
            links.append(
                {
                    "joints": [i, j],
                    "layer": int(plan.link_layer[k]),
                    "length_mm": lengths[(i, j)].length_mm,
                    "kind": lengths[(i, j)].kind,
                    "z_mm": list(self.link_z(k)),
                    "angle_deg": math.degrees(math.atan2(dy, dx)),
                    "node": link_name(i, j),
                    "part": part_file(link_name(i, j)),
                }
            )
        pins = [
            {
                "joint": pin.joint,
                "layers": list(pin.layers),
                "length_mm": pin.length_mm,
                "diameter_mm": self.options.pin_diameter_mm,
                "z_mm": list(pin.z_mm),
                "post": pin.post,
                "node": pin.node,
                "part": part_file(pin.node),
            }
            for pin in self.pins
        ]
        spacers = [
            {
                "joint": spacer.joint,
                "between": list(spacer.between),
                "length_mm": spacer.length_mm,
                "inner_diameter_mm": self.options.hole_diameter_mm,
                "outer_diameter_mm": self.options.spacer_diameter_mm,
                "z_mm": list(spacer.z_mm),
                "node": spacer.node,
                "part": part_file(spacer.part),
            }
            for spacer in self.spacers
        ]
        base = None
        if self.base is not None:
            base = {
                "extent_mm": list(self.base.extent_mm),
                "z_mm": list(self.base.z_mm),
                "posts": list(self.base.posts),
                "hole_diameter_mm": self.options.pin_diameter_mm,
                "node": "base",
                "part": part_file("base"),
            }
        return {
            "unit": "mm",
            "frame": drawing.frame,
            "crank_mm": drawing.crank_mm,
            "mm_per_unit": drawing.scale,
            "origin": drawing.origin.tolist(),
            "layers": plan.layers,
            "lower_bound": plan.lower_bound,
            "optimal": plan.optimal,
            "status": plan.status,
            **options,
            "links": links,
            "pins": pins,
            "spacers": spacers,
            "base": base,
            "joints": joints,
            "parts": sorted({part_file(placement.part) for placement in self.placements()}),
            "assembly": ASSEMBLY_FILE,
        }


def link_name(i: int, j: int) -> str:
    """The name of the link between joints i < j: its part's and its node's."""
    return f"link-{i}-{j}"


def part_file(name: str) -> str:
    """The file of the part named `name`, relative to the kit's folder."""
    return f"{PARTS_FOLDER}/{name}.stl"


def _moved(x: float, y: float, z: float, angle: float = 0.0) -> np.ndarray:
    """The 4 x 4 matrix turning by `angle` radians about z, then moving by (x, y, z)."""
    cos, sin = math.cos(angle), math.sin(angle)
    return np.array(
        [[cos, -sin, 0.0, x], [sin, cos, 0.0, y], [0.0, 0.0, 1.0, z], [0.0, 0.0, 0.0, 1.0]]
    )


def plan_kit(
    adjacency: ArrayLike,
    node_types: ArrayLike,
    positions: ArrayLike,
    options: KitOptions | None = None,
    *,
    steps: int = DEFAULT_COLLISION_STEPS,
) -> Kit:
    """The mechanism as a kit of printed parts (the module's docstring): in millimetres as `options`
    says (default `KitOptions()`: a 20 mm crank), its layers planned over a turn of
    `steps` steps and proven between them.

    Raises `ValueError` naming the problem: what `fabrication` and `plan_layers` refuse, a
    link too short to hold its two holes, and `LayeringError` when no stacking keeps every pin
    clear.
    """
    options = _as_options(options)
    drawing = fabrication(adjacency, node_types, positions, crank_mm=options.crank_mm)
    shortest = min(drawing.links, key=lambda link: link.length_mm)
    if shortest.length_mm <= options.hole_diameter_mm:
        scale = "a longer crank_mm" if drawing.frame == "crank" else "a crank_mm to scale it"
        raise ValueError(
            f"link {list(shortest.joints)} is {shortest.length_mm:.3g} mm long: its holes, "
            f"{options.hole_diameter_mm:g} mm across, would meet; give {scale}, or smaller holes"
        )
    plan = _planned(adjacency, node_types, drawing, options, steps)
    posts = (drawing.node_types == FIXED) & options.ground_on_base
    pins, spacers = _pins_and_spacers(plan, posts, options)
    base = None
    if options.ground_on_base:
        turn = simulate(adjacency, node_types, drawing.joints_mm, steps)
        low = turn.min(axis=(0, 1)) - options.bar_width_mm
        high = turn.max(axis=(0, 1)) + options.bar_width_mm
        bottom = options.layer_bottom(-1)  # the plate is layer -1, as thick as a layer
        base = BasePlate(
            extent_mm=(float(low[0]), float(low[1]), float(high[0]), float(high[1])),
            z_mm=(bottom, bottom + options.layer_thickness_mm),
            posts=tuple(int(j) for j in np.flatnonzero(posts)),
        )
    return Kit(options, drawing, plan, pins, spacers, base)


def kit_layers(
    adjacency: ArrayLike,
    node_types: ArrayLike,
    positions: ArrayLike,
    options: KitOptions | None = None,
    *,
    steps: int = DEFAULT_COLLISION_STEPS,
) -> LayerPlan:
    """The layer plan `plan_kit` would give the mechanism, without its parts: the layers
    alone do not depend on the holes, so a link too short for its two holes is no error here.

    Raises `ValueError` as `plan_kit` does for the drawing and the plan (`LayeringError`
    when no stacking keeps every pin clear)."""
    options = _as_options(options)
    drawing = fabrication(adjacency, node_types, positions, crank_mm=options.crank_mm)
    return _planned(adjacency, node_types, drawing, options, steps)


def _as_options(options: object) -> KitOptions:
    """`options`, or `KitOptions()` for None; ValueError for anything else."""
    if options is None:
        return KitOptions()
    if not isinstance(options, KitOptions):
        raise ValueError(f"options must be a KitOptions, got {type(options).__name__}")
    return options


def _planned(
    adjacency: ArrayLike,
    node_types: ArrayLike,
    drawing: Fabrication,
    options: KitOptions,
    steps: int,
) -> LayerPlan:
    """The layers of `drawing` (the mechanism in mm) at the sizes of `options`."""
    try:
        return plan_layers(
            adjacency,
            node_types,
            drawing.joints_mm,
            bar_width=options.bar_width_mm,
            clearance=options.clearance_mm,
            pin_diameter=options.spacer_diameter_mm,  # the widest a pin is within its span
            ground_on_base=options.ground_on_base,
            steps=steps,
        )
    except LayeringError as exc:
        if options.bar_width_mm < drawing.crank_mm:
            raise
        # Bars as wide as the crank is long: the sizes, not the mechanism, are what is wrong.
        raise LayeringError(
            f"{exc}; the bars are {options.bar_width_mm:g} mm wide beside a crank "
            f"{drawing.crank_mm:.3g} mm long: give a longer crank_mm, or smaller sizes"
        ) from None


def _pins_and_spacers(
    plan: LayerPlan, posts: np.ndarray, options: KitOptions
) -> tuple[tuple[Pin, ...], tuple[Spacer, ...]]:
    """Every joint's pin and the spacers on it, from below (the module's docstring)."""
    half_gap, thickness = options.layer_gap_mm / 2, options.layer_thickness_mm
    pins, spacers = [], []
    for joint, (lo, hi) in enumerate(plan.pin_span.tolist()):
        if lo < 0:  # no links, no pin
            continue
        own = sorted({int(layer) for layer in plan.link_layer[(plan.links == joint).any(axis=1)]})
        post = bool(posts[joint])
        stops = [-1, *own] if post else own
        bottom = options.layer_bottom(-1) if post else options.layer_bottom(own[0]) - half_gap
        top = options.layer_bottom(own[-1]) + thickness + half_gap
        pins.append(Pin(joint, (lo, hi), (bottom, top), post))
        for below, above in itertools.pairwise(stops):
            start, end = options.layer_bottom(below) + thickness, options.layer_bottom(above)
            if end > start:
                spacers.append(Spacer(joint, (below, above), (start, end)))
    return tuple(pins), tuple(spacers)
