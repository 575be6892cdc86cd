"""Target curves read from drawings: SVG, DXF, CSV and JSON files.

`read_curve("drawing.svg#wing")` reads one curve, chosen by what follows `#` (an SVG element's
id, a DXF layer's name) or else the first in the file, and samples it evenly by arc length to
a fixed count of points, open or closed; the engine's validator (`as_drawn_points`) then holds
it to the limits every drawn curve meets; `read_curve_text` reads the same from a file's
contents (what the HTTP API's `/api/curve` is sent). `read_points` reads the JSON points
`links retrieve` and `links synthesize --points` take, as they are.

- `.svg`: a `path`, `polyline`, `polygon`, `rect`, `circle`, `ellipse` or `line`, every transform
  applied (its own and its parents'), in the user units of the outer `svg`, y negated so the
  curve reads as drawn (SVG's y points down); closed when the path ends with `Z`, or the shape
  is a polygon, rect, circle or ellipse.
- `.dxf`: an `LWPOLYLINE` (the arcs of its bulges included), `POLYLINE` or `SPLINE` in
  modelspace; closed by the entity's closed flag.
- `.csv`: `x,y` lines, a header line allowed; closed when the last point repeats the first.
- `.json`: `[[x, y], ...]` or `{"points": [[x, y], ...], "closed": true}`; closed when it says
  so or the last point repeats the first.

Every file is bounded before its parser expands it (interop/curve_limits.py): an SVG is
scanned first (its elements, nesting, numbers and transforms counted as svgelements would make
them, `<use>` copies included) and handed to svgelements with its geometry alone, no CSS, text
or styling; a DXF's entities are counted before ezdxf loads it; the curve read has at most
MAX_CURVE_SEGMENTS segments and is flattened to a fixed budget of points. A file past a limit
raises `CurveFileTooLarge`.

svgelements and ezdxf are imported only when an SVG or a DXF file is read.
"""

from __future__ import annotations

import io
import json
import math
import os
import re
import xml.etree.ElementTree as ET
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from xml.parsers import expat

import numpy as np
import orjson

from links_ray.engine.inputs import (
    MAX_COORDINATE,
    MAX_POINTS,
    MIN_POINTS,
    as_drawn_points,
    as_int,
    shown,
)
from links_ray.engine.paths import even_along
from links_ray.interop.curve_limits import (
    MAX_CURVE_FILE_BYTES,
    MAX_CURVE_SEGMENTS,
    MAX_DXF_ENTITIES,
    MAX_SPLINE_FIT_POINTS,
    MAX_SVG_ATTRIBUTE_CHARS,
    MAX_SVG_DEPTH,
    MAX_SVG_ELEMENTS,
    MAX_SVG_NUMBERS,
    MAX_SVG_TRANSFORMS,
)

__all__ = [
    "CURVE_FILE_TYPES",
    "DEFAULT_CURVE_POINTS",
    "Curve",
    "CurveFileTooLarge",
    "read_curve",
    "read_curve_text",
    "read_points",
]

#: Points a curve read from a file is sampled to by default: as dense as the bench's targets.
DEFAULT_CURVE_POINTS = 400
#: Points the curved segments of a drawing (Béziers, arcs, splines) share by length before
#: the even resampling, two each at the least: a circle's chords then sag about 1e-8 of its
#: radius, far below the MAX_POINTS the curve is resampled to at the most.
FLAT_POINTS = 20_000
#: The extensions read, lower case.
CURVE_FILE_TYPES = (".csv", ".dxf", ".json", ".svg")

_TOO_LARGE = f"larger than {MAX_CURVE_FILE_BYTES:,} bytes, the most a curve file may be"
_SVG_SHAPES = "path, polyline, polygon, rect, circle, ellipse or line"
_DXF_ENTITIES = "LWPOLYLINE, POLYLINE or SPLINE"


class CurveFileTooLarge(ValueError):
    """A drawing past a limit on what a curve file may hold (its bytes, an SVG's elements, a
    curve's segments, ...): `limit` is the name of the constant in interop/curve_limits.py. The
    HTTP API answers it with 413."""

    status = 413

    def __init__(self, message: str, limit: str) -> None:
        super().__init__(message)
        self.limit = limit


