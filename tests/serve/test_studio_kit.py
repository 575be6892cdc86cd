"""The studio's kit in 3D (*Build 3D*: POST /api/kit), in Debian's Chromium against the real
Serve app (the `client` fixture's, shared with the other HTTP and studio tests).

The page is read through `window.studio.kitView` (studio/kit.js): the parts its 3D view holds
and draws, in the kit's frame (mm, z up). Where they should be is worked out here from the
mechanism and the request alone: /api/simulate's trajectories, joint 0 moved to the origin and
scaled so that the crank is `crank_mm` long, each layer `layer_thickness_mm + layer_gap_mm`
above the one below (docs/guides/building.md), plus the view's explode spacing per layer.

Screenshots go where the other test_studio_*.py files' go (LINKS_STUDIO_SCREENSHOTS, else a
temporary folder).
"""

from __future__ import annotations

import io
import json
import math
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import links_ray
from tests.interop.test_parts import UNBUILDABLE, random_mechanism
from tests.support.serving import Client
from tests.support.studio_page import Studio

STEPS = 200
CRANK_MM = 30.0
#: The page's defaults for the sizes it sends: bar 8 mm, clearance 1 mm, layer 3 mm; the
#: server's gap between layers.
BAR_MM, CLEARANCE_MM, LAYER_MM, GAP_MM = 8.0, 1.0, 3.0, 0.5
#: 12 joints on a base plate: several layers, spacers and posts, planned in under a second.
BUILDABLE = {name: np.asarray(value).tolist() for name, value in random_mechanism(4, 12).items()}
THREE_JS = "vendor/three-0.187.0/three.module.js"


def build(studio: Studio, tmp_path: Path, mechanism: dict[str, Any], base: bool) -> str:
    """Import `mechanism` into the editor and build it (`press_build`)."""
    studio.import_mechanism(tmp_path, mechanism, "kit.json")
    return press_build(studio, base)


def press_build(studio: Studio, base: bool) -> str:
    """Set a CRANK_MM crank (and the base plate), press *Build 3D* and wait for the answer;
    the kit panel's state: shown, refused or failed."""
    studio.page.get_by_test_id("crank-mm").fill(f"{CRANK_MM:g}")
    studio.page.get_by_test_id("kit-base").set_checked(base)
    studio.click("build-kit")
    panel = "document.querySelector('[data-testid=kit-panel]').dataset.state"
    studio.wait(f"() => ['shown', 'refused', 'failed'].includes({panel})")
    studio.wait_idle()
    return studio.js(f"() => {panel}")


def kit_body(mechanism: dict[str, Any], base: bool) -> dict[str, Any]:
    """What the page asks /api/kit for, written out here."""
    sizes = {"bar_width_mm": BAR_MM, "clearance_mm": CLEARANCE_MM, "layer_thickness_mm": LAYER_MM}
    return {**mechanism, "crank_mm": CRANK_MM, "ground_on_base": base, **sizes}


def in_mm(mechanism: dict[str, Any], points: np.ndarray) -> np.ndarray:
    """Points of the mechanism's plane in the kit's frame: joint 0 at the origin, the crank
    CRANK_MM long."""
    p = np.asarray(mechanism["positions"], dtype=float)
    return (points - p[0]) * CRANK_MM / math.dist(p[0], p[1])


def at_step(studio: Studio, step: int) -> dict[str, Any]:
    """Move the kit's crank slider to `step` (which pauses it) and read the parts a frame on."""
    studio.page.get_by_test_id("kit-crank").fill(str(step))
    return studio.js(
        """async () => {
          await new Promise((r) => requestAnimationFrame(r));
          await new Promise((r) => requestAnimationFrame(r));
          const kit = window.studio.kitView;
          return {step: kit.step, playing: kit.playing, explode: kit.explodeMm,
                  parts: kit.parts(), drawn: kit.drawn()};
        }"""
    )


