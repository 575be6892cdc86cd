"""Curves read from DXF files: an LWPOLYLINE (the arcs of its bulges included), POLYLINE or
SPLINE in modelspace, its records counted before ezdxf loads the file.

ezdxf is imported only when a DXF is read.
"""

from __future__ import annotations

import io
import math
import re
from typing import Any

import numpy as np

from links_ray.interop.curve_limits import (
    MAX_CURVE_SEGMENTS,
    MAX_DXF_ENTITIES,
    MAX_SPLINE_FIT_POINTS,
)
from links_ray.interop.outlines import Along, flatten, too_many

DXF_ENTITIES = "LWPOLYLINE, POLYLINE or SPLINE"

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


def read_dxf(file: str, data: bytes, layer: str | None) -> tuple[np.ndarray, bool, str]:
    """The outline of the first curve entity on `layer` (else in modelspace) in the DXF `data`,
    whether it is closed, and what was read; ValueError naming the file and problem."""
    import ezdxf
    from ezdxf import recover

    too_many(
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
        raise ValueError(f"{file}: no {DXF_ENTITIES} {where} (layers: {', '.join(layers)})")
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
    flat = flatten(file, along, count, straight) if count else first
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
        too_many(
            file, count, MAX_CURVE_SEGMENTS, "MAX_CURVE_SEGMENTS", f"{what} control points, {curve}"
        )
    elif kind == "SPLINE":
        too_many(
            file,
            entity.fit_point_count(),
            MAX_SPLINE_FIT_POINTS,
            "MAX_SPLINE_FIT_POINTS",
            f"{what} fit points, more than the {{limit}} a spline given by fit points alone "
            "may have",
        )
    else:
        count = len(entity) if kind == "LWPOLYLINE" else len(entity.vertices)
        too_many(file, count, MAX_CURVE_SEGMENTS, "MAX_CURVE_SEGMENTS", f"{what} vertices, {curve}")


def _dxf_along(entity: Any) -> tuple[Along, int, np.ndarray, np.ndarray]:
    """The entity as `flatten` takes it (along, segments, which are straight) and its first
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
