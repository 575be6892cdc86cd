"""Curves from drawings: POST /api/curve reads an SVG, CSV or DXF file as `--curve FILE#id` does,
and the studio's Open curve… draws the file's curve (in a real browser: test_studio_page.py says
how)."""

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.support.needs import need_module
from tests.support.serving import Client
from tests.support.studio_page import Studio

#: A drawing of two shapes: a closed bean (`bean`, cubic Béziers, moved and scaled by its
#: group) and an open stroke (`wing`, a quadratic Bézier and a line), in millimetres.
DRAWING = """<svg xmlns="http://www.w3.org/2000/svg" width="120mm" height="80mm"
  viewBox="0 0 120 80">
  <g transform="translate(10 5) scale(1.5)">
    <path id="bean" d="M 10 20 C 10 0, 40 0, 40 20 C 40 30, 30 25, 25 30 C 15 40, 10 35, 10 20 Z"/>
  </g>
  <path id="wing" d="M 60 60 Q 80 10 100 50 L 110 30"/>
</svg>"""
#: A circle of radius 5 about (1, 2) as two half-circle bulges (bulge 1 = 180 degrees).
CIRCLE_CENTRE, CIRCLE_RADIUS = (1.0, 2.0), 5.0


def dxf_text(tmp_path: Path) -> Path:
    ezdxf = need_module("ezdxf", "pip install ezdxf")
    doc = ezdxf.new()
    doc.layers.add("ROUND")
    doc.modelspace().add_line((0, 0), (9, 9))  # not a curve
    doc.modelspace().add_lwpolyline(
        [(-4, 2, 0, 0, 1), (6, 2, 0, 0, 1)],
        format="xyseb",
        close=True,
        dxfattribs={"layer": "ROUND"},
    )
    path = tmp_path / "part.dxf"
    doc.saveas(path)
    return path


