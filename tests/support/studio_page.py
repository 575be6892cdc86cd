"""The studio in a browser tab, with helpers that act as a user would (tests/serve/test_studio_*.py
and the tests of an imported root), and the engine's own answers the studio's tests check the
page against; the `browser` fixture (support/browser.py) launches Debian's Chromium."""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from tests.support.serving import FOUR_BAR

CHROMIUM = os.environ.get("LINKS_CHROMIUM", "/usr/bin/chromium")
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking"]
VIEWPORT = {"width": 1400, "height": 1000}
#: The steps of a turn the studio simulates.
STEPS = 200


class Studio:
    """The studio page in one browser tab, with helpers that act as a user would."""

    def __init__(self, page: Any, base: str) -> None:
        self.page = page
        self.base = base
        self.errors: list[str] = []
        self.allowed: list[str] = []
        self.requests: list[str] = []
        page.on("console", lambda m: self.errors.append(m.text) if m.type == "error" else None)
        page.on("pageerror", lambda exc: self.errors.append(f"page error: {exc}"))
        page.on("request", lambda r: self.requests.append(r.url.removeprefix(base)))

    def allow(self, *fragments: str) -> None:
        """Expect console errors containing any of `fragments`.

        Chromium itself logs "Failed to load resource" for every 4xx answer and aborted
        request; tests that provoke those on purpose (a locking mechanism gets 422) say so.
        """
        self.allowed.extend(fragments)

    def unexpected_errors(self) -> list[str]:
        """Console errors and uncaught exceptions that no `allow` covers."""
        return [e for e in self.errors if not any(f in e for f in self.allowed)]

    def open(self, path: str = "/") -> None:
        """Load the page and wait until its first simulation and analysis are shown."""
        self.page.goto(self.base + path)
        self.wait_idle()

    def js(self, expression: str, arg: Any = None) -> Any:
        """Evaluate an arrow function in the page (the page's CSP forbids evaluating strings)."""
        return self.page.evaluate(expression, arg)

    def wait(self, predicate: str, arg: Any = None, timeout: float = 30_000) -> None:
        self.page.wait_for_function(predicate, arg=arg, timeout=timeout)

    def wait_idle(self) -> None:
        """Every edit simulated and analysed."""
        self.wait("() => window.studio && window.studio.idle()")

    def text(self, testid: str) -> str:
        return self.page.get_by_test_id(testid).inner_text()

    def click(self, testid: str) -> None:
        self.page.get_by_test_id(testid).click()

    def mechanism(self) -> dict[str, Any]:
        return self.js("() => window.studio.mechanism()")

    def trajectories(self) -> np.ndarray | None:
        data = self.js("() => window.studio.trajectories()")
        return None if data is None else np.array(data, dtype=np.float64)

    def screen(self, testid: str, local: list[float]) -> tuple[float, float]:
        """Page coordinates of a point given in a canvas's own CSS pixels."""
        box = self.page.get_by_test_id(testid).bounding_box()
        return box["x"] + local[0], box["y"] + local[1]

    def editor_point(self, world: list[float]) -> tuple[float, float]:
        """Where world point `world` is drawn in the editor, in page coordinates."""
        return self.screen("studio-canvas", self.js("(p) => window.studio.toScreen(p)", world))

    def click_world(self, world: list[float]) -> None:
        """A real mouse click on the editor at a world point."""
        self.page.mouse.click(*self.editor_point(world))

    def pixel(self) -> float:
        """One screen pixel in world units, in the editor."""
        return 1.0 / self.js("() => window.studio.editor.view.scale")

    def start_blank(self) -> None:
        """New: the crank and one ground joint, standing still (the page opens on a four-bar)."""
        self.click("new")
        self.wait_idle()
        assert self.js("() => window.studio.editor.playing") is False

    def build_four_bar(self) -> None:
        """FOUR_BAR by clicks from New: the J-operator on joints 1 and 2, placed at joint 3's
        spot."""
        self.start_blank()
        self.click("tool-joint")
        self.click_world(FOUR_BAR["positions"][1])
        self.click_world(FOUR_BAR["positions"][2])
        self.click_world(FOUR_BAR["positions"][3])
        self.wait_idle()

    def import_mechanism(self, tmp_path: Path, mechanism: dict[str, Any], name: str) -> None:
        """Import a mechanism through the page's file input, as a user picking a file."""
        path = tmp_path / name
        path.write_text(json.dumps(mechanism))
        self.page.get_by_test_id("import-file").set_input_files(str(path))
        self.wait_idle()

    def shot(self, name: str, folder: Path) -> None:
        """A screenshot of the whole page."""
        self.page.screenshot(path=str(folder / name), full_page=True)


def draw(studio: Studio, points: list[list[float]]) -> None:
    """Draw through world points on the draw canvas with the mouse."""
    local = [studio.js("(p) => window.studio.drawToScreen(p)", p) for p in points]
    page_points = [studio.screen("draw-canvas", p) for p in local]
    studio.page.mouse.move(*page_points[0])
    studio.page.mouse.down()
    for p in page_points[1:]:
        studio.page.mouse.move(*p, steps=2)
    studio.page.mouse.up()
    # The stroke is over once the page has taken the release (a loaded machine may lag it).
    studio.wait("() => window.studio.retriever.drawing === null")


@contextlib.contextmanager
def open_studio(browser: Any, port: int) -> Iterator[Studio]:
    """The studio served on `port` in a fresh browser context, opened; asserts on leaving that
    the page logged no error its test did not `allow`."""
    context = browser.new_context(viewport=VIEWPORT, accept_downloads=True)
    page = context.new_page()
    page.set_default_timeout(30_000)
    studio = Studio(page, f"http://127.0.0.1:{port}")
    try:
        studio.open()
        yield studio
        assert studio.unexpected_errors() == []
    finally:
        context.close()


def simulate(mechanism: dict[str, Any]) -> np.ndarray:
    """The engine's trajectories of `mechanism` over STEPS steps, as the studio asks for them."""
    import links_ray

    return links_ray.simulate(
        mechanism["adjacency"], mechanism["node_types"], mechanism["positions"], STEPS
    )


def assert_assembled(mechanism: dict[str, Any], trajectories: np.ndarray) -> None:
    """Every pose keeps every link's length, the crank turns by 2 pi / STEPS a step, and each
    solved joint stays on its starting side of its two parents: the dyad has one solution."""
    from links_ray.engine.kinematics.mechanism import analyze_topology

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