def test_the_kit_in_3d_turns_as_the_simulation_does(
    studio: Studio, client: Client, tmp_path: Path
) -> None:
    # three.js (2 MB) loads only when a kit is first shown.
    assert not any("vendor/" in url for url in studio.requests)
    assert build(studio, tmp_path, BUILDABLE, base=True) == "shown"
    assert f"/studio/{THREE_JS}" in studio.requests

    # The bill shown is the route's for the request the page sends.
    status, expected = client.post("/api/kit", kit_body(BUILDABLE, base=True))
    assert status == 200, expected
    bom = studio.js("() => window.studio.kitView.kit.bom")
    for answer in (bom, expected):
        answer.pop("took_ms")
    assert bom == expected
    assert expected["layers"] >= 2 and expected["spacers"] and expected["base"] is not None

    # The analysis line: the layer count, and whether it is proven fewest.
    words = f"{expected['layers']} layers"
    if expected["optimal"]:
        words += ", proven fewest"
    else:
        words += f", perhaps not the fewest: at least {expected['lower_bound']}"
    assert studio.text("kit-layers").startswith(words)

    # As many parts in the view as the bill lists, each by its name and kind, each drawn.
    state = at_step(studio, 0)
    listed = {link["node"]: "link" for link in expected["links"]}
    listed |= {pin["node"]: "pin" for pin in expected["pins"]}
    listed |= {spacer["node"]: "spacer" for spacer in expected["spacers"]}
    listed[expected["base"]["node"]] = "base"
    parts = state["parts"]
    assert len(parts) == len(listed)
    assert {part["name"]: part["kind"] for part in parts} == listed
    assert state["drawn"]["calls"] == len(listed)  # one draw call a part: all in view
    assert studio.page.get_by_test_id("kit-canvas").get_attribute("data-parts") == str(len(listed))

    # Each bar at two crank steps lies on the simulation's joints, at its layer's height.
    status, simulated = client.post("/api/simulate", {**BUILDABLE, "steps": STEPS})
    assert status == 200
    truth = in_mm(BUILDABLE, np.array(simulated["trajectories"]))
    pitch = LAYER_MM + GAP_MM
    seen = {}
    for step in (37, 121):
        state = at_step(studio, step)
        assert state["step"] == step and state["playing"] is False
        assert studio.text("kit-crank-value") == f"{360 * step / STEPS:.1f}°"
        explode = state["explode"]
        assert explode > 0  # the layers are shown apart by default
        for part in state["parts"]:
            if part["kind"] == "link":
                i, j = map(int, part["name"].split("-")[1:])
                z = part["layer"] * (pitch + explode)
                np.testing.assert_allclose(part["ends"][0], [*truth[i, step], z], atol=1e-6)
                np.testing.assert_allclose(part["ends"][1], [*truth[j, step], z], atol=1e-6)
                seen[part["name"], step] = part["ends"]
            elif part["kind"] in ("pin", "spacer"):
                joint = int(part["name"].split("-")[1])
                np.testing.assert_allclose(part["position"][:2], truth[joint, step], atol=1e-6)
    # The crank has turned between the two steps: its tip is elsewhere.
    assert math.dist(seen["link-0-1", 37][1], seen["link-0-1", 121][1]) > 1.0

    # The files, from the same route: the zip holds every part, the bill and the assembly.
    with studio.page.expect_download() as download:
        studio.click("kit-zip")
    assert download.value.suggested_filename == "mechanism-12-joints-kit.zip"
    with zipfile.ZipFile(io.BytesIO(Path(download.value.path()).read_bytes())) as archive:
        names = ["bom.json", "assembly.glb", *expected["parts"]]
        assert sorted(archive.namelist()) == sorted(f"kit/{name}" for name in names)
        assert json.loads(archive.read("kit/bom.json")) == expected
    with studio.page.expect_download() as download:
        studio.click("kit-glb")
    assert download.value.suggested_filename == "mechanism-12-joints-assembly.glb"
    assert Path(download.value.path()).read_bytes()[:4] == b"glTF"
    with studio.page.expect_download() as download:
        studio.click("kit-bom")
    assert download.value.suggested_filename == "mechanism-12-joints-bom.json"
    assert json.loads(Path(download.value.path()).read_text()) == expected

    # An edit makes the plan the old mechanism's: the line says so.
    studio.start_blank()
    assert studio.text("kit-layers") == "changed since its kit was planned: press Build 3D"


def test_the_opening_four_bar_stands_on_a_base_plate(studio: Studio, shots: Path) -> None:
    """What the page opens on, built as it is: its fixed joints' pins are posts in the plate,
    which the explode spacing lowers by one step below layer 0."""
    assert press_build(studio, base=True) == "shown"
    bom = studio.js("() => window.studio.kitView.kit.bom")
    assert bom["base"]["posts"] == [0, 2]  # the crank's pivot and the rocker's
    studio.page.get_by_test_id("kit-explode").fill("2")
    state = at_step(studio, 60)
    pitch = LAYER_MM + GAP_MM
    assert state["explode"] == pytest.approx(2 * pitch)
    [plate] = [part for part in state["parts"] if part["kind"] == "base"]
    assert plate["position"][2] == pytest.approx(-pitch - 2 * pitch)
    bars = [part for part in state["parts"] if part["kind"] == "link"]
    assert len(bars) == 5 and {bar["layer"] for bar in bars} == set(range(bom["layers"]))
    studio.page.get_by_test_id("kit-panel").screenshot(path=str(shots / "studio-kit.png"))


def test_an_unbuildable_mechanism_shows_why_in_the_analysis_line(
    studio: Studio, client: Client, tmp_path: Path
) -> None:
    mechanism = {name: np.asarray(value).tolist() for name, value in UNBUILDABLE.items()}
    links_ray.simulate(**mechanism, steps=STEPS)  # it turns fully: the layers are the problem
    studio.allow("status of 422")  # Chromium logs every 4xx answer
    assert build(studio, tmp_path, mechanism, base=False) == "refused"
    status, refused = client.post("/api/kit", kit_body(mechanism, base=False))
    assert status == 422 and "no layer plan keeps every pin clear" in refused["error"]
    assert studio.text("kit-layers") == f"cannot be built: {refused['error']}"
    assert studio.page.get_by_test_id("kit-layers").get_attribute("class") == "bad"
    assert studio.js("() => window.studio.kitView.parts()") == []
    for name in ("kit-zip", "kit-glb", "kit-bom", "kit-play"):
        assert studio.page.get_by_test_id(name).is_disabled(), name


def test_vendored_files_are_served_from_the_package_and_kept(client: Client) -> None:
    status, headers, body = client.request("GET", f"/studio/{THREE_JS}")
    assert status == 200 and headers["content-type"].startswith("text/javascript")
    assert "immutable" in headers["cache-control"]
    folder = Path(links_ray.__file__).parent / "serve" / "studio"
    assert body == (folder / THREE_JS).read_text()
    # Its license ships beside it; the page needs only the scripts.
    assert (folder / "vendor" / "three-0.187.0" / "LICENSE").read_text().startswith("The MIT")
    status, _, data = client.request("GET", "/studio/vendor/three-0.187.0/LICENSE")
    assert status == 404 and data["error"]
    status, headers, _ = client.request("GET", "/studio/kit.js")
    assert status == 200 and headers["cache-control"] == "no-cache"