@dataclass(frozen=True)
class Curve:
    """A target curve read from a file: `points` (N, 2) float64, evenly spaced by arc length
    (from end to end when open, around when `closed`, its last point then not repeating its
    first); `source`, the file and what in it was read."""

    points: np.ndarray
    closed: bool
    source: str


def read_curve(target: str | os.PathLike[str], points: int = DEFAULT_CURVE_POINTS) -> Curve:
    """The curve in `target`, a file path with an optional `#id` (an SVG element's id, a DXF
    layer's name), sampled evenly by arc length to `points` points (MIN_POINTS to MAX_POINTS).

    SVG's y axis points down: y is negated, so the curve reads as drawn. ValueError naming the
    file and the problem: an unknown extension, a file unreadable or malformed, no such element
    or layer, a single point; `CurveFileTooLarge` (a ValueError) for a file past a limit."""
    count = as_int("points", points, MIN_POINTS, MAX_POINTS)
    file, part = _split_target(os.fspath(target))
    _reader(file)  # an unknown extension is named before the file is read
    return _parse_curve(file, _read_bytes(file, file), part, count)


def read_curve_text(
    name: str, text: str | bytes, part: str | None = None, points: int = DEFAULT_CURVE_POINTS
) -> Curve:
    """The curve in a file's contents `text`, as `read_curve` reads the file: `name` (its
    extension) says how to read it and names it in messages, `part` is what `#id` selects.
    For callers that hold the file but not a path to it (the HTTP API's /api/curve)."""
    count = as_int("points", points, MIN_POINTS, MAX_POINTS)
    return _parse_curve(name, _sized(name, text), part, count)


def _sized(name: str, text: str | bytes) -> bytes:
    """A file's contents `text` as bytes, or CurveFileTooLarge past MAX_CURVE_FILE_BYTES."""
    data = text.encode("utf-8") if isinstance(text, str) else bytes(text)
    if len(data) > MAX_CURVE_FILE_BYTES:
        raise CurveFileTooLarge(f"{name}: {_TOO_LARGE}", "MAX_CURVE_FILE_BYTES")
    return data


def _reader(file: str) -> Callable[[str, bytes, str | None], tuple[np.ndarray, bool, str]]:
    """The reader of `file`'s extension, or ValueError naming the extensions read."""
    kind = Path(file).suffix.lower()
    reader = _READERS.get(kind)
    if reader is None:
        raise ValueError(
            f"{file}: unknown extension {kind or '(none)'!r} (read: {', '.join(CURVE_FILE_TYPES)})"
        )
    return reader


def _parse_curve(file: str, data: bytes, part: str | None, count: int) -> Curve:
    """The curve in `data`, the contents of `file` (named so in messages), resampled."""
    reader = _reader(file)
    kind = Path(file).suffix.lower()
    if part is not None and kind in (".csv", ".json"):
        raise ValueError(f"{file}: a {kind[1:].upper()} file holds one curve, there is no #{part}")
    outline, closed, source = reader(file, data, part)
    if closed and _repeats_first(outline):
        outline = outline[:-1]
    _check_coordinates(file, outline)
    if len(outline) == 0 or np.all(outline == outline[0]):
        raise ValueError(f"{file}: a single point, there is no curve")
    try:
        resampled = as_drawn_points(even_along(outline, count, closed), "the curve's points")
    except ValueError as exc:
        raise ValueError(f"{file}: {exc}") from None
    return Curve(resampled, closed, source)


def read_points(path: str | os.PathLike[str]) -> object:
    """The points of a JSON file holding [[x, y], ...] or {"points": [[x, y], ...]}, as they
    are (the caller validates them); ValueError naming the file if it cannot be read, is
    nested deeper than 1,024 levels or holds a number past float64."""
    label = f"cannot read points from {os.fspath(path)}"
    try:
        value = _load_json(_read_bytes(os.fspath(path), label))
    except ValueError as exc:
        raise ValueError(f"{label}: {exc}") from None
    return _json_points(value)


# -- the file ---------------------------------------------------------------------------------


