"""The Ray Serve app (docs/reference/contract.md, HTTP API) on real Ray, over real HTTP on loopback.

One small dataset (300 mechanisms, generated and curated; `dataset` in support/datasets.py) and one
Serve application (`client`) serve the whole module; every request goes, with `http.client`,
to the port the replica answers on itself, as under `links serve`. The studio's page and files
are tested in test_studio.py.
"""

import contextlib
import http.client
import importlib
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

import links_ray
from links_ray.engine import inputs
from links_ray.engine.fabrication import limits as fabrication_limits
from links_ray.engine.fabrication.drawings import fabrication
from links_ray.engine.inputs import validate_query
from links_ray.engine.synthesis import options as synthesis_options
from links_ray.interop.drawings import dxf_drawing, svg_drawing
from links_ray.serve.app import bindable_port
from links_ray.serve.http import limits as http_limits
from tests.support.drawings import dxf_parts, read_dxf
from tests.support.fourbars import stretched_four_bar, window_slack
from tests.support.serving import (
    FOUR_BAR,
    LOCKING_FOUR_BAR,
    TWO_CPU_RAY,
    Client,
    as_served,
    command_line,
    descendants,
    links_serve,
    processes_mentioning,
)

REPO = Path(__file__).resolve().parents[2]
RESULT_FIELDS = {
    "path_id",
    "n_joints",
    "mechanism_id",
    "joint",
    "chamfer",
    "points",
    "mechanism",
    "mechanism_joint",
}


def _post(client: Client, path: str, body: Any) -> tuple[int, Any]:
    status, data = client.post(path, body)
    assert status == 200, data
    return status, data


# -- routes ---------------------------------------------------------------------------------


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
        assert (k["minimum"], k["maximum"], k["default"]) == (
            inputs.MIN_K,
            inputs.MAX_K,
            inputs.DEFAULT_K,
        )
        assert fields["min_transmission"]["maximum"] == inputs.MAX_TRANSMISSION_DEG
    most = requests["/api/retrieve"]["max_joints"]["anyOf"][0]
    assert (most["minimum"], most["maximum"]) == (inputs.MIN_JOINTS, inputs.MAX_DATASET_JOINTS)
    seconds = requests["/api/synthesize"]["seconds"]
    assert seconds["exclusiveMinimum"] == 0
    assert seconds["maximum"] == synthesis_options.MAX_SYNTHESIS_SECONDS
    assert seconds["default"] == synthesis_options.DEFAULT_SYNTHESIS_SECONDS
    iterations = requests["/api/synthesize"]["iterations"]["anyOf"][0]
    assert (iterations["minimum"], iterations["maximum"]) == (
        1,
        synthesis_options.MAX_SYNTHESIS_ITERATIONS,
    )
    assert requests["/api/synthesize"]["seed"]["maximum"] == synthesis_options.MAX_SEED
    for path in ("/api/simulate", "/api/analyze"):
        fields = requests[path]
        steps = fields["steps"]
        assert (steps["minimum"], steps["maximum"], steps["default"]) == (
            inputs.MIN_STEPS,
            inputs.MAX_STEPS,
            inputs.DEFAULT_STEPS,
        )
        adjacency = fields["adjacency"]
        assert adjacency["minItems"] == inputs.MIN_JOINTS
        assert adjacency["maxItems"] == http_limits.MAX_REQUEST_JOINTS
        node_types = fields["node_types"]
        assert node_types["maxItems"] == http_limits.MAX_REQUEST_JOINTS
        assert node_types["items"]["enum"] == [0, 1, 2]
    positions = requests["/api/simulate"]["positions"]
    assert positions["maxItems"] == http_limits.MAX_REQUEST_JOINTS
    export = paths["/api/export"]["post"]
    body = export["requestBody"]["content"]["application/json"]["schema"]
    fields = schema_of(spec, body)["properties"]
    assert fields["crank_mm"]["maximum"] == fabrication_limits.MAX_CRANK_MM
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


def test_a_replica_keeps_to_its_num_cpus(ray_cluster: str) -> None:
    """A replica's threads are the CPUs Ray gave it (whole, at least 1), not the machine's
    cores: read as the app's replicas read them (`use_replica_cpus`, in their constructors),
    in Ray actors given what a replica's `ray_actor_options` give (a Serve replica is one;
    under direct ingress a second app would find no port for its own)."""
    import ray

    from links_ray.serve.deployments import use_replica_cpus

    @ray.remote
    class Replica:
        def __init__(self) -> None:
            use_replica_cpus()

        def cpus(self) -> tuple[float | None, int]:
            from links_ray.engine.cpus import given_cpus, usable_cpus

            return given_cpus(), usable_cpus()

    for num_cpus, expected in ((0.5, (0.5, 1)), (1, (1.0, 1)), (0, (0.0, 1))):
        replica = Replica.options(num_cpus=num_cpus).remote()
        try:
            assert ray.get(replica.cpus.remote(), timeout=120) == expected
        finally:
            ray.kill(replica)


@pytest.mark.parametrize("steps", [None, 50, 1])
def test_simulate_matches_the_engine(client: Client, steps: int | None) -> None:
    body = FOUR_BAR if steps is None else {**FOUR_BAR, "steps": steps}
    _, data = _post(client, "/api/simulate", body)
    expected = links_ray.simulate(
        FOUR_BAR["adjacency"], FOUR_BAR["node_types"], FOUR_BAR["positions"], steps or 200
    )
    got = np.array(data["trajectories"])
    assert got.shape == expected.shape == (4, steps or 200, 2)
    np.testing.assert_array_equal(got, expected)  # JSON round-trips float64 exactly


def test_simulate_locking_is_422_with_step_and_node(client: Client) -> None:
    with pytest.raises(links_ray.LockingError) as locked:
        links_ray.simulate(**LOCKING_FOUR_BAR)
    status, data = client.post("/api/simulate", LOCKING_FOUR_BAR)
    assert status == 422
    assert data == {"error": "locking", "step": locked.value.step, "node": locked.value.node}


def test_simulate_locking_between_steps_is_422(client: Client) -> None:
    """A four-bar that assembles at all 200 steps but locks between steps 37 and 38."""
    four_bar = stretched_four_bar(37, 200, window_slack(200))
    body = {name: value.tolist() for name, value in four_bar.items()}
    status, data = client.post("/api/simulate", body)
    assert status == 422
    assert data == {"error": "locking", "step": 38, "node": 3}


# -- /api/export: fabrication files ------------------------------------------------------------


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
        _check_error(status, headers, data, expected, words)
    big = {
        "adjacency": np.eye(101, k=1, dtype=int).tolist(),
        "node_types": [0] * 101,
        "positions": [[0, 0]] * 101,
    }
    status, headers, data = client.request("POST", "/api/export", big)
    _check_error(status, headers, data, 413, "at most 100 joints per request, got 101")
    status, headers, data = client.request("POST", "/api/export", {"format": "svg"})
    _check_error(status, headers, data, 400, "missing field 'adjacency'")


def _check_result(result: dict[str, Any]) -> None:
    assert set(result) >= RESULT_FIELDS
    mechanism = result["mechanism"]
    assert set(mechanism) >= {"adjacency", "node_types", "positions"}
    n = len(mechanism["node_types"])
    assert np.array(mechanism["adjacency"]).shape == (n, n)
    assert np.array(mechanism["positions"]).shape == (n, 2)
    assert 0 <= result["mechanism_joint"] < n
    assert result["n_joints"] == n
    assert np.array(result["points"]).shape == (200, 2)
    assert isinstance(result["chamfer"], float) and result["chamfer"] >= 0


