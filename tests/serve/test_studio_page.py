"""The studio's page, in a real browser against the real Serve app: its files served from the
package, the verdicts of /api/analyze it shows, the first screen (a four-bar turning on its
own), a load without console errors, and the limits it takes from /api/limits.

The test_studio_*.py files drive Debian's Chromium (`/usr/bin/chromium`, or LINKS_CHROMIUM; one
for all of them: the `browser` fixture, tests/support/browser.py) with Playwright and real mouse
events, on the page the `client` fixture serves (a 300-mechanism dataset, see
support/datasets.py). Numbers the page shows are read from `window.studio` and checked against
`links_ray` in Python.

Screenshots go to pytest's temporary folder, or to the folder LINKS_STUDIO_SCREENSHOTS names:
`LINKS_STUDIO_SCREENSHOTS=docs python -m pytest -q tests/serve/test_studio_*.py` refreshes the
README's.
"""

import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import links_ray
from links_ray.engine.inputs import MAX_K, MAX_TRANSMISSION_DEG
from links_ray.engine.kinematics.mechanism import analyze_topology
from links_ray.serve.http.limits import request_limits
from tests.support.serving import FOUR_BAR, LOCKING_FOUR_BAR, Client
from tests.support.studio_page import STEPS, VIEWPORT, Studio, assert_assembled, simulate

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