def _split_target(target: str) -> tuple[str, str | None]:
    """The file and the part after its last `#` (None without one). A file whose own name
    holds `#` is read whole."""
    if "#" in target and not os.path.exists(target):
        file, _, part = target.rpartition("#")
        return file, part or None
    return target, None


def _read_bytes(file: str, label: str) -> bytes:
    """The file's bytes, refused before reading past MAX_CURVE_FILE_BYTES."""
    too_large = CurveFileTooLarge(f"{label}: {_TOO_LARGE}", "MAX_CURVE_FILE_BYTES")
    try:
        if os.stat(file).st_size > MAX_CURVE_FILE_BYTES:
            raise too_large
        with open(file, "rb") as stream:
            data = stream.read(MAX_CURVE_FILE_BYTES + 1)  # a file growing meanwhile
    except OSError as exc:
        raise ValueError(f"{label}: {exc.strerror or exc}") from None
    if len(data) > MAX_CURVE_FILE_BYTES:
        raise too_large
    return data


def _as_outline(value: object) -> np.ndarray | None:
    """`value` as an (N, 2) float64 array, or None if it is not number pairs."""
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        return None
    return array if array.ndim == 2 and array.shape[1] == 2 else None


def _repeats_first(outline: np.ndarray) -> bool:
    return len(outline) > 2 and bool(np.array_equal(outline[0], outline[-1]))


def _check_coordinates(file: str, points: np.ndarray) -> None:
    """Refuse points that are not finite or lie beyond MAX_COORDINATE: lengths measured among
    them would overflow, and no drawn curve holds them."""
    if not np.all(np.isfinite(points)):
        raise ValueError(f"{file}: coordinates must be finite numbers")
    if points.size and (worst := float(np.abs(points).max())) > MAX_COORDINATE:
        raise ValueError(f"{file}: coordinates must lie within +-{MAX_COORDINATE:g}, got {worst:g}")


# -- JSON and CSV -----------------------------------------------------------------------------


def _load_json(data: bytes) -> object:
    """`data` as JSON, or ValueError: orjson refuses nesting deeper than 1,024 levels and
    numbers past float64, where the json module would recurse past Python's limit or hand
    over an integer no float holds."""
    text = data.decode(json.detect_encoding(data))  # UTF-8 (a BOM dropped), -16 or -32
    try:
        return orjson.loads(text)
    except orjson.JSONDecodeError as exc:
        if str(exc).startswith("Not enough memory"):  # how orjson says an allocation failed
            raise MemoryError(str(exc)) from None
        raise


def _json_points(value: object) -> object:
    return value["points"] if isinstance(value, dict) and "points" in value else value


def _read_json(file: str, data: bytes, part: str | None) -> tuple[np.ndarray, bool, str]:
    try:
        value = _load_json(data)
    except ValueError as exc:  # orjson.JSONDecodeError and UnicodeDecodeError are ValueErrors
        raise ValueError(f"{file}: not valid JSON ({exc})") from None
    outline = _as_outline(_json_points(value))
    if outline is None:
        raise ValueError(f'{file}: expected [[x, y], ...] or {{"points": [[x, y], ...]}}')
    said = value.get("closed") if isinstance(value, dict) else None
    if said is not None and not isinstance(said, bool):
        raise ValueError(f"{file}: closed must be true or false, got {said!r}")
    return outline, bool(said) or _repeats_first(outline), file


def _read_csv(file: str, data: bytes, part: str | None) -> tuple[np.ndarray, bool, str]:
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ValueError(f"{file}: not UTF-8 text ({exc})") from None
    rows: list[tuple[float, float]] = []
    first = True
    for number, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        fields = [field.strip() for field in line.split(",")]
        numbers = [_number(field) for field in fields]
        if len(fields) == 2 and None not in numbers:
            rows.append((numbers[0], numbers[1]))  # type: ignore[arg-type]
        elif not (first and len(fields) == 2 and numbers == [None, None]):  # not a header
            raise ValueError(
                f"{file} line {number}: expected two numbers, got {shown(line.strip())}"
            )
        first = False
    outline = np.array(rows, dtype=np.float64).reshape(-1, 2)
    return outline, _repeats_first(outline), file


