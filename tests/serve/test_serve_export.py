"""POST /api/export over real HTTP: a mechanism's fabrication files (SVG, DXF, parts table) as
attachments, as the engine draws them, their defaults and refusals (the `client` fixture's app)."""

import xml.etree.ElementTree as ET

import numpy as np
import pytest

import links_ray
from links_ray.engine.fabrication.drawings import fabrication
from links_ray.interop.drawings import dxf_drawing, svg_drawing
from tests.support.drawings import dxf_parts, read_dxf
from tests.support.serving import FOUR_BAR, LOCKING_FOUR_BAR, Client, check_error


@pytest.mark.parametrize(
    ("chosen", "media", "suffix"),
    [
        ("svg", "image/svg+xml", "svg"),
        ("dxf", "image/vnd.dxf", "dxf"),
        ("table", "text/plain", "txt"),
    ],
)
def test_export_answers_the_file_as_an_attachment(
    client: Client, chosen: str, media: str, suffix: str
) -> None:
    body = {**FOUR_BAR, "format": chosen, "crank_mm": 12.5, "path_joint": 3}
    status, headers, text = client.request("POST", "/api/export", body)
    assert status == 200, text
    assert headers["content-type"].startswith(media)
    assert headers["content-disposition"] == (
        f'attachment; filename="mechanism-4-joints-12.5mm.{suffix}"'
    )
    drawing = fabrication(**FOUR_BAR, crank_mm=12.5, path_joint=3)
    if chosen == "dxf":  # each file has its own time stamps and GUIDs: the same parts drawn
        written = read_dxf(text)
        assert written.header["$INSUNITS"] == 4
        assert dxf_parts(written) == dxf_parts(read_dxf(dxf_drawing(drawing)))
        assert [kind for kind, _, _ in dxf_parts(written)].count("LWPOLYLINE") == 1  # the path
    else:
        assert text == {"svg": svg_drawing, "table": type(drawing).table_text}[chosen](drawing)
    if chosen == "svg":  # at scale: the crank's line is 12.5 mm long in 1 mm user units
        crank = ET.fromstring(text).find(".//{http://www.w3.org/2000/svg}line[@data-joints='0 1']")
        x1, y1, x2, y2 = (float(crank.get(k)) for k in ("x1", "y1", "x2", "y2"))
        assert np.hypot(x2 - x1, y2 - y1) == pytest.approx(12.5, abs=1e-8)


def test_export_defaults_and_refusals(client: Client) -> None:
    status, headers, text = client.request("POST", "/api/export", FOUR_BAR)
    assert status == 200 and headers["content-type"].startswith("image/svg+xml")
    assert text == svg_drawing(fabrication(**FOUR_BAR, crank_mm=20))  # SVG, crank 20 mm, no path
    # A locking mechanism draws, but its path does not: 422 with where it locks.
    assert client.request("POST", "/api/export", LOCKING_FOUR_BAR)[0] == 200
    status, data = client.post("/api/export", {**LOCKING_FOUR_BAR, "path_joint": 3})
    with pytest.raises(links_ray.LockingError) as locked:
        links_ray.simulate(**LOCKING_FOUR_BAR)
    assert status == 422
    assert data == {
        "error": f"{locked.value}: it has no full path to draw",
        "step": locked.value.step,
        "node": locked.value.node,
    }
    refused = [
        ({"format": "pdf"}, 400, "format must be one of svg, dxf, table, got a string"),
        ({"format": 1}, 400, "format must be one of svg, dxf, table, got a number"),
        ({"crank_mm": 0}, 400, "crank_mm must be more than 0 and at most 100000 mm, got 0"),
        ({"crank_mm": -3}, 400, "crank_mm must be more than 0"),
        ({"crank_mm": "20"}, 400, "crank_mm must be a number of millimetres, got '20'"),
        ({"crank_mm": True}, 400, "crank_mm must be a number of millimetres, got True"),
        ({"path_joint": 2}, 400, "path_joint 2 is fixed: it traces no path"),
        ({"path_joint": 9}, 400, "path_joint must be from 0 to 3, got 9"),
        ({"path_joint": "3"}, 400, "path_joint must be an integer from 0 to 3, got '3'"),
        ({"node_types": [0, 1, 0, 1]}, 400, "joint 1 must be the actuated joint"),
        ({"positions": [[0, 0], [0, 0], [1, 0], [1, 1]]}, 400, "the crank has zero length"),
    ]
    for change, expected, words in refused:
        status, headers, data = client.request("POST", "/api/export", {**FOUR_BAR, **change})
        check_error(status, headers, data, expected, words)
    big = {
        "adjacency": np.eye(101, k=1, dtype=int).tolist(),
        "node_types": [0] * 101,
        "positions": [[0, 0]] * 101,
    }
    status, headers, data = client.request("POST", "/api/export", big)
    check_error(status, headers, data, 413, "at most 100 joints per request, got 101")
    status, headers, data = client.request("POST", "/api/export", {"format": "svg"})
    check_error(status, headers, data, 400, "missing field 'adjacency'")
