"""Small drawing files that cost their reader far more than their size: the worst inputs the
curve readers are bounded against, for `links bench hostile` and the tests.

Each is a (file name, text) pair that `/api/curve` and `read_curve_text` take. They are
written here, from their parameters, so that the bench and the tests send the same bytes.
"""

from __future__ import annotations

import io

import numpy as np

#: A path any reader draws: three points.
_PATH = '<path d="M0 0L1 1L2 0"/>'
_SVG = '<svg xmlns="http://www.w3.org/2000/svg">'


def style_without_brace(chars: int) -> tuple[str, str]:
    """An SVG whose `<style>` holds `chars` characters and no `{`: a CSS rule that never
    opens, which a regular expression that backtracks reads in time quadratic in its length."""
    return "style.svg", f"{_SVG}<style>{'a' * chars}</style>{_PATH}</svg>"


def nested_uses(levels: int, fan: int = 10) -> tuple[str, str]:
    """An SVG of `levels` groups, each holding `fan` `<use>` of the group below: about
    fan^levels paths once every reference is inlined, from about 200 bytes a level."""
    groups = [f'<g id="u0">{_PATH}</g>']
    for level in range(1, levels + 1):
        uses = f'<use href="#u{level - 1}"/>' * fan
        groups.append(f'<g id="u{level}">{uses}</g>')
    return "uses.svg", f'{_SVG}<defs>{"".join(groups)}</defs><use href="#u{levels}"/></svg>'


def alternating_bulges(vertices: int) -> tuple[str, str]:
    """A DXF LWPOLYLINE of `vertices` vertices 1 apart on a line, each segment a half circle
    (bulge 1), bulging to either side in turn: a chain of arcs whose flattening to a fixed
    sag of the drawing's size takes thousands of points an arc."""
    import ezdxf

    doc = ezdxf.new("R2010")
    points = [(float(i), 0.0, 0.0, 0.0, 1.0 if i % 2 else -1.0) for i in range(vertices)]
    doc.modelspace().add_lwpolyline(points, format="xyseb")
    return "bulges.dxf", _dxf_text(doc)


def random_spline(fit_points: int, seed: int = 0) -> tuple[str, str]:
    """A DXF SPLINE through `fit_points` random points in the unit square."""
    import ezdxf

    doc = ezdxf.new("R2010")
    rng = np.random.default_rng(seed)
    doc.modelspace().add_spline(rng.random((fit_points, 2)).tolist())
    return "spline.dxf", _dxf_text(doc)


def _dxf_text(doc: object) -> str:
    stream = io.StringIO()
    doc.write(stream)  # type: ignore[attr-defined]
    return stream.getvalue()


def hostile_drawings() -> dict[str, tuple[str, str]]:
    """The drawings `links bench hostile` sends, by what they are, at the sizes that once
    froze or exhausted a server: the longest reads in seconds to hours, the largest
    expansions in gigabytes."""
    return {
        "style 40,000 chars": style_without_brace(40_000),
        "style 300,000 chars": style_without_brace(300_000),
        "uses 5 levels": nested_uses(5),
        "uses 6 levels": nested_uses(6),
        "bulges 1,000 vertices": alternating_bulges(1_000),
        "spline 1,000 fit points": random_spline(1_000),
    }
