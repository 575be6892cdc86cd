"""The studio's editor, in a real browser (test_studio_page.py says how): a four-bar built by
clicks and taps, dragged, edited, undone and redone, a locking mechanism shown where it locks,
errors in words, and the files it writes and reads (JSON, SVG, a share link, fabrication SVG and
DXF in millimetres)."""

import json
import math
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import links_ray
from tests.support.drawings import dxf_parts, read_dxf
from tests.support.serving import FOUR_BAR, LOCKING_FOUR_BAR, Client
from tests.support.studio_page import STEPS, VIEWPORT, Studio, assert_assembled, simulate


def assert_same_mechanism(got: dict[str, Any], expected: dict[str, Any], atol: float) -> None:
    assert got["adjacency"] == expected["adjacency"]
    assert got["node_types"] == expected["node_types"]
    np.testing.assert_allclose(got["positions"], expected["positions"], rtol=0, atol=atol)


def test_four_bar_built_by_clicks_simulates_as_links_ray(studio: Studio) -> None:
    studio.build_four_bar()
    mechanism = studio.mechanism()
    # The click landed within a pixel of where it was aimed.
    assert_same_mechanism(mechanism, FOUR_BAR, atol=1.5 * studio.pixel())
    # The page shows exactly what the Python engine computes for what the page holds...
    np.testing.assert_array_equal(studio.trajectories(), simulate(mechanism))
    # ... which is the intended four-bar's motion, to within the click's rounding.
    np.testing.assert_allclose(studio.trajectories(), simulate(FOUR_BAR), atol=20 * studio.pixel())
    assert studio.text("dof").startswith("1 (2 x 2 moving joints - 3 links)")
    assert studio.text("solvable") == "yes"
    assert "4 joints, outside 8-20" in studio.text("rules")

    # The crank slider and play both move the drawn pose.
    studio.page.get_by_test_id("crank-slider").fill("50")
    assert studio.text("crank-value") == "90.0°"
    assert studio.js("() => window.studio.editor.pose()") == studio.trajectories()[:, 50].tolist()
    studio.click("play")
    first = int(studio.page.get_by_test_id("studio-canvas").get_attribute("data-step"))
    studio.wait(
        "(s) => +document.querySelector('[data-testid=studio-canvas]').dataset.step !== s", first
    )
    studio.click("play")


def test_dragging_resimulates_live_with_one_request_in_flight(studio: Studio) -> None:
    studio.build_four_bar()
    studio.click("tool-move")
    before = studio.mechanism()
    studio.requests.clear()
    studio.js("() => { window.studio.editor.latencies.length = 0; }")
    in_flight = [0, 0]  # now, most ever

    def track(request: Any, change: int) -> None:
        if request.url.endswith("/api/simulate"):
            in_flight[0] += change
            in_flight[1] = max(in_flight)

    studio.page.on("request", lambda r: track(r, 1))
    studio.page.on("requestfinished", lambda r: track(r, -1))
    studio.page.on("requestfailed", lambda r: track(r, -1))
    # Drag joint 3 along an arc in 60 mouse moves, as fast as the browser takes them.
    x, y = studio.editor_point(before["positions"][3])
    studio.page.mouse.move(x, y)
    studio.page.mouse.down()
    for k in range(1, 61):
        studio.page.mouse.move(x + 40 * math.sin(k / 20), y - 30 * (1 - math.cos(k / 20)))
    studio.page.mouse.up()
    studio.wait_idle()
    after = studio.mechanism()
    assert after["positions"][3] != before["positions"][3]
    assert after["positions"][:3] == before["positions"][:3]
    np.testing.assert_array_equal(studio.trajectories(), simulate(after))

    sent = [url for url in studio.requests if url == "/api/simulate"]
    latencies = studio.js("() => window.studio.latencies()")
    assert len(latencies) == len(sent)
    # Coalesced: one request in flight at a time, and never more requests than moves.
    assert in_flight == [0, 1]
    assert 2 <= len(sent) <= 60
    median = float(np.median(latencies))
    print(
        f"\n/api/simulate while dragging: {len(sent)} requests for 60 moves, round trip "
        f"median {median:.1f} ms, p90 {np.percentile(latencies, 90):.1f} ms, "
        f"max {max(latencies):.1f} ms"
    )
    assert "/api/simulate" in studio.text("latency")

    # The whole drag is one undo step.
    studio.click("undo")
    studio.wait_idle()
    assert studio.mechanism() == before
    np.testing.assert_array_equal(studio.trajectories(), simulate(before))
    studio.page.keyboard.press("Control+Shift+Z")
    studio.wait_idle()
    assert studio.mechanism() == after