@pytest.mark.parametrize("where", ["as stored", "moved and scaled", "turned", "mirrored"])
def test_retrieve_finds_a_stored_path_and_a_mechanism_that_traces_it(
    client: Client, curated: Any, where: str
) -> None:
    row = 17 % len(curated)
    stored = curated.points.iloc[row].astype(np.float64)
    query = {
        "as stored": stored,
        "moved and scaled": stored * 3.0 + 7.0,
        "turned": (stored - 0.5) @ np.array([[0.0, -1.0], [1.0, 0.0]]) * 0.2 + 1.0,
        "mirrored": stored * np.array([1.0, -1.0]) + 2.0,
    }[where]
    _, data = _post(client, "/api/retrieve", {"points": query.tolist(), "k": 5})
    results = data["results"]
    assert isinstance(data["took_ms"], float) and data["took_ms"] >= 0
    assert len(results) == 5
    for result in results:
        _check_result(result)
    chamfers = [result["chamfer"] for result in results]
    assert chamfers == sorted(chamfers), "best first"
    assert chamfers[0] < 1e-6
    best = results[0]
    assert best["path_id"] == int(curated.path_id.iloc[row]) or chamfers[1] < 1e-6
    # A floor on the transmission angle: only paths keeping it, the best of them first.
    floor = 5.0
    _, kept = _post(
        client, "/api/retrieve", {"points": query.tolist(), "k": 5, "min_transmission": floor}
    )
    keeping = [r for r in results if r["min_transmission_deg"] >= floor]
    assert len(kept["results"]) == 5
    assert all(r["min_transmission_deg"] >= floor for r in kept["results"])
    assert [r["path_id"] for r in kept["results"]][: len(keeping)] == [
        r["path_id"] for r in keeping
    ]
    # The mechanism comes back in the query's frame: its joint traces the query itself.
    _, traced = _post(client, "/api/simulate", best["mechanism"])
    path = np.array(traced["trajectories"])[best["mechanism_joint"]]
    size = np.ptp(query, axis=0).max()
    assert links_ray.chamfer(path, query) < 1e-4 * size


def test_retrieve_keeps_to_mechanisms_of_at_most_max_joints(
    client: Client, dataset_index: Any, queries: list
) -> None:
    """`max_joints` reaches the index: one index's answer kept to paths whose reduced
    mechanism has at most that many joints (tests/search/test_retrieval.py holds that against brute
    force), each saying its count; null keeps none out; a limit below every path's, none."""
    counts = dataset_index.n_joints
    most = int(np.median(counts))
    for query in queries[:3]:
        body = {"points": np.asarray(query).tolist(), "k": 5}
        _, data = _post(client, "/api/retrieve", {**body, "max_joints": most})
        expected = as_served(dataset_index.retrieve(query, 5, max_joints=most))
        assert len(expected) == 5 and data["results"] == expected
        assert all(result["n_joints"] <= most for result in data["results"])
        _, unrestricted = _post(client, "/api/retrieve", {**body, "max_joints": None})
        assert unrestricted["results"] == as_served(dataset_index.retrieve(query, 5))
    smallest = int(counts.min())
    if smallest > inputs.MIN_JOINTS:
        _, data = _post(client, "/api/retrieve", {**body, "max_joints": smallest - 1})
        assert data["results"] == []
    _, data = _post(client, "/api/retrieve", {**body, "max_joints": smallest})
    assert data["results"] and {r["n_joints"] for r in data["results"]} == {smallest}


def test_retrieve_default_k_and_longest_query(client: Client, curated: Any) -> None:
    stored = curated.points.iloc[0].astype(np.float64)
    _, data = _post(client, "/api/retrieve", {"points": stored.tolist()})
    assert len(data["results"]) == 3
    many = np.tile(stored, (50, 1))  # exactly 10,000 pairs
    _, data = _post(client, "/api/retrieve", {"points": many.tolist(), "k": 1})
    assert data["results"][0]["chamfer"] < 1e-6


@pytest.mark.parametrize("length", [200, 3])
def test_retrieve_gives_k_results_when_the_index_has_them(
    client: Client, curated: Any, length: int
) -> None:
    stored = curated.points.iloc[0].astype(np.float64)[:length]
    _, data = _post(client, "/api/retrieve", {"points": stored.tolist(), "k": 100})
    assert len(curated) >= 100
    chamfers = [result["chamfer"] for result in data["results"]]
    assert len(chamfers) == 100
    assert chamfers == sorted(chamfers)
    assert len({result["path_id"] for result in data["results"]}) == 100


# -- bad input: always a 4xx with a JSON error, never a 5xx -------------------------------------

LIMIT = 2 * 1024 * 1024
POINTS = [[0.0, 0.0], [1.0, 0.5], [2.0, 0.0], [3.0, 1.0]]
FOUR_BAR_JSON = json.dumps(FOUR_BAR)


def bad(name: str, path: str, body: Any, words: str, status: int = 400, **request: Any) -> Any:
    """One bad request: a JSON-able body, or raw bytes sent as they are; `words` must be in the
    error message."""
    method = request.pop("method", "POST")
    headers = request.pop("headers", {})
    return pytest.param(method, path, body, headers, status, words, id=name)


def sim(name: str, words: str, status: int = 400, **changes: Any) -> Any:
    """A four-bar simulation with some fields replaced."""
    return bad(name, "/api/simulate", {**FOUR_BAR, **changes}, words, status)


def ret(name: str, words: str, status: int = 400, **body: Any) -> Any:
    """A retrieval with this body."""
    return bad(name, "/api/retrieve", body, words, status)


def sim_raw(name: str, text: str, words: str) -> Any:
    """The four-bar's JSON with 0.8 (a coordinate of joint 2) replaced by `text`."""
    return bad(name, "/api/simulate", FOUR_BAR_JSON.replace("0.8", text).encode(), words)


def ret_raw(name: str, text: str, words: str, route: str = "/api/retrieve") -> Any:
    """A body written out by hand (PTS stands for the points), posted to `route`."""
    return bad(name, route, text.replace("PTS", json.dumps(POINTS)).encode(), words)


