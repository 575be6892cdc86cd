"""Reading back the fabrication DXF with ezdxf, a reader independent of the writer's code."""

from __future__ import annotations

import io

from ezdxf import recover
from ezdxf.document import Drawing


def read_dxf(data: str | bytes) -> Drawing:
    """The DXF document in `data` (text is encoded as UTF-8, as R2007 and later files are),
    read by ezdxf's recovering reader, which must have had nothing to recover from."""
    raw = data.encode("utf-8") if isinstance(data, str) else data
    doc, recovered = recover.read(io.BytesIO(raw))
    assert (recovered.errors, recovered.fixes) == ([], [])
    return doc


def dxf_parts(doc: Drawing) -> list[tuple]:
    """Each modelspace entity as (type, layer, what it draws), in file order: a LINE's ends, a
    CIRCLE's centre and radius, a TEXT's string, insertion point and height, an LWPOLYLINE's
    closed flag and vertices."""
    parts = []
    for entity in doc.modelspace():
        kind, dxf = entity.dxftype(), entity.dxf
        if kind == "LINE":
            drawn: tuple = (dxf.start.x, dxf.start.y, dxf.end.x, dxf.end.y)
        elif kind == "CIRCLE":
            drawn = (dxf.center.x, dxf.center.y, dxf.radius)
        elif kind == "TEXT":
            drawn = (dxf.text, dxf.insert.x, dxf.insert.y, dxf.height)
        elif kind == "LWPOLYLINE":
            drawn = (entity.closed, tuple(entity.get_points("xy")))
        else:
            raise AssertionError(f"an entity the drawing does not write: {kind}")
        parts.append((kind, dxf.layer, drawn))
    return parts