def test_locking_mechanism_shows_where_and_at_which_angle(
    studio: Studio, tmp_path: Path, shots: Path
) -> None:
    with pytest.raises(links_ray.LockingError) as locked:
        simulate(LOCKING_FOUR_BAR)
    step, node = locked.value.step, locked.value.node
    studio.allow("status of 422")  # /api/simulate's answer for a locking mechanism
    studio.import_mechanism(tmp_path, LOCKING_FOUR_BAR, "locking.json")
    lock = studio.page.get_by_test_id("lock")
    assert lock.is_visible()
    angle = f"{360 * step / STEPS:.1f}°"
    assert f"crank angle {angle} (step {step} of {STEPS})" in lock.inner_text()
    assert f"joint {node}" in lock.inner_text()
    assert f"locks after {angle}" in studio.text("status")
    # The paths drawn stop where it locks and are real assemblies of the mechanism.
    partial = studio.trajectories()
    assert partial.shape == (4, step, 2)
    assert_assembled(LOCKING_FOUR_BAR, partial)
    assert studio.page.get_by_test_id("crank-slider").get_attribute("max") == str(step - 1)
    studio.click("fit")
    studio.shot("studio-locking.png", shots)


def test_edits_undo_redo_and_errors_in_words(studio: Studio) -> None:
    studio.allow("status of 400")  # the over-constrained and 2-DOF states below
    studio.build_four_bar()
    # Link joint 3 to joint 0: three known neighbours, so over-constrained (0 DOF).
    studio.click("tool-link")
    studio.click_world(FOUR_BAR["positions"][3])
    studio.click_world(FOUR_BAR["positions"][0])
    studio.wait_idle()
    assert studio.mechanism()["adjacency"][0][3] == 1
    assert studio.text("dof").startswith("0 (2 x 2 moving joints - 4 links)")
    assert studio.text("solvable").startswith("no: over-constrained")
    assert "cannot simulate: over-constrained" in studio.text("status")
    assert "(HTTP 400)" in studio.text("status")
    assert studio.trajectories() is None

    # Delete that link again; then refuse to delete the crank, in words.
    studio.click("tool-delete")
    a = np.array(studio.editor_point(FOUR_BAR["positions"][3]))
    b = np.array(studio.editor_point(FOUR_BAR["positions"][0]))
    studio.page.mouse.click(*(0.6 * a + 0.4 * b))
    studio.wait_idle()
    assert studio.mechanism()["adjacency"][0][3] == 0
    studio.click_world(FOUR_BAR["positions"][1])
    assert "cannot be deleted" in studio.text("hint")
    assert len(studio.mechanism()["node_types"]) == 4

    # Add a ground joint and delete joint 2: two degrees of freedom, not solvable.
    studio.click("tool-ground")
    studio.click_world([0.7, 0.3])
    studio.wait_idle()
    assert studio.mechanism()["node_types"] == [0, 2, 0, 1, 0]
    studio.click("tool-delete")
    studio.click_world(FOUR_BAR["positions"][2])
    studio.wait_idle()
    assert studio.mechanism()["node_types"] == [0, 2, 1, 0]
    assert studio.text("dof").startswith("2 ")
    assert "more than one degree of freedom" in studio.text("solvable")
    for _ in range(2):
        studio.click("undo")
    studio.wait_idle()
    assert_same_mechanism(studio.mechanism(), FOUR_BAR, atol=1.5 * studio.pixel())
    assert "every joint assembles" in studio.text("status")

    # A server that cannot be reached is said so, in the status and the banner.
    studio.allow("net::ERR_FAILED")
    studio.page.route("**/api/simulate", lambda route: route.abort())
    studio.click("redo")
    studio.wait("() => window.studio.editor.sim.version === window.studio.editor.version")
    assert "cannot reach the links-ray server" in studio.text("status")
    assert "Simulation failed" in studio.text("error")
    studio.page.unroute("**/api/simulate")