def _number(field: str) -> float | None:
    try:
        return float(field)
    except ValueError:
        return None


# -- flattening -------------------------------------------------------------------------------

#: A curve as `_flatten` takes it: its points at (segment index, t from 0 to 1) pairs, given
#: as two arrays, the indices in ascending order.
Along = Callable[[np.ndarray, np.ndarray], np.ndarray]

#: Where each segment's length is measured, before its share of FLAT_POINTS is set.
_COARSE = np.linspace(0.0, 1.0, 17)
#: Counts saturate here: a chain of SVG `<use>` multiplies them past any limit.
_MANY = 10**15


def _flatten(file: str, along: Along, count: int, straight: np.ndarray) -> np.ndarray:
    """The `count` segments `along` traces as one polyline: each `straight` one by its end, the
    others sharing FLAT_POINTS by length, two each at the least; at most 3 x `count` +
    FLAT_POINTS + 1 points. Coordinates beyond MAX_COORDINATE are refused first."""
    segments = np.arange(count)
    coarse = along(np.repeat(segments, len(_COARSE)), np.tile(_COARSE, count))
    coarse = coarse.reshape(count, len(_COARSE), 2)
    _check_coordinates(file, coarse)
    lengths = np.linalg.norm(np.diff(coarse, axis=1), axis=2).sum(axis=1)
    curved = float(lengths[~straight].sum())
    share = np.ceil(FLAT_POINTS * lengths / curved) if curved > 0 else np.zeros(count)
    steps = np.where(straight, 1, np.maximum(2, share)).astype(np.int64)
    index = np.repeat(segments, steps)
    taken = np.arange(int(steps.sum())) - np.repeat(np.cumsum(steps) - steps, steps)
    start = along(np.zeros(1, dtype=np.int64), np.zeros(1))
    return np.concatenate([start, along(index, (taken + 1) / steps[index])])


def _too_many(file: str, count: int, limit: int, name: str, message: str) -> None:
    """Refuse `count` past `limit`, the constant `name`: `message` says what, {count} and
    {limit} in it standing for the two."""
    if count > limit:
        found = f"{count:,}" if count < _MANY else f"over {_MANY:.0e}"
        said = message.replace("{count}", found).replace("{limit}", f"{limit:,}")
        raise CurveFileTooLarge(f"{file}: {said}", name)