#: Deeper than the parser reads, in fewer brackets than a body may hold.
NESTED = "[" * 2_000 + "]" * 2_000
JUNK_ROWS = [[[0], {"a": [1]}, "x", None]] * 4
PAD = "x" * LIMIT
NOT_JSON = "the body is not valid JSON"
OVER_LIMIT = f"the body is over the limit of {LIMIT} bytes"
BAD_REQUESTS = [
    # Not a JSON object.
    bad("invalid JSON", "/api/simulate", b"{adjacency: [", f"{NOT_JSON}: Expecting property name"),
    ret_raw("truncated JSON", '{"points": [[0, 0],', f"{NOT_JSON}: Expecting value"),
    ret_raw("empty body", "", "the body is empty: expected a JSON object"),
    bad("not UTF-8", "/api/retrieve", b'{"points": "\xff\xfe"}', "the body is not UTF-8 text"),
    ret_raw("array body", json.dumps([POINTS]), "the body must be a JSON object, got an array"),
    ret_raw("null body", "null", "the body must be a JSON object, got null"),
    bad("number body", "/api/simulate", 3, "the body must be a JSON object, got a number"),
    bad("string body", "/api/simulate", "adjacency", "must be a JSON object, got a string"),
    ret_raw("deep nesting", '{"k": ' + NESTED + "}", f"{NOT_JSON}: nested too deeply"),
    ret_raw(
        "50,000 brackets",
        '{"k": ' + "[" * 50_000 + "]" * 50_000 + "}",
        "the body holds 50001 brackets, more arrays and objects than any /api/retrieve body",
    ),
    bad(
        "text/plain",
        "/api/retrieve",
        b"{}",
        "the body must be JSON, sent as Content-Type application/json: got 'text/plain'",
        415,
        headers={"Content-Type": "text/plain"},
    ),
    bad(
        "form",
        "/api/simulate",
        b"a=1",
        "got 'multipart/form-data'",
        415,
        headers={"Content-Type": "multipart/form-data"},
    ),
    # What a page of another site can post without a preflight: no type, or a plain one.
    bad(
        "no Content-Type",
        "/api/curve",
        json.dumps({"name": "a.json", "text": "[[0,0],[1,1],[2,0]]"}).encode(),
        "sent as Content-Type application/json: none was given",
        415,
        headers={"Content-Type": None},
    ),
    bad(
        "urlencoded",
        "/api/synthesize",
        json.dumps({"points": POINTS}).encode(),
        "got 'application/x-www-form-urlencoded'",
        415,
        headers={"Content-Type": "application/x-www-form-urlencoded"},
    ),
    # Numbers past float64, in every field that takes a number; the lone surrogate once sent
    # such a body to a second parser, which read them as exact integers.
    *(
        ret_raw(f"{digits}-digit {field}", text.replace("BIG", "1" + "0" * digits), words, route)
        for digits in (310, 4300)
        for field, text, route in (
            ("seconds", '{"points": PTS, "seconds": BIG, "id": "\\ud800"}', "/api/synthesize"),
            ("min_transmission", '{"points": PTS, "min_transmission": BIG}', "/api/retrieve"),
            ("timing", '{"points": PTS, "timing": [0, BIG, 2, 3]}', "/api/synthesize"),
            (
                "box",
                '{"points": PTS, "constraints": {"pivots": [0, 0, BIG, 1]}}',
                "/api/synthesize",
            ),
            ("crank_mm", FOUR_BAR_JSON[:-1] + ', "crank_mm": BIG}', "/api/export"),
            ("k", '{"points": PTS, "k": BIG}', "/api/retrieve"),
        )
        for words in ("number is infinity when parsed as double",)
    ),
    # /api/simulate: missing fields, wrong types, wrong shapes, limits.
    bad("missing all", "/api/simulate", {}, "missing field 'adjacency'"),
    bad(
        "missing positions",
        "/api/simulate",
        {k: FOUR_BAR[k] for k in ("adjacency", "node_types")},
        "missing field 'positions'",
    ),
    sim(
        "adjacency string",
        "adjacency must be an n x n array of 0/1, got a string",
        adjacency="0110",
    ),
    sim(
        "adjacency strings",
        "adjacency[0][0] must be 0 or 1, got a string",
        adjacency=[["0", "1"], ["1", "0"]],
    ),
    sim(
        "adjacency nested junk", "adjacency[0][0] must be 0 or 1, got an array", adjacency=JUNK_ROWS
    ),
    sim(
        "adjacency not square",
        "adjacency[0] must hold 4 entries (one per joint), got 3",
        adjacency=[row[:3] for row in FOUR_BAR["adjacency"]],
    ),
    sim(
        "adjacency empty",
        "adjacency must be an n x n array of 0/1, got an empty array",
        adjacency=[],
    ),
    sim(
        "adjacency asymmetric",
        "adjacency is not symmetric: [2, 3] = 1 but [3, 2] = 0",
        adjacency=[[0, 1, 0, 0], [1, 0, 0, 1], [0, 0, 0, 1], [0, 1, 0, 0]],
    ),
    sim(
        "adjacency booleans",
        "adjacency[0][0] must be 0 or 1, got a boolean",
        adjacency=[[x == 1 for x in r] for r in FOUR_BAR["adjacency"]],
    ),
    sim(
        "node_types object",
        "node_types must be an array of 4 numbers, got an object",
        node_types={"0": 0},
    ),
    sim(
        "node_types short",
        "node_types must hold 4 entries (one per joint), got 3",
        node_types=[0, 2, 0],
    ),
    sim(
        "no actuated joint",
        "joint 1 must be the actuated joint (2), got 1",
        node_types=[0, 1, 0, 1],
    ),
    sim(
        "positions triples",
        "positions[0] must be an [x, y] pair, got 3 entries",
        positions=[[0.5, 0.5, 0.0]] * 4,
    ),
    sim(
        "positions null",
        "positions[0] must hold two numbers, got null",
        positions=[[0.5, None]] * 4,
    ),
    sim(
        "positions too few",
        "positions must hold 4 [x, y] pairs (one per joint), got 3",
        positions=FOUR_BAR["positions"][:3],
    ),
    sim(
        "zero-length crank",
        "the crank has zero length: joints 0 and 1 are closer than 1e-09",
        positions=[[0.5, 0.5], [0.5, 0.5], [0.8, 0.5], [0.6, 0.7]],
    ),
    sim_raw("NaN literal", "NaN", f"{NOT_JSON}: NaN is not a JSON number"),
    sim_raw("Infinity literal", "Infinity", f"{NOT_JSON}: Infinity is not a JSON number"),
    sim_raw("overflow to inf", "1e999", f"{NOT_JSON}: number is infinity when parsed as double"),
    sim_raw("integer beyond float", "9" * 400, "number is infinity when parsed as double"),
    sim("steps string", "steps must be an integer from 1 to 100000, got '200'", steps="200"),
    sim("steps true", "steps must be an integer from 1 to 100000, got True", steps=True),
    sim("steps float", "steps must be an integer from 1 to 100000, got 200.5", steps=200.5),
    sim("steps 0", "steps must be from 1 to 100000, got 0", steps=0),
    sim("steps huge", "steps must be from 1 to 100000, got 1000000000000", steps=10**12),
    sim(
        "huge simulation",
        "simulation too large: 4 joints x 100000 steps = 400000, the limit is 100000 joint-steps",
        413,
        steps=100_000,
    ),
    bad(
        "too many joints",
        "/api/simulate",
        {"adjacency": [[0] * 101] * 101, "node_types": [0] * 101, "positions": [[0, 0]] * 101},
        "at most 100 joints per request, got 101",
        413,
    ),
    # /api/retrieve: points and k.
    ret("missing points", "missing field 'points'", k=3),
    ret(
        "points string",
        "points must be an array of [x, y] pairs, got a string",
        points="0,0 1,1 2,0",
    ),
    ret(
        "points strings",
        "points[0] must hold two numbers, got a string",
        points=[["0", "0"], ["1", "1"], ["2", "0"]],
    ),
    ret(
        "points nested junk",
        "points[0] must be an [x, y] pair, got 1 entries",
        points=[[[0, 0]], {"x": 1}, [None, []]],
    ),
    ret(
        "points objects",
        "points[0] must be an [x, y] pair, got an object",
        points=[{"x": 0, "y": 0}] * 3,
    ),
    ret(
        "points triples",
        "points[0] must be an [x, y] pair, got 3 entries",
        points=[[0, 0, 0], [1, 1, 1], [2, 0, 0]],
    ),
    ret(
        "points booleans",
        "points[0] must hold two numbers, got a boolean",
        points=[[True, False], [1, 1], [2, 0]],
    ),
    ret("2 pairs", "points must hold 3 to 10000 pairs, got 2", points=POINTS[:2]),
    ret(
        "10,001 pairs",
        "points must hold 3 to 10000 pairs, got 10001",
        points=[[i, i % 7] for i in range(10_001)],
    ),
    ret(
        "all one point",
        "points are all the same point: there is no curve",
        points=[[0.3, 0.4]] * 50,
    ),
    ret_raw(
        "NaN", '{"points": [[NaN, 0], [1, 1], [2, 0]]}', f"{NOT_JSON}: NaN is not a JSON number"
    ),
    ret_raw(
        "Infinity", '{"points": [[0, 0], [1, Infinity], [2, 0]]}', "Infinity is not a JSON number"
    ),
    ret_raw(
        "-Infinity",
        '{"points": [[0, 0], [1, -Infinity], [2, 0]]}',
        "-Infinity is not a JSON number",
    ),
    ret_raw(
        "overflow to inf",
        '{"points": [[0, 0], [1, 1e999], [2, 0]]}',
        f"{NOT_JSON}: number is infinity when parsed as double",
    ),
    ret_raw(
        "integer beyond float",
        '{"points": [[0, 0], [1, ' + "9" * 400 + "], [2, 0]]}",
        f"{NOT_JSON}: number is infinity when parsed as double",
    ),
    ret(
        "coordinates huge",
        "points must lie within +-1e+12",
        points=[[0, 0], [1e300, 0], [0, 1e300]],
    ),
    ret(
        "extent tiny",
        "points span less than 1e-09: there is no curve to match",
        points=[[0, 0], [1e-300, 0], [0, 1e-300]],
    ),
    ret("k 0", "k must be from 1 to 100, got 0", points=POINTS, k=0),
    ret("k 101", "k must be from 1 to 100, got 101", points=POINTS, k=101),
    ret("k -1", "k must be from 1 to 100, got -1", points=POINTS, k=-1),
    ret("k true", "k must be an integer from 1 to 100, got True", points=POINTS, k=True),
    ret("k string", "k must be an integer from 1 to 100, got '3'", points=POINTS, k="3"),
    ret("k float", "k must be an integer from 1 to 100, got 2.5", points=POINTS, k=2.5),
    ret("k array", "k must be an integer from 1 to 100, got [3]", points=POINTS, k=[3]),
    ret(
        "min_transmission 50",
        "min_transmission must be from 0 to 45 degrees, got 50",
        points=POINTS,
        min_transmission=50,
    ),
    ret(
        "min_transmission text",
        "min_transmission must be a number of degrees, got '5'",
        points=POINTS,
        min_transmission="5",
    ),
    ret("max_joints 1", "max_joints must be from 2 to 20, got 1", points=POINTS, max_joints=1),
    ret("max_joints 21", "max_joints must be from 2 to 20, got 21", points=POINTS, max_joints=21),
    ret(
        "max_joints text",
        "max_joints must be an integer from 2 to 20, got '6'",
        points=POINTS,
        max_joints="6",
    ),
    ret(
        "max_joints float",
        "max_joints must be an integer from 2 to 20, got 6.5",
        points=POINTS,
        max_joints=6.5,
    ),
    ret(
        "max_joints true",
        "max_joints must be an integer from 2 to 20, got True",
        points=POINTS,
        max_joints=True,
    ),
    # Size limits and routes.
    ret("oversized body", OVER_LIMIT, 413, points=POINTS, pad=PAD),
    ret(
        "oversized points",
        OVER_LIMIT,
        413,
        points=[[0.123456789012345678, i * 1e-3] for i in range(80_000)],
    ),
    # A field a route does not take is refused by name, never dropped: a misspelled option
    # would otherwise be ignored without the client knowing.
    ret(
        "misspelled k",
        "unknown field 'K': /api/retrieve takes points, k, min_transmission",
        points=POINTS,
        K=3,
    ),
    bad(
        "unknown field simulate", "/api/simulate", {**FOUR_BAR, "bogus": 1}, "unknown field 'bogus'"
    ),
    bad(
        "unknown field analyze",
        "/api/analyze",
        {"adjacency": FOUR_BAR["adjacency"], "node_types": FOUR_BAR["node_types"], "step": 9},
        "unknown field 'step'",
    ),
    bad("unknown field export", "/api/export", {**FOUR_BAR, "crank": 20}, "unknown field 'crank'"),
    bad(
        "unknown field synthesize",
        "/api/synthesize",
        {"points": POINTS, "max_joint": 6},
        "unknown field 'max_joint': /api/synthesize takes points, k, min_transmission, seconds",
    ),
    bad(
        "unknown constraint",
        "/api/synthesize",
        {"points": POINTS, "constraints": {"pivot": [0, 0, 1, 1]}},
        "unknown constraint 'pivot': constraints are pivots, footprint, max_link_ratio",
    ),
    bad(
        "bad pivot box",
        "/api/synthesize",
        {"points": POINTS, "constraints": {"pivots": [1, 0, 0, 1]}},
        "pivots must have xmin < xmax and ymin < ymax",
    ),
    bad(
        "min_link above max_link",
        "/api/synthesize",
        {"points": POINTS, "constraints": {"min_link": 2, "max_link": 1}},
        "min_link (2) must not exceed max_link (1)",
    ),
    bad(
        "timing count",
        "/api/synthesize",
        {"points": POINTS, "timing": [0, 10]},
        f"timing must give one angle per point: {len(POINTS)}, got 2",
    ),
    bad(
        "timing true on a stroke",
        "/api/synthesize",
        {"points": POINTS, "timing": True, "partial": True},
        "timing=true spreads the points over a whole turn",
    ),
    bad("front not a flag", "/api/synthesize", {"points": POINTS, "front": 1}, "front must be"),
    bad(
        "max_joints too small",
        "/api/synthesize",
        {"points": POINTS, "max_joints": 1},
        "max_joints must be from 2 to 20",
    ),
    bad("unknown route", "/api/nothing", None, "not found", 404, method="GET"),
    bad("GET simulate", "/api/simulate", None, "method not allowed", 405, method="GET"),
    bad("POST health", "/api/health", {}, "method not allowed", 405),
]


