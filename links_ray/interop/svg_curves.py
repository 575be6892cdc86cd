"""Curves read from SVG files, bounded before svgelements expands them.

An SVG is scanned by expat first (`_SvgScan`): its elements, nesting, numbers and transforms
are counted as svgelements would make them, `<use>` copies included without making them, and
an XML entity is refused. svgelements then gets the geometry alone (no CSS, text or styling),
and the chosen shape's segments are flattened within the budget of `interop.outlines`.
svgelements is imported only when an SVG is read.
"""

from __future__ import annotations

import io
import math
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from typing import Any
from xml.parsers import expat

import numpy as np

from links_ray.engine.inputs import shown
from links_ray.interop.curve_limits import (
    MAX_CURVE_SEGMENTS,
    MAX_SVG_ATTRIBUTE_CHARS,
    MAX_SVG_DEPTH,
    MAX_SVG_ELEMENTS,
    MAX_SVG_NUMBERS,
    MAX_SVG_TRANSFORMS,
)
from links_ray.interop.outlines import (
    SATURATED_COUNT,
    Along,
    CurveFileTooLarge,
    flatten,
    too_many,
)

SVG_SHAPES = "path, polyline, polygon, rect, circle, ellipse or line"

_SVG_NAMESPACE = "{http://www.w3.org/2000/svg"  # svgelements strips it so, without the "}"
_XLINK_HREF = "{http://www.w3.org/1999/xlink}href"
#: The attributes svgelements draws shapes from. Every other one (fill, stroke, font, class,
#: clip-path, ...) is dropped before it parses, with text and `<style>`'s CSS: none of them is
#: geometry, and svgelements reads several with regular expressions that take quadratic time
#: or worse on a short string (a `<style>` with no `{`, digits in a polyline's points, a
#: `font`, a color).
_SVG_GEOMETRY = frozenset(
    "id transform display viewBox preserveAspectRatio x y width height rx ry cx cy r "
    "x1 y1 x2 y2".split()
)
#: Attributes kept only on the elements that draw with them: svgelements would let an element
#: inherit one from its parent and parse it again.
_SVG_DATA = {"d": ("path",), "points": ("polyline", "polygon")}
_SVG_HREFS = ("href", _XLINK_HREF)  # svgelements reads xlink:href, then href over it
#: A number of SVG path data or points, with possessive quantifiers: linear time.
_SVG_NUMBER = re.compile(r"[-+]?+(?:[0-9]++(?:\.[0-9]*+)?+|\.[0-9]++)(?:[eE][-+]?+[0-9]++)?+")
_PATH_COMMAND = re.compile(r"[MmZzLlHhVvCcSsQqTtAa]")
#: Transform functions whose arguments hold no parenthesis, on which svgelements' pattern
#: runs in linear time (`scale(` repeated unclosed takes it quadratic time).
_TRANSFORM = re.compile(r"(?:[\s,]*+[A-Za-z]++\s*+\([^()]*+\))*+[\s,]*+")


@dataclass
class _SvgNode:
    """An element of a scanned SVG, with the work svgelements does for it alone."""

    element: ET.Element
    children: list[int]
    numbers: int  # in its path data or points
    transforms: int  # functions it applies to itself and every element below it
    href: str | None  # what a <use> refers to


