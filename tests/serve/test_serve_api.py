"""The links app's routes over real HTTP: health, the OpenAPI document (the one the docs are
made from), and the limits it states and enforces.

The `client` fixture's app (tests/support/serve_app.py, shared with the other HTTP and studio
tests) serves the lean twin of the 300-mechanism `dataset` (tests/support/datasets.py); every
request goes, with `http.client`, to the port the replica answers on itself, as under `links
serve`. The studio's page and files are tested in test_studio_page.py.
"""

import json
import math
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np

from links_ray.engine import inputs
from links_ray.engine.fabrication import limits as fabrication_limits
from links_ray.engine.synthesis import options as synthesis_options
from links_ray.serve.http import limits as http_limits
from tests.support.serving import FOUR_BAR, Client

REPO = Path(__file__).resolve().parents[2]


def test_the_app_serves_the_lean_twin_of_the_stored_dataset(
    lean_dataset: str, dataset: str
) -> None:
    """Every test here talks to a root of mechanisms and curated ids, and compares what it
    answers with `dataset`, which stores every table."""
    from links_ray.data.derived import derived_tables
    from links_ray.data.store import Store

    assert derived_tables(Store.open(lean_dataset)) == ("simulations", "paths", "curated")
    assert derived_tables(Store.open(dataset)) == ()


def test_health_counts_the_curated_paths(client: Client, curated: Any) -> None:
    assert client.get("/api/health") == (200, {"status": "ok", "paths": len(curated)})


def test_openapi_describes_the_routes(client: Client) -> None:
    status, spec = client.get("/openapi.json")
    assert status == 200 and spec["info"]["title"] == "links-ray"
    routes = {(path, method) for path, item in spec["paths"].items() for method in item}
    assert {
        ("/api/health", "get"),
        ("/api/limits", "get"),
        ("/api/simulate", "post"),
        ("/api/retrieve", "post"),
        ("/api/synthesize", "post"),
        ("/api/analyze", "post"),
        ("/api/export", "post"),
    } <= routes


