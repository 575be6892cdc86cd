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

Every file is bounded before its parser expands it (interop/curve_limits.py): an SVG
is scanned first (`interop.svg_curves`), a DXF's records are counted (`interop.dxf_curves`),
and the curve read has at most MAX_CURVE_SEGMENTS segments, flattened to a fixed budget of
points (`interop.outlines`). A file past a limit raises `interop.outlines.CurveFileTooLarge`.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import orjson

from links_ray.engine.inputs import (
    MAX_POINTS,
    MIN_POINTS,
    as_drawn_points,
    as_int,
    shown,
)
from links_ray.engine.kinematics.paths import even_along
from links_ray.interop.curve_limits import MAX_CURVE_FILE_BYTES
from links_ray.interop.dxf_curves import read_dxf
from links_ray.interop.outlines import CurveFileTooLarge, check_coordinates
from links_ray.interop.svg_curves import read_svg

__all__ = [
    "CURVE_FILE_TYPES",
    "DEFAULT_CURVE_POINTS",
    "Curve",
    "CurveFileTooLarge",  # what read_curve raises past a limit, a public name of this module
    "read_curve",
    "read_curve_text",
    "read_points",
]

#: Points a curve read from a file is sampled to by default: as dense as the bench's targets.
DEFAULT_CURVE_POINTS = 400
#: The extensions read, lower case.
CURVE_FILE_TYPES = (".csv", ".dxf", ".json", ".svg")

_TOO_LARGE = f"larger than {MAX_CURVE_FILE_BYTES:,} bytes, the most a curve file may be"


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
    return _parse_curve(name, curve_file_bytes(name, text), part, count)


def curve_file_bytes(name: str, text: str | bytes) -> bytes:
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
    check_coordinates(file, outline)
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


_READERS: dict[str, Callable[[str, bytes, str | None], tuple[np.ndarray, bool, str]]] = {
    ".csv": _read_csv,
    ".dxf": read_dxf,
    ".json": _read_json,
    ".svg": read_svg,
}
