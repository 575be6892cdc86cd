"""Limits on the drawing files a target curve is read from (SVG, DXF, CSV, JSON), and on the
reader processes that read them (`interop.curve_worker`): each bounds what a hostile file can
make a parser spend. docs/reference/contract.md, Limits, lists them.
"""

from __future__ import annotations

#: Largest drawing a target curve is read from (SVG, DXF, CSV, JSON), in bytes: refused before
#: it is parsed, since a parser holds the whole document, several times its size, in memory.
MAX_CURVE_FILE_BYTES = 32 * 1024 * 1024

#: The most segments (an SVG path's), vertices (a DXF polyline's) or control points (a DXF
#: spline's) the curve read from a drawing may have: each costs Python work to flatten.
MAX_CURVE_SEGMENTS = 10_000
#: The most fit points of a DXF spline given by them alone: ezdxf finds its control points by
#: solving a dense system of that many equations.
MAX_SPLINE_FIT_POINTS = 1_000
#: The most entities a DXF file may hold, counting every record ezdxf makes an object of (a
#: POLYLINE's every VERTEX, table entries, objects): about 60 us and 1 KB apiece.
MAX_DXF_ENTITIES = 20_000
#: The most elements an SVG may hold, each `<use>` counted with the copy it makes of what it
#: refers to: svgelements makes every copy, about 100 us apiece.
MAX_SVG_ELEMENTS = 10_000
#: The deepest an SVG's elements may nest, `<use>` copies included.
MAX_SVG_DEPTH = 100
#: The most numbers (and path commands) in the path data and points of an SVG's shapes,
#: `<use>` copies counted: svgelements makes an object of each segment, about 15 us apiece.
MAX_SVG_NUMBERS = 100_000
#: The most transform functions svgelements may apply to an SVG's elements: each element
#: applies its own and all its ancestors' (`<use>` copies counted), about 20 us apiece.
MAX_SVG_TRANSFORMS = 50_000
#: The longest attribute an SVG element may have, but for path data and points (what
#: svgelements parses of an element is read again by every element below it).
MAX_SVG_ATTRIBUTE_CHARS = 1000
#: Seconds a reader process is given for one file (`interop.curve_worker`) before it is killed.
CURVE_READ_SECONDS = 5.0
#: The address space a reader process may take, its libraries' (about 350 MiB) included.
CURVE_READER_MEMORY_BYTES = 1024 * 1024 * 1024
#: Reader processes that read files at once, and the seconds a file waits for one of them.
CURVE_READERS = 2
CURVE_READER_WAIT_S = 2.0
#: The niceness a reader process runs at (Linux), whatever its caller's: below a server's
#: threads, its retrievals' too (`serve.http.admission.RETRIEVAL_NICENESS`), since a file may keep
#: a reader busy for CURVE_READ_SECONDS; above Ray's workers (15).
CURVE_READER_NICENESS = 10