def _check_error(
    status: int, headers: dict[str, str], data: Any, expected: int, words: str
) -> None:
    assert status < 500, (status, data)
    assert status == expected, (status, data)
    assert headers.get("content-type", "").startswith("application/json")
    assert isinstance(data, dict) and set(data) == {"error"}, data
    assert words in data["error"], data["error"]


@pytest.mark.parametrize(("method", "path", "body", "headers", "expected", "words"), BAD_REQUESTS)
def test_bad_requests_get_a_4xx_json_error(
    client: Client,
    method: str,
    path: str,
    body: Any,
    headers: dict[str, str],
    expected: int,
    words: str,
) -> None:
    """Each bad request gets its status and an `error` that names its problem."""
    status, reply_headers, data = client.request(method, path, body, headers)
    _check_error(status, reply_headers, data, expected, words)


def test_error_messages_name_the_problem(client: Client) -> None:
    """The messages are the engine's own, word for word: one validator for Python and HTTP."""
    cases = [
        ({"points": POINTS[:2]}, "points must hold 3 to 10000 pairs, got 2"),
        ({"points": POINTS, "k": 101}, "k must be from 1 to 100, got 101"),
        ({"points": [[0.3, 0.4]] * 5}, "points are all the same point: there is no curve"),
    ]
    for body, message in cases:
        status, data = client.post("/api/retrieve", body)
        with pytest.raises(ValueError) as refused:
            validate_query(body["points"], body.get("k", 3))
        assert str(refused.value) == message
        assert (status, data) == (400, {"error": message})
    status, data = client.post("/api/retrieve", {"k": 3})
    assert (status, data) == (400, {"error": "missing field 'points'"})
    wrong = {**FOUR_BAR, "node_types": [0, 1, 0, 1]}
    status, data = client.post("/api/simulate", wrong)
    with pytest.raises(links_ray.InvalidMechanismError) as refused:
        links_ray.simulate(**wrong)
    assert (status, data) == (400, {"error": str(refused.value)})
    assert "joint 1 must be the actuated joint (2), got 1" in data["error"]