# -- SVG --------------------------------------------------------------------------------------

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
        _too_many(
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
                _too_many(
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
                _too_many(
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
                elements[index] = min(_MANY, 1 + sum(elements[k] for k in below))
                depth[index] = 1 + max((depth[k] for k in below), default=0)
                numbers[index] = min(_MANY, node.numbers + sum(numbers[k] for k in below))
                applied[index] = min(
                    _MANY, node.transforms * elements[index] + sum(applied[k] for k in below)
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
        _too_many(
            file,
            elements[0],
            MAX_SVG_ELEMENTS,
            "MAX_SVG_ELEMENTS",
            f"{{count}} elements, {copies}, more than the {{limit}} an SVG may hold",
        )
        _too_many(
            file,
            depth[0],
            MAX_SVG_DEPTH,
            "MAX_SVG_DEPTH",
            f"elements nested {{count}} deep, {copies}, more than the {{limit}} an SVG's may be",
        )
        _too_many(
            file,
            numbers[0],
            MAX_SVG_NUMBERS,
            "MAX_SVG_NUMBERS",
            f"{{count}} numbers in its shapes' path data and points, {copies}, more "
            "than the {limit} an SVG may hold",
        )
        _too_many(
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


def _read_svg(file: str, data: bytes, part: str | None) -> tuple[np.ndarray, bool, str]:
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
            raise ValueError(f"{file}: no {_SVG_SHAPES} in it")
        shape = shapes[0]
    else:
        chosen = [e for e in shapes if e.id == part]
        if not chosen:
            if any(getattr(e, "id", None) == part for e in elements):
                raise ValueError(f"{file}: element {part!r} is not a {_SVG_SHAPES}")
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
    _too_many(
        file,
        len(segments),
        MAX_CURVE_SEGMENTS,
        "MAX_CURVE_SEGMENTS",
        f"{name.strip()} has {{count}} segments, more than the {{limit}} a curve may have",
    )
    closed = isinstance(segments[-1], se.Close)
    straight = np.array([isinstance(s, se.Linear) for s in segments])
    outline = _flatten(file, _svg_along(segments), len(segments), straight)
    return outline * [1.0, -1.0], closed, f"{file}{name}"


def _svg_along(segments: list[Any]) -> Along:
    """svgelements' segments as `_flatten` takes them, evaluated all at once: lines and
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


# -- DXF --------------------------------------------------------------------------------------

#: The first integer on a line, as ezdxf's loader takes a group code from a line it cannot
#: read as one whole.
_FIRST_INT = re.compile(rb"[+-]?[0-9]+")


def _dxf_entities(data: bytes) -> int:
    """The records ezdxf would load from `data`, or more: its loader reads lines in pairs, a
    group code (the first integer on its line) then its value, a code 0 starting a record,
    and stops at the first line with no integer."""
    count = 0
    for code in data.split(b"\n")[0::2]:
        head = code.lstrip(b" \t+-")
        if not head[:1].isdigit():
            found = _FIRST_INT.search(code)
            if found is None:
                break
            head = found.group().lstrip(b"+-")
        if head[:1] == b"0" and not head.lstrip(b"0")[:1].isdigit():
            count += 1
    return count


def _read_dxf(file: str, data: bytes, layer: str | None) -> tuple[np.ndarray, bool, str]:
    import ezdxf
    from ezdxf import recover

    _too_many(
        file,
        _dxf_entities(data),
        MAX_DXF_ENTITIES,
        "MAX_DXF_ENTITIES",
        "{count} entities (and other records), more than the {limit} a DXF file may hold",
    )
    try:
        doc, _ = recover.read(io.BytesIO(data))
    except MemoryError:
        raise
    except Exception as exc:  # ezdxf.DXFError, UnicodeDecodeError, or what recovery trips on
        raise ValueError(f"{file}: not a readable DXF ({exc})") from None
    entities = list(doc.modelspace().query("LWPOLYLINE POLYLINE SPLINE"))
    if layer is not None:
        entities = [e for e in entities if e.dxf.layer.casefold() == layer.casefold()]
    if not entities:
        where = f"on layer {layer!r}" if layer is not None else "in modelspace"
        layers = sorted(entry.dxf.name for entry in doc.layers)
        raise ValueError(f"{file}: no {_DXF_ENTITIES} {where} (layers: {', '.join(layers)})")
    entity = entities[0]
    kind = entity.dxftype()
    source = f"{file}#{entity.dxf.layer} ({kind})"
    if kind == "POLYLINE" and (entity.is_poly_face_mesh or entity.is_polygon_mesh):
        raise ValueError(f"{file}: the POLYLINE on layer {entity.dxf.layer!r} is a mesh")
    _check_dxf_size(file, entity)
    try:
        along, count, straight, first = _dxf_along(entity)
    except (ezdxf.DXFError, TypeError, ValueError, ZeroDivisionError, StopIteration) as exc:
        raise ValueError(
            f"{file}: cannot trace the {kind} on {entity.dxf.layer!r} ({exc})"
        ) from None
    flat = _flatten(file, along, count, straight) if count else first
    closed = bool(entity.closed if kind != "POLYLINE" else entity.is_closed)
    return flat, closed, source


def _check_dxf_size(file: str, entity: Any) -> None:
    """Refuse a polyline of more than MAX_CURVE_SEGMENTS vertices, a spline of more than
    MAX_CURVE_SEGMENTS control points or, given by fit points alone, of more than
    MAX_SPLINE_FIT_POINTS of them."""
    kind = entity.dxftype()
    what = f"the {kind} on layer {entity.dxf.layer!r} has {{count}}"
    curve = "more than the {limit} a curve may have"
    if kind == "SPLINE" and entity.control_point_count():
        count = entity.control_point_count()
        _too_many(
            file, count, MAX_CURVE_SEGMENTS, "MAX_CURVE_SEGMENTS", f"{what} control points, {curve}"
        )
    elif kind == "SPLINE":
        _too_many(
            file,
            entity.fit_point_count(),
            MAX_SPLINE_FIT_POINTS,
            "MAX_SPLINE_FIT_POINTS",
            f"{what} fit points, more than the {{limit}} a spline given by fit points alone "
            "may have",
        )
    else:
        count = len(entity) if kind == "LWPOLYLINE" else len(entity.vertices)
        _too_many(
            file, count, MAX_CURVE_SEGMENTS, "MAX_CURVE_SEGMENTS", f"{what} vertices, {curve}"
        )


def _dxf_along(entity: Any) -> tuple[Along, int, np.ndarray, np.ndarray]:
    """The entity as `_flatten` takes it (along, segments, which are straight) and its first
    point (1, 2): a spline's segments are its knot spans, evaluated on the spline itself; a
    polyline's are its lines and the arcs of its bulges, evaluated on their circles."""
    if entity.dxftype() == "SPLINE":
        tool = entity.construction_tool()
        knots = np.unique(np.asarray(tool.knots(), dtype=np.float64))
        if len(knots) < 2:
            raise ValueError("its knots span nothing")

        def on_spline(index: np.ndarray, t: np.ndarray) -> np.ndarray:
            at = knots[index] + t * (knots[index + 1] - knots[index])
            return np.array([(v.x, v.y) for v in tool.points(at)], dtype=np.float64)

        first = on_spline(np.zeros(1, dtype=np.int64), np.zeros(1))
        return on_spline, len(knots) - 1, np.zeros(len(knots) - 1, dtype=bool), first
    vertices = (
        entity.vertices_in_wcs() if entity.dxftype() == "LWPOLYLINE" else entity.points_in_wcs()
    )
    first = next(iter(vertices))
    parts = list(entity.virtual_entities())
    count = len(parts)
    ends = np.zeros((count, 2, 2))  # a line's start and end
    arc = np.zeros(count, dtype=bool)
    centre = np.zeros((count, 3))  # an arc's, in its OCS
    radius, angle, sweep = np.zeros(count), np.zeros(count), np.zeros(count)
    axes = np.zeros((count, 3, 3))  # an arc's OCS axes in the WCS, as rows
    at = (first.x, first.y)
    for k, part in enumerate(parts):
        if part.dxftype() == "ARC":
            start, end = part.start_point, part.end_point
            begin, stop = math.radians(part.dxf.start_angle), math.radians(part.dxf.end_angle)
            arc[k], centre[k], radius[k] = True, part.dxf.center.xyz, part.dxf.radius
            angle[k], sweep[k] = begin, (stop - begin) % math.tau
            ocs = part.ocs()
            axes[k] = [ocs.ux.xyz, ocs.uy.xyz, ocs.uz.xyz]
            # A DXF arc runs counter-clockwise: a clockwise bulge's is drawn from its end.
            if math.dist((end.x, end.y), at) < math.dist((start.x, start.y), at):
                start, end = end, start
                angle[k], sweep[k] = stop, -sweep[k]
        else:  # a LINE
            start, end = part.dxf.start, part.dxf.end
        ends[k] = [(start.x, start.y), (end.x, end.y)]
        at = (end.x, end.y)

    def on_parts(index: np.ndarray, t: np.ndarray) -> np.ndarray:
        line = ends[index, 0] + t[:, None] * (ends[index, 1] - ends[index, 0])
        turn = angle[index] + t * sweep[index]
        local = centre[index] + radius[index, None] * np.column_stack(
            [np.cos(turn), np.sin(turn), np.zeros(len(t))]
        )
        world = np.einsum("nk,nkj->nj", local, axes[index])[:, :2]
        return np.where(arc[index, None], world, line)

    return on_parts, count, ~arc, np.array([[first.x, first.y]])


_READERS: dict[str, Callable[[str, bytes, str | None], tuple[np.ndarray, bool, str]]] = {
    ".csv": _read_csv,
    ".dxf": _read_dxf,
    ".json": _read_json,
    ".svg": _read_svg,
}
