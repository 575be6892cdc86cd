"""`POST /api/kit` on the Serve app (the `client` fixture's, shared with the other HTTP tests):
the bill of materials of the Python API, the assembly as GLB and the kit as a zip, refusals as
4xx JSON (a kit past MAX_KIT_JOINTS among them), 503 past the kits a replica holds, and
health answered while kits are made. The parts themselves are tested in
tests/interop/test_parts.py.
"""

from __future__ import annotations

import http.client
import io
import json
import threading
import time
import zipfile
from typing import Any

import numpy as np
import pytest

from links_ray.bench.kit import kit_workload
from links_ray.engine.fabrication.kit import KitOptions, plan_kit
from links_ray.serve.http.limits import MAX_KIT_JOINTS, MAX_KITS
from tests.interop.test_parts import UNBUILDABLE, random_mechanism
from tests.support.needs import need_module
from tests.support.serving import FOUR_BAR, LOCKING_FOUR_BAR, Client

trimesh = need_module("trimesh", "pip install 'links-ray[build]' (the test extra)")


#: A random dataset mechanism (`links bench kit`'s 50th) that takes seconds to plan as a kit.
SLOW_KIT = 49


def plain(mechanism: dict[str, Any]) -> dict[str, Any]:
    """A mechanism as a JSON body holds it."""
    return {name: np.asarray(value).tolist() for name, value in mechanism.items()}


def post_raw(client: Client, body: Any) -> tuple[int, dict[str, str], bytes]:
    """(status, headers, body bytes) of one POST to /api/kit: the files are binary."""
    conn = http.client.HTTPConnection("127.0.0.1", client.port, timeout=120)
    try:
        conn.request("POST", "/api/kit", json.dumps(body), {"Content-Type": "application/json"})
        response = conn.getresponse()
        return response.status, {k.lower(): v for k, v in response.getheaders()}, response.read()
    finally:
        conn.close()


def test_the_bill_glb_and_zip_of_a_kit(client: Client) -> None:
    mechanism = plain(random_mechanism(4, 12))
    options = {"crank_mm": 25, "bar_width_mm": 7.5, "ground_on_base": True}
    status, data = client.post("/api/kit", {**mechanism, **options})
    assert status == 200, data
    expected = plan_kit(**mechanism, options=KitOptions(**options)).bom()
    took_ms = data.pop("took_ms")
    assert 0 < took_ms < 60_000
    assert data == json.loads(json.dumps(expected))
    assert data["crank_mm"] == 25 and data["bar_width_mm"] == 7.5 and data["base"] is not None
    # The defaults: a 20 mm crank, the sizes of KitOptions.
    status, data = client.post("/api/kit", plain(FOUR_BAR))
    assert status == 200, data
    data.pop("took_ms")
    assert data == json.loads(json.dumps(plan_kit(**FOUR_BAR).bom()))

    status, headers, glb = post_raw(client, {**mechanism, **options, "format": "glb"})
    assert status == 200 and headers["content-type"] == "model/gltf-binary"
    assert headers["content-disposition"] == (
        'attachment; filename="mechanism-12-joints-assembly.glb"'
    )
    scene = trimesh.load(io.BytesIO(glb), file_type="glb")
    nodes = {item["node"] for group in ("links", "pins", "spacers") for item in expected[group]}
    assert set(scene.graph.nodes_geometry) == nodes | {"base"}

    status, headers, packed = post_raw(client, {**mechanism, **options, "format": "zip"})
    assert status == 200 and headers["content-type"] == "application/zip"
    assert headers["content-disposition"] == 'attachment; filename="mechanism-12-joints-kit.zip"'
    with zipfile.ZipFile(io.BytesIO(packed)) as archive:
        assert sorted(archive.namelist()) == sorted(
            f"kit/{name}" for name in ["bom.json", "assembly.glb", *expected["parts"]]
        )
        assert json.loads(archive.read("kit/bom.json")) == json.loads(json.dumps(expected))
        for name in expected["parts"]:
            part = trimesh.load(io.BytesIO(archive.read(f"kit/{name}")), file_type="stl")
            assert part.is_watertight, name


def test_refusals_are_4xx_json(client: Client) -> None:
    four_bar = plain(FOUR_BAR)
    refused = [
        (plain(UNBUILDABLE), 422, "no layer plan keeps every pin clear"),
        ({**four_bar, "format": "stl"}, 400, "format must be one of bom, glb, zip, got a string"),
        ({**four_bar, "crank_mm": 0}, 400, "crank_mm must be more than 0"),
        ({**four_bar, "bar_width_mm": "8"}, 400, "bar_width_mm must be a number of millimetres"),
        ({**four_bar, "clearance_mm": -1}, 400, "clearance_mm must be from 0"),
        ({**four_bar, "ground_on_base": 1}, 400, "ground_on_base must be true or false"),
        (
            {**four_bar, "spacer_diameter_mm": 8},
            400,
            "spacer_diameter_mm must be less than bar_width_mm",
        ),
        ({**four_bar, "crank_mm": 1}, 400, "link [0, 1] is 1 mm long: its holes"),
        (
            {**four_bar, "format": "glb", "bar_width_mm": 1e-10, "spacer_diameter_mm": 9e-11}
            | {"hole_diameter_mm": 8e-11, "pin_diameter_mm": 7e-11},
            400,
            "cannot be made as a closed solid",
        ),
        ({**four_bar, "bar": 8}, 400, "unknown field 'bar'"),
        ({**four_bar, "node_types": [0, 1, 0, 1]}, 400, "joint 1 must be the actuated joint"),
        ({"format": "bom"}, 400, "missing field 'adjacency'"),
        (
            {
                "adjacency": np.eye(101, k=1, dtype=int).tolist(),
                "node_types": [0] * 101,
                "positions": [[0, 0]] * 101,
            },
            413,
            "at most 100 joints per request, got 101",
        ),
    ]
    for body, expected, words in refused:
        status, headers, data = client.request("POST", "/api/kit", body)
        assert status == expected, (status, data)
        assert headers["content-type"].startswith("application/json")
        assert set(data) == {"error"} and words in data["error"], data
    status, data = client.post("/api/kit", plain(LOCKING_FOUR_BAR))
    assert status == 422 and set(data) == {"error", "step", "node"}
    assert data["error"].endswith("it has no full turn to build")