def test_oversized_body_without_content_length(client: Client) -> None:
    """A chunked body is counted as it arrives."""
    body = json.dumps({"points": POINTS, "pad": PAD}).encode()
    status, headers, data = client.request("POST", "/api/retrieve", body, chunked=True)
    _check_error(status, headers, data, 413, OVER_LIMIT)
    small = json.dumps({"points": POINTS, "k": 2}).encode()
    status, _, data = client.request("POST", "/api/retrieve", small, chunked=True)
    assert status == 200 and len(data["results"]) == 2


def test_lying_content_length_is_refused(client: Client) -> None:
    status, headers, data = client.request(
        "POST", "/api/retrieve", b'{"points": []}', {"Content-Length": str(10 * LIMIT)}
    )
    # The header is checked before the body is read: refused at once, no waiting.
    _check_error(status, headers, data, 413, OVER_LIMIT)


def test_large_answers_render_in_pieces_as_one_call_would() -> None:
    """`render_json` gives the bytes one `json.dumps` call gives (JsonResponse's), for answers
    of every shape, in pieces of at most about JSON_PIECE_NUMBERS numbers."""
    from links_ray.serve.http.responses import JSON_PIECE_NUMBERS, _dumps, _json_pieces, render_json

    rng = np.random.default_rng(3)
    trajectories = rng.uniform(-1, 1, (100, 1000, 2))
    results = [
        {"path_id": i, "points": rng.random((200, 2)).tolist(), "chamfer": np.float64(i / 7)}
        for i in range(100)
    ]
    for content in (
        {"trajectories": trajectories},
        {"trajectories": trajectories.tolist(), "lock": None},
        {"results": results, "took_ms": 1.25},
        {"x": list(range(10_000)), "y": rng.random(9_001), "e": [], "d": {}},
        [[1, 2]] * 5_000,
        {"status": "ok"},
    ):
        pieces: list[bytes] = []
        _json_pieces(content, pieces)
        assert render_json(content) == b"".join(pieces) == _dumps(content)
        assert max(len(piece) for piece in pieces) < 30 * JSON_PIECE_NUMBERS
    with pytest.raises(ValueError, match="not JSON compliant"):
        render_json({"trajectories": np.full((10, 1000, 2), np.nan)})


def raw_post(port: int, length: int, pieces: list[tuple[float, bytes]]) -> dict[str, Any]:
    """POST /api/retrieve over a plain socket: headers declaring `length` body bytes at once,
    then each (pause in seconds, bytes) of `pieces`, then nothing, the connection held open.
    What came back: `seconds` from the headers to the answer's first byte, the `status`, the
    `headers`, the JSON `body`, and whether the server then `closed` the connection."""
    import socket

    sock = socket.create_connection(("127.0.0.1", port), timeout=120)
    head = (
        f"POST /api/retrieve HTTP/1.1\r\nHost: 127.0.0.1\r\n"
        f"Content-Type: application/json\r\nContent-Length: {length}\r\n\r\n"
    )
    answered = threading.Event()

    def send() -> None:
        for pause, piece in pieces:
            if answered.wait(pause):
                return
            try:
                sock.sendall(piece)
            except OSError:  # the server has closed: it answered
                return

    start = time.monotonic()
    sock.sendall(head.encode())
    sender = threading.Thread(target=send, daemon=True)
    sender.start()
    received = b""
    seconds = None
    try:
        while True:
            chunk = sock.recv(65536)
            if seconds is None:
                seconds = time.monotonic() - start
                answered.set()
            if not chunk:
                closed = True
                break
            received += chunk
            header, _, rest = received.partition(b"\r\n\r\n")
            declared = [
                int(line.split(b":", 1)[1])
                for line in header.split(b"\r\n")
                if line.lower().startswith(b"content-length:")
            ]
            if declared and len(rest) >= declared[0] and b"connection: close" not in header:
                closed = False  # a whole answer on a connection kept alive
                break
    except TimeoutError:
        closed = False
    finally:
        answered.set()
        sock.close()
    header, _, rest = received.partition(b"\r\n\r\n")
    lines = header.decode().split("\r\n")
    headers = dict(line.lower().split(": ", 1) for line in lines[1:] if ": " in line)
    return {
        "seconds": seconds,
        "status": int(lines[0].split()[1]) if lines[0] else None,
        "headers": headers,
        "body": json.loads(rest) if rest else None,
        "closed": closed,
    }