class _SvgScan:
    """An SVG parsed by expat into what svgelements is to read (`nodes`, the first the root),
    bounded as it is read: MAX_SVG_ELEMENTS and MAX_SVG_DEPTH as the document stands,
    MAX_SVG_ATTRIBUTE_CHARS and MAX_SVG_NUMBERS for each element. An entity declaration is
    refused: no drawing needs one, and entities expand."""

    def __init__(self, file: str) -> None:
        self.file = file
        self.nodes: list[_SvgNode] = []
        self.ids: dict[str, int] = {}
        self.open: list[int] = []

    def parse(self, data: bytes) -> None:
        """Read `data` into `nodes`, or ValueError naming the problem."""
        parser = expat.ParserCreate(namespace_separator="}")
        parser.StartElementHandler = self.start
        parser.EndElementHandler = self.end
        parser.EntityDeclHandler = self.entity
        parser.UnparsedEntityDeclHandler = self.entity
        try:
            parser.Parse(data, True)
        except expat.ExpatError as exc:  # named as ElementTree, svgelements' parser, names it
            if exc.code == expat.errors.codes[expat.errors.XML_ERROR_NO_MEMORY]:
                raise MemoryError(str(exc)) from None
            raise ValueError(f"{self.file}: not a readable SVG (ParseError: {exc})") from None

    def entity(self, name: str, *_: object) -> None:
        """Refuse an entity declaration."""
        raise ValueError(f"{self.file}: declares the XML entity {shown(name)}: none is read")

    def start(self, name: str, given: dict[str, str]) -> None:
        """Keep the element `name` with its geometry, bounded."""
        file = self.file
        if len(self.nodes) == MAX_SVG_ELEMENTS:
            raise CurveFileTooLarge(
                f"{file}: more than the {MAX_SVG_ELEMENTS:,} elements an SVG may hold",
                "MAX_SVG_ELEMENTS",
            )
        too_many(
            file,
            len(self.open) + 1,
            MAX_SVG_DEPTH,
            "MAX_SVG_DEPTH",
            "elements nested {count} deep, more than the {limit} an SVG's may be",
        )
        tag = "{" + name if "}" in name else name
        local = tag[28:] if tag.startswith(_SVG_NAMESPACE) else tag
        attributes = {("{" + k if "}" in k else k): v for k, v in given.items()}
        # What svgelements looks an element up by, and a <use> refers by: as written.
        written_id = attributes.get("id")
        href = attributes.get("href", attributes.get(_XLINK_HREF)) if local == "use" else None
        # The style attribute split as svgelements splits it (";" then ":"), what it says
        # taking the place of the attribute of that name.
        for item in attributes.pop("style", "").split(";"):
            key, *value = item.split(":")
            if len(value) == 1:
                attributes[key.strip()] = value[0].strip()
        kept = {}
        for key, value in attributes.items():
            if key in _SVG_GEOMETRY or (key in _SVG_HREFS and local == "use"):
                too_many(
                    file,
                    len(value),
                    MAX_SVG_ATTRIBUTE_CHARS,
                    "MAX_SVG_ATTRIBUTE_CHARS",
                    f"the {key} of a <{local}> holds {{count}} characters, more than the "
                    "{limit} an attribute may (path data and points aside)",
                )
                kept[key] = value
            elif local in _SVG_DATA.get(key, ()):
                kept[key] = value
        functions = _transform_functions(file, local, kept)
        numbers = 0
        for key, holders in _SVG_DATA.items():
            if local in holders:
                value = kept.setdefault(key, "")  # so that it inherits none from its parent
                numbers = _SVG_NUMBER.subn("", value)[1]
                if key == "d":
                    numbers += _PATH_COMMAND.subn("", value)[1]
                too_many(
                    file,
                    numbers,
                    MAX_SVG_NUMBERS,
                    "MAX_SVG_NUMBERS",
                    f"the {key} of a <{local}> holds {{count}} numbers, more than the "
                    "{limit} an SVG's shapes may",
                )
                if key == "points":
                    kept[key] = _plain_points(value)
        index = len(self.nodes)
        if self.open:
            parent = self.nodes[self.open[-1]]
            parent.children.append(index)
            element = ET.SubElement(parent.element, tag, kept)
        else:
            element = ET.Element(tag, kept)
        if written_id is not None:
            self.ids[written_id] = index  # the last of an id wins, as in svgelements
        self.open.append(index)
        self.nodes.append(_SvgNode(element, [], numbers, functions, href))

    def end(self, name: str) -> None:
        """Close the element `name`."""
        self.open.pop()

    def check_copies(self) -> None:
        """Refuse the document if, with every copy its `<use>` elements make, it holds more
        than MAX_SVG_ELEMENTS elements or MAX_SVG_NUMBERS numbers, nests deeper than
        MAX_SVG_DEPTH, or has svgelements apply more than MAX_SVG_TRANSFORMS transform
        functions; or if a `<use>` contains itself. Each element is visited once: the
        copies are counted, not made."""
        nodes = self.nodes
        # Of each element with all it holds, copies made: elements, depth, numbers, transform
        # functions applied (every element applies its own and its ancestors').
        elements, depth, numbers, applied = ([0] * len(nodes) for _ in range(4))
        done, walking = [False] * len(nodes), [False] * len(nodes)
        stack = [(0, False)]
        while stack:
            index, returning = stack.pop()
            below = self._below(index)
            if returning:
                node = nodes[index]
                elements[index] = min(SATURATED_COUNT, 1 + sum(elements[k] for k in below))
                depth[index] = 1 + max((depth[k] for k in below), default=0)
                numbers[index] = min(SATURATED_COUNT, node.numbers + sum(numbers[k] for k in below))
                applied[index] = min(
                    SATURATED_COUNT,
                    node.transforms * elements[index] + sum(applied[k] for k in below),
                )
                done[index], walking[index] = True, False
            elif not done[index]:
                walking[index] = True
                stack.append((index, True))
                for k in below:
                    if walking[k]:
                        looped = shown(nodes[k].element.get("id"))
                        raise ValueError(f"{self.file}: a <use> of #{looped} contains itself")
                    if not done[k]:
                        stack.append((k, False))
        file, copies = self.file, "counting <use> copies"
        too_many(
            file,
            elements[0],
            MAX_SVG_ELEMENTS,
            "MAX_SVG_ELEMENTS",
            f"{{count}} elements, {copies}, more than the {{limit}} an SVG may hold",
        )
        too_many(
            file,
            depth[0],
            MAX_SVG_DEPTH,
            "MAX_SVG_DEPTH",
            f"elements nested {{count}} deep, {copies}, more than the {{limit}} an SVG's may be",
        )
        too_many(
            file,
            numbers[0],
            MAX_SVG_NUMBERS,
            "MAX_SVG_NUMBERS",
            f"{{count}} numbers in its shapes' path data and points, {copies}, more "
            "than the {limit} an SVG may hold",
        )
        too_many(
            file,
            applied[0],
            MAX_SVG_TRANSFORMS,
            "MAX_SVG_TRANSFORMS",
            f"{{count}} transform functions applied (each element applies its "
            f"ancestors' too), {copies}, more than the {{limit}} an SVG may apply",
        )

    def _below(self, index: int) -> list[int]:
        """The elements svgelements reads inside element `index`: its children, then for a
        `<use>` what it refers to (by its href without the first character, as svgelements
        looks it up)."""
        node = self.nodes[index]
        if node.href is None or (target := self.ids.get(node.href[1:])) is None:
            return node.children
        return [*node.children, target]


