"""Draw to retrieve, in a real browser (test_studio_page.py says how): a curve drawn with the
mouse, the API's results listed best first and animated over it, one opened in the editor, a
least transmission angle kept, and errors in words."""

import time
from pathlib import Path

import numpy as np
import pytest

from links_ray.serve.http.limits import request_limits
from tests.support.serving import Client
from tests.support.studio_page import Studio, draw, simulate


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
