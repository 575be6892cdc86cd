"""The web studio, in a real browser against the real Serve app.

Debian's Chromium (`/usr/bin/chromium`, or LINKS_CHROMIUM) is driven by Playwright with real
mouse events on the page the `client` fixture serves (a 300-mechanism dataset, see
support/datasets.py).
Numbers the page shows are read from `window.studio` and checked against `links_ray` in Python.

Screenshots go to pytest's temporary folder, or to the folder LINKS_STUDIO_SCREENSHOTS names:
`LINKS_STUDIO_SCREENSHOTS=docs python -m pytest -q tests/serve/test_studio.py` refreshes the
README's.
"""

import json
import math
import time
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import links_ray
from links_ray.engine.inputs import MAX_K, MAX_TRANSMISSION_DEG
from links_ray.engine.kinematics.mechanism import analyze_topology
from links_ray.serve.http.limits import request_limits
from tests.support.drawings import dxf_parts, read_dxf
from tests.support.needs import need_module
from tests.support.serving import FOUR_BAR, LOCKING_FOUR_BAR, Client
from tests.support.studio_page import VIEWPORT, Studio, draw

STEPS = 200


# -- the studio page ----------------------------------------------------------------------------


def assert_same_mechanism(got: dict[str, Any], expected: dict[str, Any], atol: float) -> None:
    assert got["adjacency"] == expected["adjacency"]
    assert got["node_types"] == expected["node_types"]
    np.testing.assert_allclose(got["positions"], expected["positions"], rtol=0, atol=atol)


def simulate(mechanism: dict[str, Any]) -> np.ndarray:
    return links_ray.simulate(
        mechanism["adjacency"], mechanism["node_types"], mechanism["positions"], STEPS
    )


# -- serving the page ---------------------------------------------------------------------------


def test_page_and_files_are_served_from_the_package(client: Client) -> None:
    status, headers, html = client.request("GET", "/")
    assert status == 200 and headers["content-type"].startswith("text/html")
    assert "default-src 'self'" in headers["content-security-policy"]
    for testid in ("studio-canvas", "draw-canvas", "retrieve-button", "error"):
        assert f'data-testid="{testid}"' in html
    for name, kind in [
        ("studio.js", "text/javascript"),
        ("editor.js", "text/javascript"),
        ("studio.css", "text/css"),
    ]:
        status, headers, body = client.request("GET", f"/studio/{name}")
        assert status == 200 and headers["content-type"].startswith(kind), (name, headers)
        assert headers["x-content-type-options"] == "nosniff"
        assert body == (Path(links_ray.__file__).parent / "serve" / "studio" / name).read_text()
    for name in ("missing.js", "..%2Fapp.py", "index.py"):
        status, headers, data = client.request("GET", f"/studio/{name}")
        assert status == 404 and headers["content-type"] == "application/json"
        assert data["error"]


def test_analyze_route_reports_the_engines_verdicts(client: Client) -> None:
    status, data = client.post(
        "/api/analyze", {k: FOUR_BAR[k] for k in FOUR_BAR if k != "positions"}
    )
    assert status == 200, data
    assert (data["dof"], data["moving"], data["links"], data["solvable"]) == (1, 2, 3, True)
    order = analyze_topology(FOUR_BAR["adjacency"], FOUR_BAR["node_types"]).order.tolist()
    assert data["order"] == order and data["lock"] is None and "trajectories" not in data

    # A third link on joint 3 over-constrains it: the engine's own message comes back.
    adjacency = [row[:] for row in FOUR_BAR["adjacency"]]
    adjacency[0][3] = adjacency[3][0] = 1
    status, data = client.post(
        "/api/analyze", {"adjacency": adjacency, "node_types": FOUR_BAR["node_types"]}
    )
    assert status == 200 and data["dof"] == 0 and data["solvable"] is False
    with pytest.raises(links_ray.InvalidMechanismError) as raised:
        analyze_topology(adjacency, FOUR_BAR["node_types"])
    assert data["problem"] == str(raised.value)

    with pytest.raises(links_ray.LockingError) as locked:
        simulate(LOCKING_FOUR_BAR)
    status, data = client.post("/api/analyze", LOCKING_FOUR_BAR)
    assert status == 200
    step = locked.value.step
    assert data["lock"] == {"step": step, "node": locked.value.node, "angle": 360 * step / STEPS}
    partial = np.array(data["trajectories"])
    assert partial.shape == (4, step, 2)
    assert_assembled(LOCKING_FOUR_BAR, partial)

    for body, words in [
        ({"node_types": [0, 2]}, "adjacency"),
        ({**FOUR_BAR, "positions": [[0.5, 0.5]] * 4}, "zero length"),
        ({**FOUR_BAR, "steps": 0}, "steps"),
    ]:
        status, data = client.post("/api/analyze", body)
        assert status == 400 and words in data["error"], data