def test_the_docs_document_is_the_served_one(client: Client) -> None:
    """`serve.http.openapi` builds, without Ray or Serve, the document a replica serves: the docs'
    HTTP reference is made from it (no `self` parameter of the routes' methods in either).
    Built as the docs hook builds it: in a fresh process that imports no Ray."""
    probe = (
        "import json, sys\n"
        "from links_ray.serve.http.asgi import api\n"
        "from links_ray.serve.http.openapi import openapi_document\n"
        "assert 'ray' not in sys.modules\n"
        "print(json.dumps(openapi_document(api.routes)))"
    )
    env = {**os.environ, "PYTHONPATH": str(REPO)}  # this checkout, whatever is installed
    done = subprocess.run(
        [sys.executable, "-c", probe], cwd=REPO, env=env, capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr
    _, spec = client.get("/openapi.json")
    assert spec == json.loads(done.stdout)
    assert "self" not in json.dumps(spec["paths"])


def schema_of(spec: dict[str, Any], ref: dict[str, Any]) -> dict[str, Any]:
    """The component a `$ref` names."""
    return spec["components"]["schemas"][ref["$ref"].rpartition("/")[2]]


def own_kind(field: dict[str, Any]) -> dict[str, Any]:
    """A field's schema but null: the first of its `anyOf` when null (its default) is one."""
    return field["anyOf"][0] if "anyOf" in field else field


def test_openapi_bodies_carry_the_engines_limits(client: Client) -> None:
    """Every API route has its request and response schemas; their bounds are the limits of
    engine/inputs.py; every refusal is documented as {"error"} (a locking simulation as
    {"error", "step", "node"}), never FastAPI's {"detail"}."""
    _, spec = client.get("/openapi.json")
    paths = spec["paths"]
    requests = {}
    for path in ("/api/simulate", "/api/retrieve", "/api/synthesize", "/api/analyze"):
        operation = paths[path]["post"]
        body = operation["requestBody"]["content"]["application/json"]["schema"]
        requests[path] = schema_of(spec, body)["properties"]
        responses = operation["responses"]
        assert schema_of(spec, responses["200"]["content"]["application/json"]["schema"])
        for status in ("400", "413", "415"):
            error = schema_of(spec, responses[status]["content"]["application/json"]["schema"])
            assert set(error["properties"]) == {"error"}, (path, status)
    for path in ("/api/health", "/api/limits"):
        ok = paths[path]["get"]["responses"]["200"]["content"]["application/json"]["schema"]
        assert schema_of(spec, ok)["properties"]
    locking = paths["/api/simulate"]["post"]["responses"]["422"]["content"]["application/json"]
    assert set(schema_of(spec, locking["schema"])["properties"]) == {"error", "step", "node"}
    assert "HTTPValidationError" not in json.dumps(spec)

    for path in ("/api/retrieve", "/api/synthesize"):
        fields = requests[path]
        points = fields["points"]
        assert (points["minItems"], points["maxItems"]) == (inputs.MIN_POINTS, inputs.MAX_POINTS)
        assert points["items"]["minItems"] == points["items"]["maxItems"] == 2
        assert points["items"]["items"]["maximum"] == inputs.MAX_COORDINATE
        k = fields["k"]
        assert (own_kind(k)["minimum"], own_kind(k)["maximum"], k["default"]) == (
            inputs.MIN_K,
            inputs.MAX_K,
            inputs.DEFAULT_K,
        )
        assert own_kind(fields["min_transmission"])["maximum"] == inputs.MAX_TRANSMISSION_DEG
    most = requests["/api/retrieve"]["max_joints"]["anyOf"][0]
    assert (most["minimum"], most["maximum"]) == (inputs.MIN_JOINTS, inputs.MAX_DATASET_JOINTS)
    seconds = requests["/api/synthesize"]["seconds"]
    assert own_kind(seconds)["exclusiveMinimum"] == 0
    assert own_kind(seconds)["maximum"] == synthesis_options.MAX_SYNTHESIS_SECONDS
    assert seconds["default"] == synthesis_options.DEFAULT_SYNTHESIS_SECONDS
    iterations = requests["/api/synthesize"]["iterations"]["anyOf"][0]
    assert (iterations["minimum"], iterations["maximum"]) == (
        1,
        synthesis_options.MAX_SYNTHESIS_ITERATIONS,
    )
    assert own_kind(requests["/api/synthesize"]["seed"])["maximum"] == synthesis_options.MAX_SEED
    for path in ("/api/simulate", "/api/analyze"):
        fields = requests[path]
        steps = fields["steps"]
        assert (own_kind(steps)["minimum"], own_kind(steps)["maximum"], steps["default"]) == (
            inputs.MIN_STEPS,
            inputs.MAX_STEPS,
            inputs.DEFAULT_STEPS,
        )
        adjacency = fields["adjacency"]
        assert adjacency["minItems"] == inputs.MIN_JOINTS
        assert adjacency["maxItems"] == http_limits.MAX_REQUEST_JOINTS
        node_types = fields["node_types"]
        assert node_types["maxItems"] == http_limits.MAX_REQUEST_JOINTS
        assert (node_types["items"]["minimum"], node_types["items"]["maximum"]) == (0, 2)
    positions = requests["/api/simulate"]["positions"]
    assert positions["maxItems"] == http_limits.MAX_REQUEST_JOINTS
    export = paths["/api/export"]["post"]
    body = export["requestBody"]["content"]["application/json"]["schema"]
    fields = schema_of(spec, body)["properties"]
    assert own_kind(fields["crank_mm"])["maximum"] == fabrication_limits.MAX_CRANK_MM
    assert fields["crank_mm"]["default"] == fabrication_limits.DEFAULT_CRANK_MM
    assert fields["format"]["enum"] == ["svg", "dxf", "table"]
    assert {"image/svg+xml", "image/vnd.dxf"} <= set(export["responses"]["200"]["content"])


def test_limits_are_the_engines_and_enforced(client: Client) -> None:
    """GET /api/limits is serve/http/limits.py's limits, and each is where requests start to be
    refused."""
    status, limits = client.get("/api/limits")
    assert status == 200 and limits == http_limits.request_limits()
    assert (limits["max_points"], limits["max_k"], limits["max_joints"]) == (
        inputs.MAX_POINTS,
        inputs.MAX_K,
        http_limits.MAX_REQUEST_JOINTS,
    )
    assert limits["max_joint_steps"] == http_limits.MAX_REQUEST_JOINT_STEPS
    assert limits["max_seconds"] == synthesis_options.MAX_SYNTHESIS_SECONDS
    assert limits["max_iterations"] == synthesis_options.MAX_SYNTHESIS_ITERATIONS
    curve = [[math.cos(t), math.sin(2 * t)] for t in np.linspace(0, 6, limits["max_points"])]
    assert client.post("/api/retrieve", {"points": curve, "k": limits["max_k"]})[0] == 200
    too_many = [*curve, [0.5, 0.5]]
    assert client.post("/api/retrieve", {"points": too_many})[0] == 400
    assert client.post("/api/retrieve", {"points": curve, "k": limits["max_k"] + 1})[0] == 400
    assert client.post("/api/retrieve", {"points": curve[:3], "k": limits["min_k"]})[0] == 200
    assert client.post("/api/retrieve", {"points": curve[:2]})[0] == 400
    steps = limits["max_joint_steps"] // 4
    assert client.post("/api/simulate", {**FOUR_BAR, "steps": steps})[0] == 200
    assert client.post("/api/simulate", {**FOUR_BAR, "steps": steps + 1})[0] == 413