def test_openapi_describes_the_route(client: Client) -> None:
    _, spec = client.get("/openapi.json")
    operation = spec["paths"]["/api/kit"]["post"]
    body = operation["requestBody"]["content"]["application/json"]["schema"]
    request = spec["components"]["schemas"][body["$ref"].rpartition("/")[2]]["properties"]
    # Sizes take null for their defaults: each is the first of an anyOf with null.
    crank, clearance = request["crank_mm"], request["clearance_mm"]
    assert crank["default"] == 20 and crank["anyOf"][0]["maximum"] == 1e5
    assert request["format"]["enum"] == ["bom", "glb", "zip"]
    assert clearance["anyOf"][0]["minimum"] == 0 and request["bar_width_mm"]["default"] == 8
    assert request["node_types"]["maxItems"] == MAX_KIT_JOINTS
    answers = operation["responses"]
    assert {"200", "400", "413", "415", "422", "501", "503"} <= set(answers)
    assert {"model/gltf-binary", "application/zip"} <= set(answers["200"]["content"])
    bill = answers["200"]["content"]["application/json"]["schema"]["$ref"].rpartition("/")[2]
    assert {"layers", "links", "pins", "spacers", "mm_per_unit", "origin"} <= set(
        spec["components"]["schemas"][bill]["properties"]
    )


def test_kits_past_the_limit_wait_elsewhere_and_health_is_answered(client: Client) -> None:
    """MAX_KITS kits at once, a slow one each (18 joints: about 4 s of collision check and
    layer plan here): one more is 503 with Retry-After at once, and health is answered
    meanwhile."""
    adjacency, node_types, positions = kit_workload(SLOW_KIT + 1, 0)[SLOW_KIT]
    slow = plain({"adjacency": adjacency, "node_types": node_types, "positions": positions})
    answers: list[int] = []

    def make() -> None:
        answers.append(client.post("/api/kit", slow)[0])

    makers = [threading.Thread(target=make) for _ in range(MAX_KITS)]
    for maker in makers:
        maker.start()
    time.sleep(0.5)  # both claimed their places (a body is read in milliseconds)
    start = time.perf_counter()
    status, headers, data = client.request("POST", "/api/kit", plain(FOUR_BAR))
    assert status == 503 and int(headers["retry-after"]) >= 1, data
    assert "kits are being made here" in data["error"]
    assert time.perf_counter() - start < 1.0
    worst = 0.0
    while any(maker.is_alive() for maker in makers):
        start = time.perf_counter()
        assert client.get("/api/health")[0] == 200
        worst = max(worst, time.perf_counter() - start)
        time.sleep(0.1)
    for maker in makers:
        maker.join()
    assert answers == [200] * MAX_KITS
    assert worst < 1.0
    assert client.post("/api/kit", plain(FOUR_BAR))[0] == 200  # the places are free again


@pytest.mark.parametrize("chosen", ["glb", "zip"])
def test_a_file_of_an_unbuildable_mechanism_is_refused_as_json(client: Client, chosen: str) -> None:
    status, headers, data = client.request(
        "POST", "/api/kit", {**plain(UNBUILDABLE), "format": chosen}
    )
    assert status == 422 and headers["content-type"].startswith("application/json")
    assert "no layer plan" in data["error"]


def test_a_kit_past_its_joints_is_refused_and_one_at_them_is_made(client: Client) -> None:
    """A kit of MAX_KIT_JOINTS + 1 joints is refused 400 naming the bound, before it takes
    one of the replica's places; one of MAX_KIT_JOINTS joints is the Python API's kit."""
    over = plain(random_mechanism(0, MAX_KIT_JOINTS + 1))
    status, data = client.post("/api/kit", over)
    assert status == 400, data
    assert data["error"] == (
        f"a kit is built of at most {MAX_KIT_JOINTS} joints here (MAX_KIT_JOINTS), got "
        f"{MAX_KIT_JOINTS + 1}: its layer plan would hold the server too long"
    )
    at = plain(random_mechanism(2, MAX_KIT_JOINTS))
    status, data = client.post("/api/kit", at)
    assert status == 200, data
    data.pop("took_ms")
    assert data == json.loads(json.dumps(plan_kit(**at).bom()))