def test_touch_builds_and_drags_on_a_phone_sized_screen(browser: Any, client: Client) -> None:
    """Taps build the four-bar and a finger drags a joint (touch events through the browser's
    input pipeline, as a touch screen sends them), on a narrow one-column layout."""
    context = browser.new_context(viewport={"width": 412, "height": 915}, has_touch=True)
    try:
        studio = Studio(context.new_page(), f"http://127.0.0.1:{client.port}")
        studio.open()
        studio.start_blank()
        studio.click("tool-joint")
        for position in FOUR_BAR["positions"][1:]:
            studio.page.touchscreen.tap(*studio.editor_point(position))
        studio.wait_idle()
        assert_same_mechanism(studio.mechanism(), FOUR_BAR, atol=1.5 * studio.pixel())

        studio.click("tool-move")
        cdp = context.new_cdp_session(studio.page)
        x, y = studio.editor_point(FOUR_BAR["positions"][3])
        # A fingertip lands a little off the joint: touch gets a larger target than a mouse.
        touch = [("touchStart", x + 9, y + 9)]
        touch += [("touchMove", x + 9 + 2 * k, y + 9 + k) for k in range(1, 21)]
        for kind, tx, ty in [*touch, ("touchEnd", 0, 0)]:
            points = [] if kind == "touchEnd" else [{"x": tx, "y": ty, "id": 1}]
            cdp.send("Input.dispatchTouchEvent", {"type": kind, "touchPoints": points})
        studio.wait_idle()
        moved = studio.mechanism()
        expected = np.add(FOUR_BAR["positions"][3], np.array([40, -20]) * studio.pixel())
        np.testing.assert_allclose(moved["positions"][3], expected, atol=2 * studio.pixel())
        np.testing.assert_array_equal(studio.trajectories(), simulate(moved))
        assert studio.unexpected_errors() == []
    finally:
        context.close()


def test_export_import_svg_and_share_link(studio: Studio, tmp_path: Path, browser: Any) -> None:
    studio.build_four_bar()
    mechanism = studio.mechanism()
    with studio.page.expect_download() as download:
        studio.click("export-json")
    exported = json.loads(Path(download.value.path()).read_text())
    assert exported == mechanism
    assert set(exported) == {"adjacency", "node_types", "positions"}

    with studio.page.expect_download() as download:
        studio.click("export-svg")
    svg = ET.parse(download.value.path()).getroot()
    ns = {"svg": "http://www.w3.org/2000/svg"}
    assert svg.tag == "{http://www.w3.org/2000/svg}svg"
    assert len(svg.findall("svg:polygon[@class='path']", ns)) == 2  # joints 1 and 3 move
    assert len(svg.findall("svg:line[@class='link']", ns)) == 3
    assert len(svg.findall("svg:circle[@class='joint']", ns)) == 4

    studio.click("new")
    studio.wait_idle()
    assert len(studio.mechanism()["node_types"]) == 3
    (tmp_path / "four-bar.json").write_text(json.dumps(exported))
    studio.page.get_by_test_id("import-file").set_input_files(str(tmp_path / "four-bar.json"))
    studio.wait_idle()
    assert studio.mechanism() == mechanism

    # A file that is not a mechanism is refused in words; the mechanism stays.
    (tmp_path / "bad.json").write_text('{"adjacency": [[0]], "node_types": [0]}')
    studio.page.get_by_test_id("import-file").set_input_files(str(tmp_path / "bad.json"))
    studio.wait("() => !document.querySelector('[data-testid=error]').hidden")
    assert "Import failed: bad.json is not a mechanism" in studio.text("error")
    (tmp_path / "broken.json").write_text("{not json")
    studio.page.get_by_test_id("import-file").set_input_files(str(tmp_path / "broken.json"))
    studio.wait(
        "() => document.querySelector('[data-testid=error]').textContent.includes('broken')"
    )
    assert "broken.json is not valid JSON" in studio.text("error")
    assert studio.mechanism() == mechanism

    # The share link opens the same mechanism in a fresh tab.
    studio.click("share")
    url = studio.page.url
    assert "#mechanism=" in url
    other = Studio(browser.new_page(viewport=VIEWPORT), studio.base)
    try:
        other.open(url.removeprefix(studio.base))
        assert other.mechanism() == mechanism
        assert other.unexpected_errors() == []
    finally:
        other.page.close()