def _transform_functions(file: str, local: str, kept: dict[str, str]) -> int:
    """The transform functions svgelements applies for an element of tag `local` and
    attributes `kept`: its transform's, its viewport's (an `svg`), its translation (a `use`);
    ValueError for a transform that is not a list of functions."""
    transform = kept.get("transform", "")
    if not _TRANSFORM.fullmatch(transform):
        raise ValueError(
            f"{file}: the transform of a <{local}> is not a list of functions such as "
            f"translate(1, 2): {shown(transform)}"
        )
    functions = transform.count("(")
    if local == "svg" and "viewBox" in kept:
        functions += 2  # its viewport's scale and translation
    if local == "use" and ("x" in kept or "y" in kept):
        functions += 1
    return functions


def _plain_points(points: str) -> str:
    """`points` as "x,y x,y ..." of its numbers in pairs (an odd last one dropped, as
    svgelements drops it), each number as Python writes a float: svgelements' pattern for
    pairs takes cubic time in the length of a run of digits."""
    numbers = [float(n) for n in _SVG_NUMBER.findall(points)]
    written = [repr(n) if math.isfinite(n) else ("1e999" if n > 0 else "-1e999") for n in numbers]
    return " ".join(f"{x},{y}" for x, y in zip(written[0::2], written[1::2], strict=False))


def _bounded_svg(file: str, data: bytes) -> bytes:
    """The SVG `data` as svgelements is to read it: scanned and bounded (`_SvgScan`), and
    written again with its geometry alone."""
    scan = _SvgScan(file)
    scan.parse(data)  # an XML document has a root element, or expat says so
    scan.check_copies()
    return ET.tostring(scan.nodes[0].element)


