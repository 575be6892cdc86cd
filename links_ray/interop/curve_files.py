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

svgelements and ezdxf are imported only when an SVG or a DXF file is read.
"""

from __future__ import annotations

import io
import json
import math
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from links_ray.engine.inputs import (
    MAX_CURVE_FILE_BYTES,
    MAX_POINTS,
    MIN_POINTS,
    as_drawn_points,
    as_int,
)
from links_ray.engine.paths import even_along

__all__ = [
    "CURVE_FILE_TYPES",
    "DEFAULT_CURVE_POINTS",
    "Curve",
    "read_curve",
    "read_curve_text",
    "read_points",
]

#: Points a curve read from a file is sampled to by default: as dense as the bench's targets.
DEFAULT_CURVE_POINTS = 400
#: Points a drawing's curves (Béziers, arcs, splines) are flattened to before the even
#: resampling, at the least: a circle's chords then sag about 1e-8 of its radius.
FLAT_POINTS = 20_000
#: The sag a DXF entity is flattened to, relative to its extent (about FLAT_POINTS on a circle).
DXF_SAG = 1e-8
#: The extensions read, lower case.
CURVE_FILE_TYPES = (".csv", ".dxf", ".json", ".svg")

_TOO_LARGE = f"larger than {MAX_CURVE_FILE_BYTES:,} bytes, the most a curve file may be"
_SVG_SHAPES = "path, polyline, polygon, rect, circle, ellipse or line"
_DXF_ENTITIES = "LWPOLYLINE, POLYLINE or SPLINE"


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
    file and the problem: an unknown extension, a file unreadable, malformed or larger than
    MAX_CURVE_FILE_BYTES, no such element or layer, a single point."""
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
    data = text.encode("utf-8") if isinstance(text, str) else text
    if len(data) > MAX_CURVE_FILE_BYTES:
        raise ValueError(f"{name}: {_TOO_LARGE}")
    return _parse_curve(name, data, part, count)


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
    if not np.all(np.isfinite(outline)):
        raise ValueError(f"{file}: coordinates must be finite numbers")
    if len(outline) == 0 or np.all(outline == outline[0]):
        raise ValueError(f"{file}: a single point, there is no curve")
    try:
        resampled = as_drawn_points(even_along(outline, count, closed), "the curve's points")
    except ValueError as exc:
        raise ValueError(f"{file}: {exc}") from None
    return Curve(resampled, closed, source)


def read_points(path: str | os.PathLike[str]) -> object:
    """The points of a JSON file holding [[x, y], ...] or {"points": [[x, y], ...]}, as they
    are (the caller validates them); ValueError naming the file if it cannot be read."""
    label = f"cannot read points from {os.fspath(path)}"
    try:
        value = json.loads(_read_bytes(os.fspath(path), label))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
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
    too_large = f"{label}: {_TOO_LARGE}"
    try:
        if os.stat(file).st_size > MAX_CURVE_FILE_BYTES:
            raise ValueError(too_large)
        with open(file, "rb") as stream:
            data = stream.read(MAX_CURVE_FILE_BYTES + 1)  # a file growing meanwhile
    except OSError as exc:
        raise ValueError(f"{label}: {exc.strerror or exc}") from None
    if len(data) > MAX_CURVE_FILE_BYTES:
        raise ValueError(too_large)
    return data


def _as_outline(value: object) -> np.ndarray | None:
    """`value` as an (N, 2) float64 array, or None if it is not number pairs."""
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return None
    return array if array.ndim == 2 and array.shape[1] == 2 else None


def _repeats_first(outline: np.ndarray) -> bool:
    return len(outline) > 2 and bool(np.array_equal(outline[0], outline[-1]))


# -- JSON and CSV -----------------------------------------------------------------------------


def _json_points(value: object) -> object:
    return value["points"] if isinstance(value, dict) and "points" in value else value


def _read_json(file: str, data: bytes, part: str | None) -> tuple[np.ndarray, bool, str]:
    try:
        value = json.loads(data)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
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
            raise ValueError(f"{file} line {number}: expected two numbers, got {line.strip()!r}")
        first = False
    outline = np.array(rows, dtype=np.float64).reshape(-1, 2)
    return outline, _repeats_first(outline), file