def test_export_for_fabrication_in_millimetres(studio: Studio, tmp_path: Path) -> None:
    """SVG and DXF downloads at the crank length typed, the selected joint's path in them."""
    studio.import_mechanism(tmp_path, FOUR_BAR, "four-bar.json")
    studio.click("tool-move")
    studio.click_world(FOUR_BAR["positions"][3])  # selects joint 3
    studio.wait("() => window.studio.editor.selected === 3")
    studio.page.get_by_test_id("crank-mm").fill("30")
    scale = 30 / 0.05
    truth = (simulate(FOUR_BAR)[3] - FOUR_BAR["positions"][0]) * scale
    joints = (np.array(FOUR_BAR["positions"]) - FOUR_BAR["positions"][0]) * scale

    with studio.page.expect_download() as download:
        studio.click("export-fab-svg")
    assert download.value.suggested_filename == "mechanism-4-joints-30mm.svg"
    svg = ET.parse(download.value.path()).getroot()
    ns = {"svg": "http://www.w3.org/2000/svg"}
    _, _, width, _ = map(float, svg.get("viewBox").split())
    assert svg.get("width") == f"{width!r}mm"  # one user unit is one millimetre
    lines = svg.findall(".//svg:line", ns)
    assert len(lines) == 3  # the four-bar's links
    for line in lines:
        i, j = map(int, line.get("data-joints").split())
        x1, y1, x2, y2 = (float(line.get(k)) for k in ("x1", "y1", "x2", "y2"))
        assert math.hypot(x2 - x1, y2 - y1) == pytest.approx(
            math.dist(joints[i], joints[j]), abs=1e-8
        )
    crank = svg.find(".//svg:line[@data-joints='0 1']", ns)
    assert float(crank.get("data-length-mm")) == pytest.approx(30)
    pivots = svg.findall(".//svg:g[@id='GROUND']/svg:circle", ns)
    centres = [[float(c.get("cx")), float(c.get("cy"))] for c in pivots]
    np.testing.assert_allclose(centres, joints[[0, 2]], atol=1e-8)
    polygon = svg.find(".//svg:polygon[@data-joint='3']", ns)
    points = np.array([p.split(",") for p in polygon.get("points").split()], dtype=float)
    np.testing.assert_allclose(points, truth, atol=1e-8)

    with studio.page.expect_download() as download:
        studio.click("export-dxf")
    assert download.value.suggested_filename == "mechanism-4-joints-30mm.dxf"
    doc = read_dxf(Path(download.value.path()).read_bytes())
    assert doc.header["$INSUNITS"] == 4  # millimetres
    parts = dxf_parts(doc)
    ends = [drawn for kind, _, drawn in parts if kind == "LINE"]
    lengths = sorted(math.hypot(x2 - x1, y2 - y1) for x1, y1, x2, y2 in ends)
    expected = sorted(math.dist(joints[i], joints[j]) for i, j in [(0, 1), (1, 3), (2, 3)])
    assert lengths == pytest.approx(expected, abs=1e-8)
    [(closed, vertices)] = [drawn for kind, _, drawn in parts if kind == "LWPOLYLINE"]
    assert closed
    np.testing.assert_allclose(vertices, truth, atol=1e-8)

    # A crank length the server refuses is said in words, and nothing is downloaded.
    studio.allow("400")
    studio.page.get_by_test_id("crank-mm").fill("-2")
    studio.click("export-dxf")
    studio.wait("() => !document.querySelector('[data-testid=error]').hidden")
    assert "Export failed: crank_mm must be more than 0" in studio.text("error")