def test_a_body_that_stalls_or_trickles_is_cut_off_with_408(client: Client) -> None:
    """A body that stops coming, or trickles in a byte at a time, is answered 408 with a JSON
    error once BODY_TIMEOUT_S have passed (not before), and the connection is closed; a body
    sent in pieces with pauses shorter than that, at more than MIN_BODY_BYTES_PER_S, is
    answered as usual though it takes longer than BODY_TIMEOUT_S in all."""
    timeout, rate = http_limits.BODY_TIMEOUT_S, http_limits.MIN_BODY_BYTES_PER_S
    stall = ([(0.0, b'{"points": [[0, 0], ')], 1000)
    trickle = ([(0.0 if i == 0 else 0.25, b" ") for i in range(400)], 100_000)
    # Four pieces of 2 x rate bytes, 0.4 x timeout apart (12 s in all): each pause well within
    # the timeout, and each piece buys 2 s at the rate, so the last comes 4 s before the rate
    # would cut the body off.
    whole = json.dumps({"points": POINTS, "k": 2}).encode()
    piece = 2 * rate
    body = whole.ljust(4 * piece)
    pieces = [(0.4 * timeout if i else 0.0, body[i * piece : (i + 1) * piece]) for i in range(4)]
    paced = (pieces, len(body))
    found: dict[str, dict[str, Any]] = {}

    def run(name: str, case: tuple[list[tuple[float, bytes]], int]) -> None:
        found[name] = raw_post(client.port, case[1], case[0])

    threads = [
        threading.Thread(target=run, args=(name, case))
        for name, case in (("stall", stall), ("trickle", trickle), ("paced", paced))
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    for name in ("stall", "trickle"):
        answer = found[name]
        assert answer["status"] == 408, (name, answer)
        assert answer["headers"]["content-type"].startswith("application/json")
        assert set(answer["body"]) == {"error"}, answer
        assert answer["body"]["error"].startswith("the body came too slowly"), answer
        assert f"pause at most {timeout:g} s" in answer["body"]["error"]
        assert answer["closed"], (name, answer)
        # Not before the timeout; the upper bound is loose, for a busy machine.
        assert timeout - 0.5 <= answer["seconds"] < timeout + 20, (name, answer)
    answer = found["paced"]
    assert answer["status"] == 200 and len(answer["body"]["results"]) == 2, answer
    assert answer["seconds"] > timeout, answer
    assert client.get("/api/health")[0] == 200


def test_the_worst_small_drawings_are_answered_and_health_stays_up(client: Client) -> None:
    """The drawings that once froze a replica for minutes or filled its memory (`links bench
    hostile` sends the same) are each answered: read, or refused 413 naming the limit they
    pass; health is answered between them, and the replica's readers are ready for more."""
    from links_ray.bench.hostile_inputs import hostile_drawings

    expected = {
        "style 40,000 chars": 200,
        "style 300,000 chars": 200,
        "uses 5 levels": 413,
        "uses 6 levels": 413,
        "bulges 1,000 vertices": 200,
        "spline 1,000 fit points": 200,
    }
    drawings = hostile_drawings()
    assert set(drawings) == set(expected)
    for what, (name, text) in drawings.items():
        status, data = client.post("/api/curve", {"name": name, "text": text})
        assert status == expected[what], (what, status, data)
        if status == 413:
            assert "MAX_SVG_ELEMENTS" in data["error"] or "10,000" in data["error"], data
        else:
            assert len(data["points"]) == 400 and np.isfinite(data["points"]).all()
        assert client.get("/api/health")[0] == 200
    status, data = client.post("/api/curve", {"name": "a.csv", "text": "0,0\n1,1\n2,0\n"})
    assert status == 200 and len(data["points"]) == 400


def test_clients_that_send_only_headers_hold_no_place(client: Client, curated: Any) -> None:
    """Ten clients that send a retrieval's headers and never its body each get 408 once
    BODY_TIMEOUT_S have passed, and meanwhile an eleventh, real retrieval is answered 200:
    a place among a replica's MAX_RETRIEVALS is claimed only once a body has been read."""
    from links_ray.serve.http.limits import MAX_RETRIEVALS

    timeout = http_limits.BODY_TIMEOUT_S
    silent = MAX_RETRIEVALS + 2
    found: list[dict[str, Any]] = []
    lock = threading.Lock()

    def headers_only() -> None:
        answer = raw_post(client.port, 100, [])
        with lock:
            found.append(answer)

    threads = [threading.Thread(target=headers_only) for _ in range(silent)]
    for thread in threads:
        thread.start()
    time.sleep(1.0)  # every one of them has sent its headers and waits
    status, data = client.post("/api/retrieve", {"points": curated.points.iloc[0].tolist()})
    assert status == 200 and len(data["results"]) == 3, (status, data)
    for thread in threads:
        thread.join()
    assert len(found) == silent
    for answer in found:
        assert answer["status"] == 408, answer
        assert answer["body"]["error"].startswith("the body came too slowly (0 bytes"), answer
        assert answer["closed"], answer
        assert timeout - 0.5 <= answer["seconds"] < timeout + 20, answer


def test_still_serving_after_bad_requests(client: Client, curated: Any) -> None:
    from ray import serve

    assert client.get("/api/health") == (200, {"status": "ok", "paths": len(curated)})
    app = serve.status().applications["links"]
    assert app.status == "RUNNING"
    assert _post(client, "/api/simulate", FOUR_BAR)[0] == 200


# -- load -----------------------------------------------------------------------------------


def test_concurrent_clients(client: Client, curated: Any) -> None:
    """8 threads x 25 requests (retrieve, simulate, health), each thread on a kept-alive
    connection: every answer is 200 and correct, and every thread finishes (a hang fails the
    join's bound of 120 s, far above the seconds this takes on a busy machine)."""
    queries = [curated.points.iloc[i % len(curated)].astype(float).tolist() for i in range(8)]
    expected_sim = links_ray.simulate(**FOUR_BAR).tolist()
    failures: list[str] = []
    latencies: list[float] = []
    lock = threading.Lock()

    def worker(t: int) -> None:
        conn = http.client.HTTPConnection("127.0.0.1", client.port, timeout=60)
        try:
            for i in range(25):
                kind = ("retrieve", "simulate", "health")[(t + i) % 3]
                start = time.perf_counter()
                if kind == "retrieve":
                    status, _, data = client.request(
                        "POST", "/api/retrieve", {"points": queries[t], "k": 3}, connection=conn
                    )
                    ok = status == 200 and data["results"][0]["chamfer"] < 1e-6
                elif kind == "simulate":
                    status, _, data = client.request(
                        "POST", "/api/simulate", FOUR_BAR, connection=conn
                    )
                    ok = status == 200 and data["trajectories"] == expected_sim
                else:
                    status, _, data = client.request("GET", "/api/health", connection=conn)
                    ok = status == 200 and data["paths"] == len(curated)
                with lock:
                    latencies.append(time.perf_counter() - start)
                    if not ok:
                        failures.append(f"thread {t} request {i} {kind}: {status}")
        except Exception as exc:  # a dropped connection is a failure too
            with lock:
                failures.append(f"thread {t}: {type(exc).__name__}: {exc}")
        finally:
            conn.close()

    start = time.perf_counter()
    threads = [threading.Thread(target=worker, args=(t,)) for t in range(8)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=120)
    elapsed = time.perf_counter() - start
    assert not any(thread.is_alive() for thread in threads)
    assert not failures, failures[:5]
    assert len(latencies) == 200
    print(
        f"\n200 requests from 8 threads in {elapsed:.2f} s "
        f"(p50 {np.median(latencies) * 1e3:.0f} ms, max {max(latencies) * 1e3:.0f} ms)"
    )


# -- deployment configs ---------------------------------------------------------------------


def test_app_builder_args(dataset: str, tmp_path: Path) -> None:
    from ray.serve.deployment import Application

    from links_ray.serve.app import app_builder, build_app

    assert isinstance(app_builder({"root": dataset, "replicas": "2"}), Application)
    sharded = {"shards": "3", "shard_cpus": "0.5", "shard_memory_gb": 2, "max_retrievals": 4}
    assert isinstance(app_builder({"root": dataset, **sharded}), Application)
    for bad, message in (
        ({}, "the links application needs args.root"),
        ({"root": ""}, "the links application needs args.root"),
        ({"root": str(tmp_path)}, "has no curated table"),
        (
            {"root": dataset, "replicas": "two"},
            "args.replicas must be a positive integer, got 'two'",
        ),
        ({"root": dataset, "replicas": True}, "args.replicas must be a positive integer, got True"),
        ({"root": dataset, "x": 1}, r"unknown args for the links application: \['x'\]"),
        ({"root": dataset, "shards": 0}, "args.shards must be a positive integer, got 0"),
        ({"root": dataset, "shards": 1.5}, "args.shards must be a positive integer, got 1.5"),
        (
            {"root": dataset, "shard_cpus": "nan"},
            "args.shard_cpus must be a positive number, got 'nan'",
        ),
        (
            {"root": dataset, "shard_memory_gb": -1},
            "args.shard_memory_gb must be a positive number, got -1",
        ),
        # One part more than the dataset's curated shards: the last one would be empty.
        (
            {"root": dataset, "shards": _curated_shards(dataset) + 1},
            f"has {_curated_shards(dataset)} curated shards: split in "
            f"{_curated_shards(dataset) + 1} partitions, partition {_curated_shards(dataset)} "
            "would have none; use a smaller --shards",
        ),
    ):
        with pytest.raises(ValueError, match=message):
            app_builder(bad)
    with pytest.raises(ValueError, match="replicas must be a positive integer, got 0"):
        build_app(dataset, replicas=0)
    with pytest.raises(ValueError, match="shard_cpus must be a positive number, got 0"):
        build_app(dataset, shards=2, shard_cpus=0)


def test_allowed_hosts_args(dataset: str) -> None:
    from links_ray.serve.app import app_builder, build_app

    app_builder({"root": dataset, "allowed_hosts": ["links.example.org", "*"]})
    for bad, message in (
        ("links.example.org", "allowed hosts must be a list of host names, got str"),
        (["links example"], "'links example' is not a host name"),
        ([""], "'' is not a host name"),
        ([7], "7 is not a host name"),
        (["a" * 254], "is not a host name"),
    ):
        with pytest.raises(ValueError, match=f"args.allowed_hosts: .*{message}"):
            app_builder({"root": dataset, "allowed_hosts": bad})
        with pytest.raises(ValueError, match=message):
            build_app(dataset, allowed_hosts=bad)


def test_a_host_it_was_not_told_of_gets_400(client: Client) -> None:
    """A request for a DNS name the server was not given (how a web page reaches a loopback
    server through a name it controls) is refused 400 before its body is read, through the
    replica and through Serve's proxy; addresses, localhost and the allowed name are answered."""
    from tests.support.serve_app import ALLOWED_HOST

    port = client.port
    for way in (client, client.proxy):
        for host in ("attacker.example", f"attacker.example:{port}", "127.0.0.1.nip.io", "local"):
            status, _, data = way.request("POST", "/api/simulate", FOUR_BAR, {"Host": host})
            assert status == 400, (host, status, data)
            assert data["error"].startswith(f"Host {host!r}: this server answers its addresses")
            assert "--allow-host" in data["error"]
        for host in (
            f"127.0.0.1:{port}",
            "127.0.0.1",
            f"[::1]:{port}",
            f"localhost:{port}",
            "studio.localhost",
            f"{ALLOWED_HOST}:{port}",
            ALLOWED_HOST.upper(),
        ):
            status, _, data = way.request("POST", "/api/simulate", FOUR_BAR, {"Host": host})
            assert status == 200, (host, status, data)
    # HTTP/1.0 lets a request leave its host unsaid; one without is refused as well.
    import socket

    with socket.create_connection(("127.0.0.1", port), timeout=60) as sock:
        sock.sendall(b"GET /api/health HTTP/1.0\r\n\r\n")
        answer = b""
        while chunk := sock.recv(65536):
            answer += chunk
    assert answer.startswith(b"HTTP/1.1 400"), answer[:200]
    assert b"no Host header" in answer


def _curated_shards(root: str) -> int:
    from links_ray.data.commit import committed_shards
    from links_ray.data.store import Store

    return len(committed_shards(Store.open(root), "curation"))


def test_an_app_that_cannot_fit_is_refused() -> None:
    """On a Ray `links serve` starts itself, an app larger than the machine is refused in one
    line, where Serve would wait for resources forever."""
    from links_ray.serve.app import check_fits

    two_cpus = {"CPU": 2.0, "memory": 8e9}
    check_fits(1, None, 1.0, None, two_cpus)
    check_fits(1, 4, 0.25, 1.5, two_cpus)
    with pytest.raises(
        ValueError, match=r"the app needs 5 CPUs \(1 a gateway replica, 1 a partition"
    ):
        check_fits(1, 4, 1.0, None, two_cpus)
    with pytest.raises(
        ValueError, match=r"the partitions reserve 12\.0 GB and this Ray has 8\.0 GB"
    ):
        check_fits(1, 2, 0.5, 6, two_cpus)


def test_partitions_share_the_cpus_the_gateway_leaves() -> None:
    """On a Ray `links serve` started, shards given no CPUs reserve 1 each where that fits,
    else an equal share of what the gateway's replicas (one CPU each) leave, in Ray's steps of
    0.0001 CPU, and the app then fits; where nothing is left, a refusal naming why."""
    from links_ray.serve.app import check_fits, fit_partition_cpus

    for cpus, replicas, shards, share in (
        (8, 1, 2, 1.0),
        (3, 1, 2, 1.0),
        (2, 1, 2, 0.5),
        (2, 1, 4, 0.25),
        (2, 1, 3, 0.3333),
        (4, 2, 3, 0.3333),
        (1.5, 1, 2, 0.25),
    ):
        resources = {"CPU": float(cpus), "memory": 8e9}
        assert fit_partition_cpus(replicas, shards, resources) == share
        check_fits(replicas, shards, share, None, resources)
    for cpus, replicas in ((2, 2), (1, 1), (0, 1)):
        with pytest.raises(ValueError, match=r"none is left for the partitions"):
            fit_partition_cpus(replicas, 2, {"CPU": float(cpus)})


def listening_process(port: int) -> str:
    """The command line of the process listening on TCP port `port` of 127.0.0.1 ('' if none),
    from /proc: which process answers, not only that something does."""
    inodes = set()
    for line in Path("/proc/net/tcp").read_text().splitlines()[1:]:
        fields = line.split()
        if fields[1] == f"0100007F:{port:04X}" and fields[3] == "0A":  # LISTEN
            inodes.add(f"socket:[{fields[9]}]")
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            fds = os.listdir(f"/proc/{pid}/fd")
            if any(os.readlink(f"/proc/{pid}/fd/{fd}") in inodes for fd in fds):
                return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
        except OSError:  # gone, or not ours to read
            continue
    return ""


def test_the_replica_answers_http_itself(client: Client) -> None:
    """Direct ingress: the replica owns the port; Serve's proxy answers on its own port too."""
    assert "ServeReplica:links:LinksApi" in listening_process(client.port)
    assert client.proxy is not None
    assert "ProxyActor" in listening_process(client.proxy.port)
    assert client.proxy.get("/api/health") == client.get("/api/health")


#: The Ray a `links serve` of these tests starts has 2 CPUs, whatever the machine's count
#: (Ray's own override of a node's resources): as on a 2-core laptop.
@pytest.mark.parametrize("shards", [None, 2], ids=["one-index", "2-shards"])
def test_links_serve_answers_from_its_replica_and_stops_on_ctrl_c(
    dataset: str, curated: Any, shards: int | None, tmp_path: Path
) -> None:
    """`links serve` starts its own Ray; its request gate answers on --port and passes requests
    to the replica (the gateway, with --shards), and Ctrl-C (one index) or SIGTERM (shards) stops
    all, cleanly. On its Ray of 2 CPUs, `--shards 2` does not fit at 1 CPU a partition beside the
    gateway's 1: the partitions share the CPU the gateway leaves, said in one line on stderr."""
    port = bindable_port("127.0.0.1", 0)
    sharding = () if shards is None else ("--shards", str(shards))
    errors = tmp_path / "stderr.txt"
    stop = signal.SIGINT if shards is None else signal.SIGTERM
    with links_serve(dataset, port, errors, sharding, stop) as served:
        status, health = served.get("/api/health")
        assert status == 200 and health["paths"] == len(curated)
        assert len(health.get("shards", [])) == (shards or 0)
        status, data = served.post("/api/retrieve", {"points": [[0, 0], [1, 0.5], [2, 0], [1, -1]]})
        assert status == 200 and len(data["results"]) == 3
        # The request gate, in the command's own process, answers on the port; the replica
        # answers the gate on loopback.
        assert "links_ray.cli serve" in listening_process(port)
        # The port is taken now: a second server says so in one line, before starting Ray.
        taken = subprocess.run(
            [sys.executable, "-m", "links_ray.cli", "serve", dataset, "--port", str(port)],
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert taken.returncode == 2
        assert taken.stderr.strip().endswith(f"port {port}: Address already in use")
    assert listening_process(port) == ""
    notices = [line for line in errors.read_text().splitlines() if "partition replicas" in line]
    if shards is None:
        assert notices == []
    else:
        assert notices == [
            "links-ray: this Ray has 2 CPUs and the gateway takes 1: each of the 2 partition "
            "replicas reserves 0.5 CPU (--shard-cpus to choose)"
        ]
    assert "Traceback" not in errors.read_text()


def test_links_serve_refuses_partitions_when_the_gateway_takes_every_cpu(dataset: str) -> None:
    """Where no share is left (two gateway replicas on 2 CPUs), one line and exit status 2,
    not a server waiting for CPUs forever; and the same for shards told to take 1 CPU each."""
    port = str(bindable_port("127.0.0.1", 0))
    for options, words in (
        (
            ["--replicas", "2"],
            "this Ray has 2 CPUs and the gateway takes 2 (one a replica): none "
            "is left for the partitions; serve fewer replicas, or no --shards",
        ),
        (
            ["--shard-cpus", "1"],
            "the app needs 3 CPUs (1 a gateway replica, 1 a partition replica) and this Ray has 2",
        ),
    ):
        command = [sys.executable, "-m", "links_ray.cli", "serve", dataset, "--port", port]
        refused = subprocess.run(
            [*command, "--shards", "2", *options],
            capture_output=True,
            text=True,
            timeout=300,
            env={**os.environ, **TWO_CPU_RAY},
        )
        assert refused.returncode == 2, refused.stderr[-3000:]
        last = refused.stderr.strip().splitlines()[-1]
        assert last.startswith("links serve: error: ") and words in last, refused.stderr[-3000:]


@contextlib.contextmanager
def served_by_the_cli(root: str) -> Iterator[tuple[subprocess.Popen, Client, list[str]]]:
    """`links serve root` in a process of its own, once it answers health: the process, a
    client and the lines it prints (as they come). Its Ray keeps its files in a folder of
    its own (RAY_TMPDIR), so it neither joins nor is confused with any other Ray here."""
    port = bindable_port("127.0.0.1", 0)
    ray_dir = tempfile.mkdtemp(prefix="links-serve-", dir="/tmp")  # short: Ray's socket paths
    env = {name: value for name, value in os.environ.items() if name != "RAY_ADDRESS"}
    env["RAY_TMPDIR"] = ray_dir
    server = subprocess.Popen(
        [sys.executable, "-m", "links_ray.cli", "serve", root, "--port", str(port)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
    )
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(server.stdout), daemon=True)
    reader.start()
    served = Client(port)
    try:
        deadline = time.monotonic() + 600
        while True:
            assert server.poll() is None, "".join(lines[-30:])
            assert time.monotonic() < deadline, "".join(lines[-30:])
            try:
                if served.get("/api/health")[0] == 200:
                    break
            except OSError:  # not listening yet
                pass
            time.sleep(0.25)
        yield server, served, lines
    finally:
        if server.poll() is None:
            for pid in descendants(server.pid):
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
            server.kill()
            server.wait()
        for pid in processes_mentioning(ray_dir):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        shutil.rmtree(ray_dir, ignore_errors=True)


def stopped_by_sigterm(server: subprocess.Popen, timeout: float) -> tuple[float, dict[int, str]]:
    """SIGTERM `server`: the seconds it took to exit, and those of its processes (Ray's,
    as they were when it was sent) still alive when it had."""
    below = descendants(server.pid)
    assert below, "links serve has started no processes: is its Ray its own?"
    start = time.monotonic()
    server.send_signal(signal.SIGTERM)
    try:
        server.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        pytest.fail(f"links serve still running {timeout:g} s after SIGTERM")
    seconds = time.monotonic() - start
    left = {pid: line for pid, line in below.items() if line and command_line(pid) == line}
    return seconds, left


#: What `links serve` may take to exit after SIGTERM once no request is under way.
EXIT_S = 10.0


def test_links_serve_finishes_a_request_under_way_at_sigterm(dataset: str) -> None:
    """A synthesis under way when SIGTERM comes is answered in full (200, its results), after
    the signal; then, nothing being under way, the server exits within EXIT_S, with status 0,
    saying so, and leaves none of its Ray's processes behind."""
    from links_ray.serve.deployments import SHUTDOWN_DRAIN_S

    seconds = 4.0
    with served_by_the_cli(dataset) as (server, served, lines):
        answer: dict[str, Any] = {}

        def synthesize() -> None:
            status, data = served.post("/api/synthesize", {"points": POINTS, "seconds": seconds})
            answer.update(status=status, data=data, at=time.monotonic())

        asking = threading.Thread(target=synthesize)
        asking.start()
        time.sleep(1.0)  # under way: its budget is seconds
        assert not answer, answer
        sent = time.monotonic()
        exited, left = stopped_by_sigterm(server, timeout=120)
        asking.join(timeout=60)
        text = "".join(lines)
        print(f"\nlinks serve exited {exited:.1f} s after SIGTERM, a request under way")
        assert answer["status"] == 200 and len(answer["data"]["results"]) == 3, answer
        assert answer["at"] > sent
        assert server.returncode == 0, text[-3000:]
        assert "links-ray: shutting down" in text and "Traceback" not in text, text[-3000:]
        assert exited < SHUTDOWN_DRAIN_S + EXIT_S, f"{exited:.1f} s"
        after_answer = sent + exited - answer["at"]
        assert after_answer < EXIT_S, f"exited {after_answer:.1f} s after the last answer"
        assert left == {}, left


def test_serve_cli_refuses_a_root_without_curated_paths(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """One line and exit status 2, before Ray or Serve is touched."""
    from links_ray.cli.main import main

    port = bindable_port("127.0.0.1", 0)
    assert main(["serve", str(tmp_path / "nothing"), "--port", str(port)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "no curated table" in err


def test_serve_cli_refuses_more_shards_than_the_data_splits_into(
    dataset: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """One line and exit status 2, before Ray or Serve is touched; bad numbers likewise."""
    from links_ray.cli.main import main

    port = bindable_port("127.0.0.1", 0)
    count = _curated_shards(dataset)
    assert main(["serve", dataset, "--port", str(port), "--shards", str(count + 1)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0
    assert err.endswith(
        f"in {count + 1} partitions, partition {count} would have none; use a smaller --shards"
    )
    for option, value, words in (
        ("--shards", "0", "must be a positive integer, got 0"),
        ("--shard-cpus", "-1", "must be a positive number, got -1"),
        ("--shard-memory-gb", "inf", "must be a positive number, got inf"),
    ):
        with pytest.raises(SystemExit) as exited:
            main(["serve", dataset, option, value])
        assert exited.value.code == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and words in err, err


def _check_serve_config(config: dict[str, Any]) -> Any:
    from ray.serve.schema import ServeDeploySchema

    from links_ray.serve.app import app_builder

    schema = ServeDeploySchema.model_validate(config)
    (app,) = schema.applications
    assert app.name == "links" and app.route_prefix == "/"
    module, _, name = app.import_path.partition(":")
    assert getattr(importlib.import_module(module), name) is app_builder
    assert schema.logging_config.enable_access_log is False
    return schema


def test_serve_config_file() -> None:
    config = yaml.safe_load((REPO / "deploy/serve/serve_config.yaml").read_text())
    schema = _check_serve_config(config)
    assert schema.http_options.host == "127.0.0.1"
    assert schema.http_options.port == 8000


def test_rayservice_manifest() -> None:
    manifest = yaml.safe_load((REPO / "deploy/kuberay/rayservice.yaml").read_text())
    assert manifest["apiVersion"] == "ray.io/v1" and manifest["kind"] == "RayService"
    spec = manifest["spec"]
    schema = _check_serve_config(yaml.safe_load(spec["serveConfigV2"]))
    args = schema.applications[0].args
    assert args["root"] == "s3://links/dataset"
    # The full dataset, sharded (deploy/RUNBOOK.md, 6): args the app builder takes.
    from links_ray.serve.app import APP_ARGS, _arg

    assert set(args) <= set(APP_ARGS)
    given = {name: _arg(args, name) for name in args if name != "root"}
    assert given == {"replicas": 1, "shards": 32, "shard_cpus": 7.0, "shard_memory_gb": 8.0}
    cluster = spec["rayClusterConfig"]
    pods = [cluster["headGroupSpec"]] + cluster["workerGroupSpecs"]
    from links_ray.serve.deployments import SHUTDOWN_DRAIN_S

    for pod in pods:
        # Kubernetes kills a pod this long after SIGTERM: the replicas' drain, and the 10 s
        # `links serve` may take to stop once idle
        # (test_links_serve_finishes_a_request_under_way_at_sigterm).
        assert pod["template"]["spec"]["terminationGracePeriodSeconds"] == SHUTDOWN_DRAIN_S + EXIT_S
        (container,) = pod["template"]["spec"]["containers"]
        assert container["image"] == "links-ray:latest"
        env = {item["name"]: item for item in container["env"]}
        for key in ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY"):
            ref = env[key]["valueFrom"]["secretKeyRef"]
            assert ref == {"name": "links-s3-credentials", "key": key}
            assert "value" not in env[key]