def read_svg(file: str, data: bytes, part: str | None) -> tuple[np.ndarray, bool, str]:
    """The outline of the shape `part` names (its id; else the first shape) in the SVG `data`,
    y up, whether it is closed, and what was read; ValueError naming the file and problem."""
    import svgelements as se

    bounded = _bounded_svg(file, data)
    try:
        svg = se.SVG.parse(io.BytesIO(bounded), reify=True)
        elements = list(svg.elements())
    except MemoryError:
        raise
    except Exception as exc:  # whatever the parser trips on in a bad file
        raise ValueError(f"{file}: not a readable SVG ({type(exc).__name__}: {exc})") from None
    shapes = [e for e in elements if isinstance(e, se.Shape)]
    if part is None:
        if not shapes:
            raise ValueError(f"{file}: no {SVG_SHAPES} in it")
        shape = shapes[0]
    else:
        chosen = [e for e in shapes if e.id == part]
        if not chosen:
            if any(getattr(e, "id", None) == part for e in elements):
                raise ValueError(f"{file}: element {part!r} is not a {SVG_SHAPES}")
            ids = sorted({e.id for e in shapes if e.id})
            listed = f"ids: {', '.join(ids)}" if ids else "no shape has an id"
            raise ValueError(f"{file}: no element with id {part!r} ({listed})")
        shape = chosen[0]
    name = f"#{shape.id}" if shape.id else f" ({type(shape).__name__.lower()}, the first shape)"
    # The outer viewport's scale undone: the drawing's own units, as its author drew them.
    viewport = se.Matrix(svg.viewbox_transform) if svg.viewbox_transform else se.Matrix()
    path = abs(se.Path(shape) * ~viewport)
    drawn = [list(sub) for sub in path.as_subpaths()]
    drawn = [segments for segments in drawn if any(not isinstance(s, se.Move) for s in segments)]
    if not drawn:
        raise ValueError(f"{file}: {name.strip()} draws nothing")
    if len(drawn) > 1:
        raise ValueError(
            f"{file}: {name.strip()} holds {len(drawn)} separate curves (subpaths): one is read"
        )
    segments = [s for s in drawn[0] if not isinstance(s, se.Move)]
    too_many(
        file,
        len(segments),
        MAX_CURVE_SEGMENTS,
        "MAX_CURVE_SEGMENTS",
        f"{name.strip()} has {{count}} segments, more than the {{limit}} a curve may have",
    )
    closed = isinstance(segments[-1], se.Close)
    straight = np.array([isinstance(s, se.Linear) for s in segments])
    outline = flatten(file, _svg_along(segments), len(segments), straight)
    return outline * [1.0, -1.0], closed, f"{file}{name}"


def _svg_along(segments: list[Any]) -> Along:
    """svgelements' segments as `flatten` takes them, evaluated all at once: lines and
    quadratic Béziers raised to the cubics they are, arcs on their ellipses (svgelements' own
    evaluation costs a Python call a segment, a few times over)."""
    import svgelements as se

    count = len(segments)
    cubic = np.zeros((count, 4, 2))  # control points; an arc's start and end in 0 and 3
    arc = np.zeros(count, dtype=bool)
    ellipse = np.zeros((count, 7))  # an arc's centre x, y, radii, rotation, start, sweep
    for k, segment in enumerate(segments):
        start, end = np.array(segment.start, dtype=float), np.array(segment.end, dtype=float)
        if isinstance(segment, se.CubicBezier):
            cubic[k] = [start, segment.control1, segment.control2, end]
        elif isinstance(segment, se.QuadraticBezier):
            control = np.array(segment.control, dtype=float)
            cubic[k] = [
                start,
                start + 2 / 3 * (control - start),
                end + 2 / 3 * (control - end),
                end,
            ]
        elif isinstance(segment, se.Arc) and not (
            segment.start == segment.end and not segment.sweep
        ):
            cubic[k, 0], cubic[k, 3], arc[k] = start, end, True
            centre = segment.center
            ellipse[k] = (centre.x, centre.y, segment.rx, segment.ry, segment.get_rotation(),
                          segment.get_start_t(), segment.sweep)  # fmt: skip
        elif isinstance(segment, se.Linear | se.Arc):  # a line, or an arc that stays put
            cubic[k] = [start, (2 * start + end) / 3, (start + 2 * end) / 3, end]
        else:
            raise ValueError(f"a path segment of an unknown kind: {type(segment).__name__}")

    def along(index: np.ndarray, t: np.ndarray) -> np.ndarray:
        c, u, s = cubic[index], 1 - t[:, None], t[:, None]
        points = u**3 * c[:, 0] + 3 * u * u * s * c[:, 1] + 3 * u * s * s * c[:, 2] + s**3 * c[:, 3]
        x, y, a, b, rotation, begin, sweep = ellipse[index].T
        turn = begin + t * sweep
        along_a, along_b = a * np.cos(turn), b * np.sin(turn)
        on_arc = np.column_stack(
            [
                x + along_a * np.cos(rotation) - along_b * np.sin(rotation),
                y + along_a * np.sin(rotation) + along_b * np.cos(rotation),
            ]
        )
        points = np.where(arc[index, None], on_arc, points)
        points[t == 0] = c[t == 0, 0]  # an arc's ends exact, as svgelements keeps them
        points[t == 1] = c[t == 1, 3]
        return points

    return along