def test_curve_route_reads_a_drawing_as_the_cli_does(client: Client, tmp_path: Path) -> None:
    """POST /api/curve answers the points `read_curve` (what `--curve FILE#id` reads) finds in
    the same file, sent as text; a file it cannot read is a 400 naming the file's problem."""
    from links_ray.interop.curve_files import read_curve, read_curve_text
    from links_ray.interop.curve_limits import MAX_CURVE_FILE_BYTES
    from links_ray.serve.http.limits import MAX_BODY_BYTES

    svg = tmp_path / "drawing.svg"
    svg.write_text(DRAWING)
    csv = tmp_path / "stroke.csv"
    csv.write_text("x,y\n0,0\n3,1\n3.5,4\n1,6.25\n")
    dxf = dxf_text(tmp_path)
    for path, part, closed in [
        (svg, "wing", False),
        (svg, "bean", True),
        (svg, None, True),  # the first shape
        (csv, None, False),
        (dxf, "ROUND", True),
        (dxf, None, True),
    ]:
        body = {"name": path.name, "text": path.read_text(), **({"id": part} if part else {})}
        status, data = client.post("/api/curve", body)
        assert status == 200, (path.name, part, data)
        truth = read_curve(f"{path}#{part}" if part else path)
        assert set(data) == {"points", "closed"} and data["closed"] is truth.closed is closed
        np.testing.assert_array_equal(data["points"], truth.points)  # JSON keeps float64 whole
    # Independently of the reader: the DXF's circle is on its radius.
    _, data = client.post("/api/curve", {"name": "c.dxf", "text": dxf.read_text(), "id": "ROUND"})
    radii = np.linalg.norm(np.subtract(data["points"], CIRCLE_CENTRE), axis=1)
    np.testing.assert_allclose(radii, CIRCLE_RADIUS, rtol=1e-6)

    def refused(body: Any, expected: int, words: str) -> None:
        status, headers, data = client.request("POST", "/api/curve", body)
        assert (status, set(data)) == (expected, {"error"}), data
        assert headers["content-type"].startswith("application/json")
        assert words in data["error"], data["error"]

    text = svg.read_text()
    refused({"name": "d.svg", "text": "<svg><path d="}, 400, "d.svg: not a readable SVG")
    refused({"name": "d.svg", "text": text, "id": "tail"}, 400, "no element with id 'tail'")
    refused({"name": "d.txt", "text": text}, 400, "d.txt: unknown extension '.txt'")
    refused({"name": "p.csv", "text": "1,2\nthree,4\n"}, 400, "p.csv line 2: expected two numbers")
    refused({"name": "p.csv", "text": "1,2\n3,4\n", "id": "a"}, 400, "there is no #a")
    refused({"name": "d.svg", "text": text, "bogus": 1}, 400, "unknown field 'bogus'")
    refused({"name": "d.svg", "text": 5}, 400, "text must be a string, got a number")
    refused({"name": "d.svg", "text": text, "id": ""}, 400, "id must be 1 to")
    refused({"text": text}, 400, "missing field 'name'")
    refused(b"[1]", 400, "must be a JSON object")
    big = {"name": "big.csv", "text": "0,0\n" * (MAX_BODY_BYTES // 4)}
    refused(big, 413, f"the body is over the limit of {MAX_BODY_BYTES} bytes")
    # A file over the curve files' own limit is refused before it is parsed (in Python: the
    # body's limit, smaller, refuses it first over HTTP).
    with pytest.raises(ValueError, match=r"big\.csv: larger than"):
        read_curve_text("big.csv", b"0" * (MAX_CURVE_FILE_BYTES + 1))

    _, spec = client.get("/openapi.json")
    operation = spec["paths"]["/api/curve"]["post"]
    body = operation["requestBody"]["content"]["application/json"]["schema"]
    assert set(spec["components"]["schemas"][body["$ref"].rpartition("/")[2]]["properties"]) == {
        "name",
        "text",
        "id",
    }
    assert {"400", "413", "415"} <= set(operation["responses"])


def test_open_curve_draws_the_files_curve(studio: Studio, tmp_path: Path) -> None:
    """Open curve… with an element id: the studio holds the points `read_curve` reads from the
    same file (the server's one parser), shows them whole, and takes an open stroke as part of
    a curve; a file it cannot read is said in words, the curve kept."""
    from links_ray.interop.curve_files import read_curve

    svg = tmp_path / "drawing.svg"
    svg.write_text(DRAWING)
    studio.page.get_by_test_id("curve-id").fill("wing")
    studio.page.get_by_test_id("curve-file").set_input_files(str(svg))
    studio.wait("() => window.studio.retriever.points.length > 0 && window.studio.idle()")
    truth = read_curve(f"{svg}#wing")
    state = studio.js(
        """() => {
          const r = window.studio.retriever;
          return {points: r.points, screen: r.points.map((p) => r.view.toScreen(p)),
                  width: r.view.width, height: r.view.height,
                  partial: document.querySelector('[data-testid=partial]').checked};
        }"""
    )
    np.testing.assert_array_equal(state["points"], truth.points)
    assert state["partial"] is True  # an open stroke is matched as part of a path
    # Drawn in view, and large: the curve fills most of the canvas, whatever its units.
    screen = np.array(state["screen"])
    assert screen.min() >= 0 and np.all(screen.max(0) <= [state["width"], state["height"]])
    assert np.ptp(screen, axis=0).max() > 0.7 * min(state["width"], state["height"])
    assert "an open curve" in studio.text("retrieve-status")

    # The closed bean: partial off again.
    studio.page.get_by_test_id("curve-id").fill("bean")
    studio.page.get_by_test_id("curve-file").set_input_files(str(svg))
    studio.wait(
        "() => window.studio.idle() && !document.querySelector('[data-testid=partial]').checked"
    )
    bean = read_curve(f"{svg}#bean")
    np.testing.assert_array_equal(studio.js("() => window.studio.retriever.points"), bean.points)

    # A missing id: the server's words in the banner, the bean still drawn.
    studio.allow("status of 400")
    studio.page.get_by_test_id("curve-id").fill("tail")
    studio.page.get_by_test_id("curve-file").set_input_files(str(svg))
    studio.wait("() => !document.querySelector('[data-testid=error]').hidden")
    assert "Cannot open the curve: drawing.svg: no element with id 'tail'" in studio.text("error")
    np.testing.assert_array_equal(studio.js("() => window.studio.retriever.points"), bean.points)