def _number(field: str) -> float | None:
    try:
        return float(field)
    except ValueError:
        return None


# -- SVG --------------------------------------------------------------------------------------


def _read_svg(file: str, data: bytes, part: str | None) -> tuple[np.ndarray, bool, str]:
    import svgelements as se

    try:
        svg = se.SVG.parse(io.BytesIO(data), reify=True)
        elements = list(svg.elements())
    except Exception as exc:  # an XML error, or whatever the parser trips on in a bad file
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
    closed = isinstance(segments[-1], se.Close)
    outline = _flatten([lambda t, s=s: np.asarray(s.npoint(t)) for s in segments])
    return outline * [1.0, -1.0], closed, f"{file}{name}"


def _flatten(segments: list[Callable[[np.ndarray], np.ndarray]]) -> np.ndarray:
    """Segments (each a function of t in [0, 1]) as one polyline of at least FLAT_POINTS
    points, shared among them by length."""
    coarse = np.linspace(0.0, 1.0, 17)
    lengths = [
        np.linalg.norm(np.diff(segment(coarse), axis=0), axis=1).sum() for segment in segments
    ]
    total = sum(lengths) or 1.0
    pieces = [segments[0](np.zeros(1))]
    for segment, length in zip(segments, lengths, strict=True):
        steps = max(2, math.ceil(FLAT_POINTS * length / total))
        pieces.append(segment(np.linspace(0.0, 1.0, steps + 1)[1:]))
    return np.concatenate(pieces).astype(np.float64)


# -- DXF --------------------------------------------------------------------------------------


def _read_dxf(file: str, data: bytes, layer: str | None) -> tuple[np.ndarray, bool, str]:
    import ezdxf
    from ezdxf import path as dxf_path
    from ezdxf import recover

    try:
        doc, _ = recover.read(io.BytesIO(data))
    except (ezdxf.DXFError, UnicodeDecodeError, ValueError) as exc:
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
    try:
        flat = _trace_dxf(entity, dxf_path.make_path(entity))
    except (ezdxf.DXFError, TypeError, ValueError, ZeroDivisionError) as exc:
        raise ValueError(
            f"{file}: cannot trace the {kind} on {entity.dxf.layer!r} ({exc})"
        ) from None
    closed = bool(entity.closed if kind != "POLYLINE" else entity.is_closed)
    return np.array(flat, dtype=np.float64).reshape(-1, 2), closed, source


def _trace_dxf(entity: object, shape: object) -> np.ndarray:
    """The entity as a polyline within DXF_SAG of its extent: a spline evaluated on itself, a
    polyline's arcs on their circles (ezdxf's paths hold arcs as Béziers, 3e-4 off a circle)."""
    vertices = np.array([(v.x, v.y) for v in shape.control_vertices()], dtype=np.float64)
    sag = max(float(np.ptp(vertices, axis=0).max()) * DXF_SAG if len(vertices) else 0.0, 1e-12)
    if entity.dxftype() == "SPLINE":
        return np.array([(v.x, v.y) for v in entity.flattening(sag)], dtype=np.float64)
    pieces = [np.array([[shape.start.x, shape.start.y]])]
    for part in entity.virtual_entities():
        if part.dxftype() == "ARC":
            piece = np.array([(v.x, v.y) for v in part.flattening(sag)], dtype=np.float64)
        else:  # a LINE
            piece = np.array(
                [[part.dxf.start.x, part.dxf.start.y], [part.dxf.end.x, part.dxf.end.y]]
            )
        # A DXF arc runs counter-clockwise: a clockwise bulge's is drawn from its end.
        end = pieces[-1][-1]
        if np.linalg.norm(piece[-1] - end) < np.linalg.norm(piece[0] - end):
            piece = piece[::-1]
        pieces.append(piece[1:])
    return np.concatenate(pieces)


_READERS: dict[str, Callable[[str, bytes, str | None], tuple[np.ndarray, bool, str]]] = {
    ".csv": _read_csv,
    ".dxf": _read_dxf,
    ".json": _read_json,
    ".svg": _read_svg,
}