def assert_assembled(mechanism: dict[str, Any], trajectories: np.ndarray) -> None:
    """Every pose keeps every link's length, the crank turns by 2 pi / STEPS a step, and each
    solved joint stays on its starting side of its two parents: the dyad has one solution."""
    start = np.array(mechanism["positions"])
    topology = analyze_topology(mechanism["adjacency"], mechanism["node_types"])
    steps = trajectories.shape[1]
    for i, j in zip(*np.nonzero(np.triu(topology.adjacency)), strict=True):
        lengths = np.linalg.norm(trajectories[i] - trajectories[j], axis=1)
        np.testing.assert_allclose(lengths, np.linalg.norm(start[i] - start[j]), atol=1e-9)
    crank = trajectories[1] - start[0]
    turned = np.unwrap(np.arctan2(crank[:, 1], crank[:, 0]))
    np.testing.assert_allclose(turned - turned[0], 2 * np.pi * np.arange(steps) / STEPS)

    def side(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.sign(
            (b[..., 0] - a[..., 0]) * (p[..., 1] - a[..., 1])
            - (b[..., 1] - a[..., 1]) * (p[..., 0] - a[..., 0])
        )

    for j, a, b in topology.order:
        expected = side(start[j], start[a], start[b])
        assert np.all(side(trajectories[j], trajectories[a], trajectories[b]) == expected)


# -- the first screen ---------------------------------------------------------------------------


def transmission_deg(trajectories: np.ndarray, joint: int, a: int, b: int) -> float:
    """The least angle at `joint` between its links to `a` and `b` over the turn, folded to
    0-90 degrees (90 transmits best, 0 is a dead centre)."""
    u = trajectories[a] - trajectories[joint]
    v = trajectories[b] - trajectories[joint]
    cos = np.sum(u * v, axis=1) / (np.linalg.norm(u, axis=1) * np.linalg.norm(v, axis=1))
    angle = np.degrees(np.arccos(np.clip(cos, -1, 1)))
    return float(np.min(np.minimum(angle, 180 - angle)))


def test_the_studio_opens_on_a_moving_four_bar(studio: Studio, client: Client, shots: Path) -> None:
    """The first screen: a crank-rocker four-bar with a coupler point, simulated by the server,
    its coupler curve drawn as the engine computes it, turning without a click, and a hint that
    invites the first edit."""
    mechanism = studio.mechanism()
    topology = analyze_topology(mechanism["adjacency"], mechanism["node_types"])
    assert mechanism["node_types"] == [0, 2, 0, 1, 1]
    links = {(int(i), int(j)) for i, j in np.argwhere(np.triu(topology.adjacency))}
    assert links == {(0, 1), (1, 3), (2, 3), (1, 4), (3, 4)}  # 1-3-4 is the coupler plate
    p = np.array(mechanism["positions"])
    crank, coupler, rocker, ground = (
        math.dist(p[i], p[j]) for i, j in [(0, 1), (1, 3), (2, 3), (0, 2)]
    )
    # Grashof with the crank shortest and on the ground: a crank-rocker, the crank turns fully.
    shortest, *middle, longest = sorted([crank, coupler, rocker, ground])
    assert shortest == crank and shortest + longest < sum(middle)
    truth = simulate(mechanism)  # the engine in this process: a full turn, no lock
    # Good transmission over the whole turn: the rocker's dyad and the coupler plate.
    assert transmission_deg(truth, 3, 1, 2) >= 45
    assert transmission_deg(truth, 4, 1, 3) >= 45
    swing = np.ptp(np.unwrap(np.arctan2(*(truth[3] - p[2]).T[::-1])))
    assert math.radians(20) < swing < math.pi  # the rocker rocks, it does not turn

    # Valid by the engine's checks, shown as such; no rule of the dataset's stored mechanisms
    # flagged but their size (four-bars come from 8-20 joint mechanisms reduced to the joints
    # a path needs).
    studio.wait("() => window.studio.editor.playing")
    assert studio.text("dof").startswith("1 (2 x 3 moving joints - 5 links)")
    assert studio.text("solvable") == "yes"
    assert "every joint assembles" in studio.text("status")
    _, analysis = client.post("/api/analyze", mechanism)
    assert analysis["lock"] is None and analysis["dataset_rules"] == ["5 joints, outside 8-20"]
    assert studio.text("rules") == "unlike the dataset's mechanisms: 5 joints, outside 8-20"
    assert not studio.page.get_by_test_id("error").is_visible()
    # The first edit, invited in one line; it goes at the first action.
    assert "Drag joint 4" in studio.text("hint")

    # What the page holds is /api/simulate's answer, equal to the engine's here...
    np.testing.assert_array_equal(studio.trajectories(), truth)
    # ... and what it draws is that: the coupler curve, every step, where the view puts it.
    # (read a frame on, so the paint read is of the view read)
    drawn = studio.js(
        """async () => {
          await new Promise((r) => requestAnimationFrame(r));
          return {paths: window.studio.editor.drawnPaths, view: window.studio.editor.view};
        }"""
    )
    view = drawn["view"]
    coupler_path = np.array(drawn["paths"][4])
    assert coupler_path.shape == (STEPS, 2)
    expected = np.stack(
        [
            view["width"] / 2 + (truth[4][:, 0] - view["cx"]) * view["scale"],
            view["height"] / 2 - (truth[4][:, 1] - view["cy"]) * view["scale"],
        ],
        axis=1,
    )
    np.testing.assert_allclose(coupler_path, expected, rtol=0, atol=1e-9)
    extent = np.ptp(coupler_path, axis=0)
    assert extent.min() > 40, extent  # a curve you can see, not a dot (CSS pixels)
    assert [drawn["paths"][j] is None for j in range(5)] == [True, False, True, False, False]

    # It moves on its own: two samples of the studio's state some animation frames apart
    # (frames, not seconds: a busy machine only makes each frame later).
    sample = """async (frames) => {
      const e = window.studio.editor;
      for (let i = 0; i < frames; i++) await new Promise((r) => requestAnimationFrame(r));
      return {step: e.step, pose: e.pose(), shown: e.canvas.dataset.step};
    }"""
    first = studio.js(sample, 1)
    later = first
    for _ in range(20):  # at most 20 x 30 frames; it moves within the first few on any machine
        later = studio.js(sample, 30)
        if later["step"] != first["step"]:
            break
    assert later["step"] != first["step"]
    for s in (first, later):
        assert s["shown"] == str(s["step"])
        # Step 0 shows the starting positions, which the solver reproduces to a rounding.
        np.testing.assert_allclose(s["pose"], truth[:, s["step"]], rtol=0, atol=1e-12)
    moved = np.subtract(later["pose"][4], first["pose"][4])
    assert np.linalg.norm(moved) > 0
    studio.shot("studio-opening.png", shots)

    # The first action takes the hint's place.
    studio.click("tool-move")
    assert "Drag joint 4" not in studio.text("hint")


# -- the editor ---------------------------------------------------------------------------------


def test_page_loads_without_console_errors(studio: Studio, client: Client) -> None:
    _, health = client.get("/api/health")
    assert studio.text("health").startswith(f"{health['paths']:,}")
    assert len(studio.mechanism()["node_types"]) == 5  # the opening four-bar, tested below
    assert not studio.page.get_by_test_id("error").is_visible()
    studio.start_blank()
    assert studio.mechanism() == {
        "adjacency": [[0, 1, 0], [1, 0, 0], [0, 0, 0]],
        "node_types": [0, 2, 0],
        "positions": [[0.5, 0.5], [0.55, 0.5], [0.8, 0.5]],
    }
    assert studio.text("dof").startswith("1 (2 x 1 moving joints - 1 links)")
    assert studio.text("solvable") == "yes"
    assert "every joint assembles" in studio.text("status")
    assert not studio.page.get_by_test_id("error").is_visible()
    time.sleep(0.5)  # anything logged late still fails the fixture's check
    assert studio.errors == []


def test_the_studio_takes_its_limits_from_the_api(
    studio: Studio, browser: Any, client: Client, tmp_path: Path
) -> None:
    """The page asks GET /api/limits and bounds its inputs and imports by the answer: the
    engine's limits here, and other limits when the API gives others (no number of its own)."""
    assert "/api/limits" in studio.requests
    assert studio.js("() => window.studio.limits") == request_limits()
    assert studio.page.get_by_test_id("k").get_attribute("max") == str(MAX_K)
    angle = studio.page.get_by_test_id("min-transmission").get_attribute("max")
    assert float(angle) == MAX_TRANSMISSION_DEG

    context = browser.new_context(viewport=VIEWPORT)
    try:
        page = context.new_page()
        other = {**request_limits(), "max_k": 7, "max_joints": 5, "max_transmission_deg": 20}
        page.route("**/api/limits", lambda route: route.fulfill(json=other))
        narrow = Studio(page, studio.base)
        narrow.open()
        opened = narrow.mechanism()
        assert narrow.page.get_by_test_id("k").get_attribute("max") == "7"
        assert narrow.page.get_by_test_id("min-transmission").get_attribute("max") == "20"
        six_joints = {
            "adjacency": [
                [0, 1, 0, 0, 0, 0],
                [1, 0, 0, 1, 1, 0],
                [0, 0, 0, 1, 0, 0],
                [0, 1, 1, 0, 0, 1],
                [0, 1, 0, 0, 0, 1],
                [0, 0, 0, 1, 1, 0],
            ],
            "node_types": [0, 2, 0, 1, 1, 1],
            "positions": [[0.5, 0.5], [0.55, 0.5], [0.8, 0.5], [0.6, 0.7], [0.5, 0.7], [0.6, 0.8]],
        }
        narrow.import_mechanism(tmp_path, six_joints, "six.json")
        narrow.wait("() => !document.querySelector('[data-testid=error]').hidden")
        assert "at most 5 joints, got 6" in narrow.text("error")
        assert narrow.mechanism() == opened
        assert narrow.unexpected_errors() == []
    finally:
        context.close()


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


# -- draw to retrieve ---------------------------------------------------------------------------


def test_draw_retrieve_animate_and_open_in_editor(
    studio: Studio, client: Client, shots: Path
) -> None:
    # A bean-shaped loop across the drawing area.
    t = np.linspace(0, 2 * np.pi, 90)
    curve = np.stack([0.5 + 0.32 * np.cos(t), 0.5 + 0.18 * np.sin(t) + 0.08 * np.cos(2 * t)], 1)
    draw(studio, curve.tolist())
    drawn = studio.js("() => window.studio.retriever.points")
    assert len(drawn) > 50
    np.testing.assert_allclose(np.min(drawn, 0), curve.min(0), atol=0.01)
    np.testing.assert_allclose(np.max(drawn, 0), curve.max(0), atol=0.01)

    studio.page.get_by_test_id("k").fill("5")
    studio.click("retrieve-button")
    results = studio.page.get_by_test_id("result")
    results.nth(4).wait_for()
    assert results.count() == 5
    # The list is the API's answer for the drawn points, best first, chamfer shown.
    # The page starts at synthesis's floor, the API's default_transmission_deg.
    floor = request_limits()["default_transmission_deg"]
    assert studio.page.get_by_test_id("min-transmission").input_value() == f"{floor:g}"
    _, expected = client.post("/api/retrieve", {"points": drawn, "k": 5, "min_transmission": floor})
    chamfers = [float(results.nth(i).get_attribute("data-chamfer")) for i in range(5)]
    assert chamfers == [r["chamfer"] for r in expected["results"]]
    assert chamfers == sorted(chamfers)
    for i, result in enumerate(expected["results"]):
        shown = results.nth(i).inner_text().split("chamfer ", 1)[1].split()[0]
        assert float(shown) == pytest.approx(result["chamfer"], rel=1e-3)

    # Choosing one animates it: the frame advances, over the drawn curve, in the user's frame.
    results.nth(0).click()
    canvas = studio.page.get_by_test_id("draw-canvas")
    studio.wait(
        "() => document.querySelector('[data-testid=draw-canvas]').dataset.animating === 'true'"
    )
    frames = set()
    for _ in range(6):
        frames.add(canvas.get_attribute("data-frame"))
        time.sleep(0.12)
    assert len(frames) >= 3, frames
    chosen = studio.js("() => window.studio.retriever.chosen")
    best = expected["results"][0]
    assert chosen["result"]["mechanism"] == best["mechanism"]
    traced = np.array(chosen["trajectories"])[best["mechanism_joint"]]
    np.testing.assert_array_equal(traced, simulate(best["mechanism"])[best["mechanism_joint"]])
    # The server moved the mechanism onto the curve: their boxes share a centre, roughly.
    size = np.ptp(curve, axis=0).max()
    centre = (traced.min(0) + traced.max(0)) / 2
    assert np.linalg.norm(centre - (curve.min(0) + curve.max(0)) / 2) < 0.5 * size
    studio.shot("studio-retrieve.png", shots)

    # Open it in the editor and keep going from there.
    studio.click("open-in-editor")
    studio.wait_idle()
    assert studio.mechanism() == best["mechanism"]
    np.testing.assert_array_equal(studio.trajectories(), simulate(best["mechanism"]))
    studio.click("play")
    time.sleep(1.0)
    studio.page.get_by_test_id("studio-canvas").scroll_into_view_if_needed()
    studio.shot("studio-editor.png", shots)
    studio.click("play")


def test_retrieve_with_a_least_transmission_angle(studio: Studio, client: Client) -> None:
    """The floor set on the page goes to the API, and each result shows its angle."""
    t = np.linspace(0, 2 * np.pi, 90)
    curve = np.stack([0.5 + 0.3 * np.cos(t), 0.5 + 0.15 * np.sin(t)], 1)
    draw(studio, curve.tolist())
    drawn = studio.js("() => window.studio.retriever.points")
    studio.page.get_by_test_id("k").fill("4")
    studio.page.get_by_test_id("min-transmission").fill("5")
    studio.click("retrieve-button")
    _, expected = client.post("/api/retrieve", {"points": drawn, "k": 4, "min_transmission": 5})
    count = len(expected["results"])
    assert count > 0
    results = studio.page.get_by_test_id("result")
    results.nth(count - 1).wait_for()
    assert results.count() == count
    for i, result in enumerate(expected["results"]):
        shown = float(results.nth(i).get_attribute("data-transmission"))
        assert shown == result["min_transmission_deg"] >= 5
        assert f"least transmission {shown:.1f}°" in results.nth(i).inner_text()
    # At the highest floor the page still shows the API's answer; none at all, it says why.
    studio.page.get_by_test_id("min-transmission").fill("45")
    studio.click("retrieve-button")
    _, highest = client.post("/api/retrieve", {"points": drawn, "k": 4, "min_transmission": 45})
    if highest["results"]:
        shown = "[...document.querySelectorAll('[data-testid=result]')]"
        studio.wait(
            f"() => {shown}.length === {len(highest['results'])} && "
            f"{shown}.every((item) => Number(item.dataset.transmission) >= 45)"
        )
    else:
        studio.wait(
            "() => document.querySelector('[data-testid=retrieve-status]').textContent"
            ".includes('No curated path keeps a transmission angle of 45')"
        )
    studio.page.get_by_test_id("min-transmission").fill("0")


def test_retrieval_errors_are_shown_in_words(studio: Studio) -> None:
    studio.allow("status of 400")
    studio.click("retrieve-button")
    assert "Draw a curve first" in studio.text("retrieve-status")
    # A click is a curve of one point: the API refuses it and the page says why.
    box = studio.page.get_by_test_id("draw-canvas").bounding_box()
    studio.page.mouse.click(box["x"] + 100, box["y"] + 100)
    studio.click("retrieve-button")
    studio.wait(
        "() => document.querySelector('[data-testid=retrieve-status]').textContent.includes('HTTP')"
    )
    status = studio.text("retrieve-status")
    assert "Retrieval failed" in status and "3 to 10000" in status and "(HTTP 400)" in status
    assert studio.page.get_by_test_id("result").count() == 0


#: How long a synthesis may take to answer in the studio (ms): its few seconds of refining, and
#: the index and kernels it may load first, on a machine busy with other work.
SYNTHESIS_WAIT_MS = 180_000
#: The refinement's iterations in the studio's synthesis test.
SYNTHESIS_ITERATIONS = 40


def test_draw_and_synthesize(studio: Studio, client: Client, shots: Path) -> None:
    """The Synthesize button: the refinement shown live (the best so far animating, its
    chamfer falling), then the API's refined mechanisms, best first, each no worse than it was
    retrieved, and the best animating over the curve."""
    t = np.linspace(0, 2 * np.pi, 90)
    curve = np.stack([0.5 + 0.3 * np.cos(t), 0.5 + 0.2 * np.sin(t) + 0.06 * np.sin(2 * t)], 1)
    draw(studio, curve.tolist())
    studio.page.get_by_test_id("k").fill("3")
    # Each progress line as the page shows it, recorded as it happens: on a busy machine the
    # whole synthesis may be over before a poll of the page would see it refining.
    studio.js(
        """() => {
            const retriever = window.studio.retriever;
            const show = retriever.showProgress.bind(retriever);
            window.progressSeen = [];
            retriever.showProgress = (line) => {
                show(line);
                const chosen = retriever.chosen;
                window.progressSeen.push({
                    status: document.querySelector("[data-testid=retrieve-status]").innerText,
                    index: chosen.index,
                    joints: chosen.result.mechanism.node_types.length,
                    traced: chosen.trajectories.length,
                });
            };
        }"""
    )
    # A counted amount of work (a seed and an iteration count) instead of the studio's seconds,
    # so that what the refinement reaches does not depend on how busy the machine is.
    studio.page.route(
        "**/api/synthesize",
        lambda route: route.continue_(
            post_data=json.dumps(
                {
                    **json.loads(route.request.post_data),
                    "seed": 3,
                    "iterations": SYNTHESIS_ITERATIONS,
                }
            )
        ),
    )
    studio.click("synthesize-button")
    # While it refines: the best so far moves over the curve and the status says how near.
    studio.wait(
        "() => Number(document.querySelector('[data-testid=draw-canvas]').dataset.progress) >= 2",
        timeout=SYNTHESIS_WAIT_MS,
    )
    if "Refining: chamfer" in studio.text("retrieve-status"):
        studio.shot("studio-synthesize.png", shots)
    results = studio.page.get_by_test_id("result")
    results.nth(2).wait_for(timeout=SYNTHESIS_WAIT_MS)
    seen = studio.js("() => window.progressSeen")
    assert len(seen) >= 2
    for line in seen:
        assert line["status"].startswith("Refining: chamfer"), line
        assert line["index"] == -1 and line["traced"] == line["joints"], line
    assert results.count() == 3
    chamfers = [float(results.nth(i).get_attribute("data-chamfer")) for i in range(3)]
    assert chamfers == sorted(chamfers)
    for i in range(3):
        retrieved = float(results.nth(i).inner_text().split("refined from ", 1)[1].split(",")[0])
        assert chamfers[i] <= retrieved * (1 + 1e-3)
    falling = studio.js("() => window.studio.retriever.live")
    assert len(falling) >= 2 and falling == sorted(falling, reverse=True)
    assert chamfers[0] <= falling[-1]
    # It ends on the best, animating, without a click.
    studio.wait(
        "() => window.studio.retriever.chosen && window.studio.retriever.chosen.index === 0 && "
        "document.querySelector('[data-testid=draw-canvas]').dataset.animating === 'true'"
    )
    status = studio.text("retrieve-status")
    assert "synthesis" in status and "Result #1" in status
    results.nth(0).click()
    studio.wait(
        "() => document.querySelector('[data-testid=draw-canvas]').dataset.animating === 'true'"
    )
    chosen = studio.js("() => window.studio.retriever.chosen")
    best = chosen["result"]
    traced = np.array(chosen["trajectories"])[best["mechanism_joint"]]
    np.testing.assert_array_equal(traced, simulate(best["mechanism"])[best["mechanism_joint"]])
    np.testing.assert_array_equal(traced, np.array(best["path"]))


# -- curves from drawings -------------------------------------------------------------------------

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


# -- design constraints drawn on the canvas -------------------------------------------------------


def drag_on_drawing(studio: Studio, start: list[float], end: list[float]) -> None:
    """A mouse drag on the draw canvas between two world points."""
    a, b = (
        studio.screen("draw-canvas", studio.js("(p) => window.studio.drawToScreen(p)", p))
        for p in (start, end)
    )
    studio.page.mouse.move(*a)
    studio.page.mouse.down()
    studio.page.mouse.move(*b, steps=5)
    studio.page.mouse.up()


def draw_box(studio: Studio, kind: str, corner: list[float], other: list[float]) -> None:
    """Draw a `kind` box ("pivots" or "footprint") between two world corners, then go back to
    drawing curves."""
    studio.click(f"box-{kind}")
    drag_on_drawing(studio, corner, other)
    studio.wait(
        "(kind) => window.studio.constraints.boxes[kind] !== null"
        " && !window.studio.constraints.dragging",
        kind,
    )
    studio.click(f"box-{kind}")


def test_constraint_boxes_are_drawn_in_the_drawings_frame(studio: Studio) -> None:
    """A pivot and a footprint box dragged on the canvas are held in the frame the drawn points
    are (to a pixel), a corner dragged moves only that corner, and what a synthesis would send
    is those boxes and the link limits typed; Clear boxes removes them; the curve drawn
    meanwhile is untouched."""
    t = np.linspace(0, 2 * np.pi, 60)
    draw(studio, np.stack([0.5 + 0.3 * np.cos(t), 0.5 + 0.2 * np.sin(t)], 1).tolist())
    drawn = studio.js("() => window.studio.retriever.points")
    pixel = 1.0 / studio.js("() => window.studio.retriever.view.scale")

    draw_box(studio, "pivots", [0.15, 0.7], [0.45, 0.2])  # any two opposite corners
    draw_box(studio, "footprint", [0.05, 0.05], [0.95, 0.9])
    boxes = studio.js("() => window.studio.constraints.boxes")
    np.testing.assert_allclose(boxes["pivots"], [0.15, 0.2, 0.45, 0.7], atol=1.5 * pixel)
    np.testing.assert_allclose(boxes["footprint"], [0.05, 0.05, 0.95, 0.9], atol=1.5 * pixel)
    assert studio.js("() => window.studio.retriever.points") == drawn  # boxes draw no curve

    # A corner taken and moved: the opposite one stays where it was.
    studio.click("box-pivots")
    pivots = boxes["pivots"]
    drag_on_drawing(studio, [pivots[2], pivots[3]], [0.6, 0.8])
    studio.click("box-pivots")
    moved = studio.js("() => window.studio.constraints.boxes.pivots")
    assert moved[:2] == pivots[:2]
    np.testing.assert_allclose(moved[2:], [0.6, 0.8], atol=1.5 * pixel)

    studio.page.get_by_test_id("max-link-ratio").fill("6")
    studio.page.get_by_test_id("min-link").fill("0.02")
    studio.page.get_by_test_id("max-joints").fill("8")
    studio.page.get_by_test_id("front").check()
    studio.page.get_by_test_id("timed").check()
    options = studio.js("() => window.studio.retriever.synthesisOptions()")
    assert options == {
        "max_joints": 8,
        "front": True,
        "timing": True,
        "constraints": {
            "pivots": moved,
            "footprint": boxes["footprint"],
            "max_link_ratio": 6,
            "min_link": 0.02,
        },
    }
    studio.click("clear-boxes")
    assert studio.js("() => window.studio.constraints.boxes") == {"pivots": None, "footprint": None}
    options = studio.js("() => window.studio.retriever.synthesisOptions()")
    assert options["constraints"] == {"max_link_ratio": 6, "min_link": 0.02}


# -- simplest first, constraints and timing, against the real synthesis --------------------------


def fixed_synthesis_work(studio: Studio) -> list[dict[str, Any]]:
    """Give the page's syntheses a counted amount of work (a seed and an iteration count) instead
    of its seconds, so that what they reach does not depend on the machine's load; returns the
    bodies sent, as the server receives them."""
    sent: list[dict[str, Any]] = []

    def fixed(route: Any) -> None:
        body = {**json.loads(route.request.post_data), "seed": 3, "iterations": 40}
        sent.append(body)
        route.continue_(post_data=json.dumps(body))

    studio.page.route("**/api/synthesize", fixed)
    return sent


def streamed_answer(client: Client, body: dict[str, Any]) -> dict[str, Any]:
    """The last line of a streamed /api/synthesize answer to `body`: what the page received."""
    status, _, text = client.request("POST", "/api/synthesize", body)
    assert status == 200, text
    return json.loads(text.strip().splitlines()[-1])


def bean(studio: Studio) -> list[list[float]]:
    """A bean-shaped loop drawn across the drawing area; the points the page holds."""
    t = np.linspace(0, 2 * np.pi, 90)
    curve = np.stack([0.5 + 0.3 * np.cos(t), 0.5 + 0.2 * np.sin(t) + 0.06 * np.sin(2 * t)], 1)
    draw(studio, curve.tolist())
    return studio.js("() => window.studio.retriever.points")


#: The most joints the front test allows: fewer than the unbounded front reaches on its curve.
FRONT_MAX_JOINTS = 6


def test_simplest_first_front_table_and_timing(studio: Studio, client: Client, shots: Path) -> None:
    """Simplest first, Timed and Max joints: the answer is a table of joints against chamfer
    (and timed error), the API's front row by row, joints rising and chamfer falling, none
    over the joints allowed; a row's click animates that row's mechanism."""
    sent = fixed_synthesis_work(studio)
    bean(studio)
    # No floor: the test dataset is small, and a front needs candidates of several sizes.
    studio.page.get_by_test_id("min-transmission").fill("0")
    studio.page.get_by_test_id("max-joints").fill(str(FRONT_MAX_JOINTS))
    studio.page.get_by_test_id("front").check()
    studio.page.get_by_test_id("timed").check()
    studio.click("synthesize-button")
    table = studio.page.get_by_test_id("front-table")
    table.wait_for(timeout=SYNTHESIS_WAIT_MS)
    studio.wait("() => window.studio.retriever.chosen && window.studio.retriever.chosen.index >= 0")
    assert len(sent) == 1 and sent[0]["front"] is True and sent[0]["timing"] is True
    assert sent[0]["max_joints"] == FRONT_MAX_JOINTS
    answer = streamed_answer(client, sent[0])  # equal requests, bit-equal answers
    results = answer["results"]
    rows = studio.page.get_by_test_id("front-row")
    assert rows.count() == len(results) >= 2
    shown = [
        (
            int(rows.nth(i).get_attribute("data-joints")),
            float(rows.nth(i).get_attribute("data-chamfer")),
        )
        for i in range(rows.count())
    ]
    assert shown == [(r["n_joints"], r["chamfer"]) for r in results]
    joints = [j for j, _ in shown]
    chamfers = [c for _, c in shown]
    assert joints == sorted(set(joints))  # one row per joint count, simplest first
    assert joints[-1] <= FRONT_MAX_JOINTS
    # Any joints allowed, the same work's front goes further: the bound was kept, not idle.
    free = streamed_answer(client, {k: v for k, v in sent[0].items() if k != "max_joints"})
    assert max(r["n_joints"] for r in free["results"]) > FRONT_MAX_JOINTS
    # A timed front ranks by the timed error: each row beats every simpler one by it.
    errors = [r["timed_error"] for r in results]
    assert errors == sorted(errors, reverse=True) and len(set(errors)) == len(errors)
    assert all(chamfer > 0 for chamfer in chamfers)
    for i, result in enumerate(results):
        assert result["n_joints"] == len(result["mechanism"]["node_types"])
        timed = float(rows.nth(i).get_attribute("data-timed-error"))
        assert timed == result["timed_error"] > 0
        assert f"{timed:.4g}"[:4] in rows.nth(i).inner_text()
    assert not studio.page.get_by_test_id("results").is_visible()  # the table, not the list

    # It ends on the row of least chamfer; a click on the simplest animates that one instead.
    least = min(range(len(results)), key=lambda i: results[i]["chamfer"])
    assert least > 0  # the simplest is not the closest: the click below changes the choice
    assert studio.js("() => window.studio.retriever.chosen.index") == least
    rows.nth(0).click()
    studio.wait(
        "() => window.studio.retriever.chosen && window.studio.retriever.chosen.index === 0"
    )
    studio.wait(
        "() => document.querySelector('[data-testid=draw-canvas]').dataset.animating === 'true'"
    )
    assert rows.nth(0).get_attribute("aria-selected") == "true"
    assert rows.nth(least).get_attribute("aria-selected") == "false"
    chosen = studio.js("() => window.studio.retriever.chosen")
    simplest = results[0]
    assert chosen["result"]["mechanism"] == simplest["mechanism"]
    joint = simplest["mechanism_joint"]
    traced = np.array(chosen["trajectories"])[joint]
    np.testing.assert_array_equal(traced, simulate(simplest["mechanism"])[joint])
    frames = {studio.page.get_by_test_id("draw-canvas").get_attribute("data-frame")}
    for _ in range(20):
        studio.js("() => new Promise((r) => setTimeout(r, 100))")
        frames.add(studio.page.get_by_test_id("draw-canvas").get_attribute("data-frame"))
        if len(frames) >= 3:
            break
    assert len(frames) >= 3, frames
    assert f"{simplest['n_joints']} joints" in studio.text("retrieve-status")
    studio.shot("studio-front.png", shots)


def test_a_pivot_box_drawn_on_the_canvas_is_kept(
    studio: Studio, client: Client, shots: Path
) -> None:
    """A pivot box drawn on the canvas goes to the synthesis in the drawing's frame, and every
    fixed joint of every mechanism of the answer lies inside it; a box no candidate can reach
    is answered with `unmet`, shown in words."""
    sent = fixed_synthesis_work(studio)
    drawn = np.array(bean(studio))
    low, high = drawn.min(0), drawn.max(0)
    box = [low[0], low[1] - 0.1, high[0], high[1]]  # the pivots under and within the curve
    draw_box(studio, "pivots", [box[0], box[1]], [box[2], box[3]])
    held = studio.js("() => window.studio.constraints.boxes.pivots")
    studio.page.get_by_test_id("k").fill("3")
    studio.page.get_by_test_id("min-transmission").fill("0")  # as many candidates as can be
    studio.click("synthesize-button")
    studio.page.get_by_test_id("result").first.wait_for(timeout=SYNTHESIS_WAIT_MS)
    studio.wait(
        "() => window.studio.retriever.chosen && window.studio.retriever.chosen.index === 0"
    )
    assert sent[-1]["constraints"] == {"pivots": held}
    results = studio.js("() => window.studio.retriever.results")
    assert results == streamed_answer(client, sent[-1])["results"] and results
    for result in results:
        mechanism = result["mechanism"]
        fixed = np.array(mechanism["positions"])[np.array(mechanism["node_types"]) == 0]
        assert len(fixed) >= 2
        assert np.all(fixed >= held[:2]) and np.all(fixed <= held[2:]), (fixed, held)
        assert studio.page.get_by_test_id("result").nth(results.index(result)).get_attribute(
            "data-joints"
        ) == str(result["n_joints"])
    # Without the box the same work places a pivot outside it: the box was kept, not lucky.
    free = streamed_answer(client, {k: v for k, v in sent[-1].items() if k != "constraints"})
    outside = [
        np.array(r["mechanism"]["positions"])[np.array(r["mechanism"]["node_types"]) == 0]
        for r in free["results"]
    ]
    assert any(np.any(f < held[:2]) or np.any(f > held[2:]) for f in outside)
    studio.shot("studio-pivots.png", shots)

    # A box far from anything a mechanism of this curve can reach: unmet, said in words. Ten
    # chords away: a step moves a joint at most a quarter of the chord, so the counted work
    # cannot bring a pivot there (a box in the canvas's corner it now can, at a chamfer of a
    # chord and more). The canvas cannot draw so far: the box is held as a drawn one is.
    studio.click("clear-boxes")
    studio.js("() => { window.studio.constraints.boxes.pivots = [8, 8, 8.02, 8.02]; }")
    studio.click("synthesize-button")
    unmet = studio.page.get_by_test_id("unmet")
    unmet.wait_for(timeout=SYNTHESIS_WAIT_MS)
    answer = streamed_answer(client, sent[-1])
    assert answer["results"] == [] and answer["unmet"]["constraint"] == "pivots"
    assert unmet.get_attribute("data-constraint") == "pivots"
    assert float(unmet.get_attribute("data-by")) == answer["unmet"]["by"] > 0
    assert "pivots" in unmet.inner_text()
    assert studio.page.get_by_test_id("result").count() == 0


# -- a page of another site --------------------------------------------------------------------

ATTACK_PAGE = b"""<!doctype html><meta charset="utf-8"><title>another site</title>
<p>a page of another site</p>"""


@pytest.fixture
def named_browser(browser: Any) -> Iterator[Any]:
    """A Chromium that resolves the allowed name (serve_app.ALLOWED_HOST) and attacker.test to
    127.0.0.1, as DNS would for a server's own name and for a name rebound to loopback;
    launched by the module's own Playwright (one Playwright runs in a process at a time)."""
    from tests.support.serve_app import ALLOWED_HOST
    from tests.support.studio_page import CHROMIUM, CHROMIUM_ARGS

    rules = f"--host-resolver-rules=MAP {ALLOWED_HOST} 127.0.0.1, MAP attacker.test 127.0.0.1"
    chromium = browser.browser_type.launch(executable_path=CHROMIUM, args=[*CHROMIUM_ARGS, rules])
    try:
        yield chromium
    finally:
        chromium.close()


@pytest.fixture
def attack_site() -> Iterator[int]:
    """A plain HTTP server on a port of its own serving ATTACK_PAGE: another site's page."""
    import http.server
    import threading

    class Page(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            self.send_response(200)
            self.send_header("Content-Type", "text/html; charset=utf-8")
            self.end_headers()
            self.wfile.write(ATTACK_PAGE)

        def log_message(self, *args: Any) -> None:
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Page)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield server.server_address[1]
    finally:
        server.shutdown()


def test_the_studio_works_by_its_name_and_no_other_site_can_use_the_server(
    named_browser: Any, client: Client, attack_site: int
) -> None:
    """Opened through the name the server was given, the studio draws and retrieves as
    through 127.0.0.1. A name rebound to 127.0.0.1 gets only 400s. A page of another site can
    send the server no drawing: its posts that need no preflight (of no type, or plain text)
    are refused 415 unread, and a JSON post is stopped by the browser's preflight, which the
    server does not grant."""
    from tests.support.serve_app import ALLOWED_HOST

    context = named_browser.new_context(viewport=VIEWPORT)
    try:
        page = context.new_page()
        page.set_default_timeout(30_000)
        studio = Studio(page, f"http://{ALLOWED_HOST}:{client.port}")
        studio.open()
        t = np.linspace(0, 2 * np.pi, 60)
        draw(studio, np.stack([0.5 + 0.3 * np.cos(t), 0.5 + 0.2 * np.sin(t)], 1).tolist())
        studio.click("retrieve-button")
        page.get_by_test_id("result").nth(2).wait_for()
        assert studio.unexpected_errors() == []

        # DNS rebinding: the attacker's own name, now pointing at this machine.
        rebound = page.goto(f"http://attacker.test:{client.port}/")
        assert rebound is not None and rebound.status == 400
        assert "Host 'attacker.test" in json.loads(rebound.body())["error"]

        # Another site's page posting to the server's address.
        page.goto(f"http://attacker.test:{attack_site}/")
        answers: dict[str, int] = {}
        page.on("response", lambda r: answers.__setitem__(f"{r.request.method} {r.url}", r.status))
        target = f"http://127.0.0.1:{client.port}/api/curve"
        drawing = json.dumps({"name": "a.csv", "text": "0,0\n1,1\n2,0\n"})
        outcomes = page.evaluate(
            """async ([target, body]) => {
                // A Blob of no type is sent with no Content-Type at all.
                const untyped = new Blob([body]);
                await fetch(target + "?untyped", {method: "POST", mode: "no-cors", body: untyped});
                const plain = await fetch(target, {method: "POST", mode: "no-cors", body});
                let json = "sent";
                try {
                    await fetch(target, {
                        method: "POST", body, headers: {"Content-Type": "application/json"}});
                } catch (err) { json = "refused by the browser"; }
                return {plain: plain.type, json};
            }""",
            [target, drawing],
        )
        assert outcomes == {"plain": "opaque", "json": "refused by the browser"}, outcomes
        page.wait_for_timeout(500)
        assert answers.get(f"POST {target}") == 415, answers
        assert answers.get(f"POST {target}?untyped") == 415, answers
        assert answers.get(f"OPTIONS {target}") not in (200, 204), answers
    finally:
        context.close()
