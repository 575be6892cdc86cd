"""Bad input over real HTTP: every bad request gets a 4xx with a JSON error that names its
problem (the engine's own words), never a 5xx; bodies over the limit are refused, however sent;
and the app is still serving after them (the `client` fixture's app)."""

import json
from typing import Any

import pytest

import links_ray
from links_ray.engine.inputs import validate_query
from tests.support.serving import FOUR_BAR, POINTS, Client, check_error, post_ok

LIMIT = 2 * 1024 * 1024
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
    check_error(status, reply_headers, data, expected, words)


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
    check_error(status, headers, data, 413, OVER_LIMIT)
    small = json.dumps({"points": POINTS, "k": 2}).encode()
    status, _, data = client.request("POST", "/api/retrieve", small, chunked=True)
    assert status == 200 and len(data["results"]) == 2


def test_lying_content_length_is_refused(client: Client) -> None:
    status, headers, data = client.request(
        "POST", "/api/retrieve", b'{"points": []}', {"Content-Length": str(10 * LIMIT)}
    )
    # The header is checked before the body is read: refused at once, no waiting.
    check_error(status, headers, data, 413, OVER_LIMIT)


def test_still_serving_after_bad_requests(client: Client, curated: Any) -> None:
    from ray import serve

    assert client.get("/api/health") == (200, {"status": "ok", "paths": len(curated)})
    app = serve.status().applications["links"]
    assert app.status == "RUNNING"
    assert post_ok(client, "/api/simulate", FOUR_BAR)[0] == 200
