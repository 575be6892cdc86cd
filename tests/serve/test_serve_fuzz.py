"""Every route, fed generated bodies: each answer is 2xx or 4xx with a JSON error, never 5xx,
and the server keeps answering its health check.

Bodies are built by Hypothesis from each route's request model (`serve.http.schemas`): a valid body
with one field swapped for arbitrary JSON or an edge value (integers past float64, lone
surrogates, deep nesting, huge and tiny numbers, wrong types), unknown fields, arbitrary JSON
values, and raw bytes. Each route runs a fixed number of examples, derandomized, so a run
does the same work every time; the costly valid cases (long syntheses, huge simulations) are
kept out by the edge values each field draws from.
"""

from __future__ import annotations

import json
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from links_ray.serve.http.schemas import REQUEST_MODELS
from tests.support.serving import FOUR_BAR, Client

#: Examples each route runs; synthesis fewer, since each valid body among them refines every
#: retrieved candidate for a first round (seconds of work, where a refusal takes milliseconds).
EXAMPLES = 150
ROUTE_EXAMPLES = {"/api/synthesize": 60}
POINTS = [[0.0, 0.0], [1.0, 0.5], [2.0, 0.0], [3.0, 1.0], [2.5, -0.5]]
#: A body each route answers 200 (or 422 for a mechanism that locks), cheaply.
VALID = {
    "/api/simulate": {**FOUR_BAR, "steps": 20},
    "/api/analyze": dict(FOUR_BAR),
    "/api/export": {**FOUR_BAR, "format": "table"},
    "/api/curve": {"name": "curve.csv", "text": "0,0\n1,1\n2,0\n3,1\n"},
    "/api/retrieve": {"points": POINTS, "k": 2},
    "/api/synthesize": {"points": POINTS, "k": 1, "iterations": 2},
    "/api/kit": {**FOUR_BAR, "format": "bom"},
}

NUMBERS = st.one_of(
    st.integers(min_value=-(2**70), max_value=2**70),
    st.sampled_from([10**310, -(10**310), 10**4299, 2**63, 2**64, -(2**63) - 1]),
    st.floats(allow_nan=False, allow_infinity=False),
    st.sampled_from([1e308, -1e308, 5e-324, 0.0, -0.0, 1e12, 1e13]),
)
TEXT = st.one_of(
    st.text(max_size=20),
    st.sampled_from(["\ud800", "\udfff", "a\x00b", "{" * 50, "<svg>", "0,0\n1e999,1"]),
)
JSON_VALUES = st.recursive(
    st.none() | st.booleans() | NUMBERS | TEXT,
    lambda inner: st.lists(inner, max_size=6) | st.dictionaries(TEXT, inner, max_size=4),
    max_leaves=20,
)
#: Edge values by field, beside arbitrary JSON: each is refused, or valid and cheap.
EDGES: dict[str, st.SearchStrategy[Any]] = {
    "seconds": st.sampled_from([0, -1, 0.01, 31, 1e308, "3", True, 10**400]),
    "iterations": st.sampled_from([0, 1, 3, 10_001, 2.5, -1, 10**400]),
    "steps": st.sampled_from([0, 1, 7, 100_001, 1.5, -3, 10**400]),
    "k": st.sampled_from([0, 1, 100, 101, 2.5, -1, 10**400]),
    "points": st.one_of(
        st.lists(st.lists(NUMBERS, min_size=2, max_size=2), max_size=12),
        st.sampled_from([[[0, 0]] * 3, [[0, 0], [1, 1]], [[[0, 0]]], "M0 0"]),
    ),
    "positions": st.lists(st.lists(NUMBERS, min_size=2, max_size=2), min_size=4, max_size=4),
    "text": st.sampled_from(
        [
            "<svg xmlns='http://www.w3.org/2000/svg'><style>" + "a" * 3000 + "</style>"
            "<path d='M0 0L1 1L2 0'/></svg>",
            "<svg xmlns='http://www.w3.org/2000/svg'><path d='M0 0L1e305 0L1e305 1'/></svg>",
            "[" * 3000 + "]" * 3000,
            "[[0,0],[1,1],[1" + "0" * 400 + ",2]]",
            "0,0\n1,1\n1e999,2\n",
            "0\n",
        ]
    ),
    "name": st.sampled_from(["a.svg", "a.dxf", "a.json", "a.csv", "a.exe", "", "x" * 1001]),
}


def body_for(route: str) -> st.SearchStrategy[bytes]:
    """Bodies for `route`: its valid body with one field changed, dropped or added, or JSON
    values of any shape, or raw bytes."""
    valid = VALID[route]
    fields = sorted(REQUEST_MODELS[route].model_fields)

    @st.composite
    def changed(draw: st.DrawFn) -> bytes:
        body = dict(valid)
        field = draw(st.sampled_from([*fields, "unknown_field"]))
        how = draw(st.sampled_from(["edge", "json", "drop"]))
        if how == "drop":
            body.pop(field, None)
        elif how == "edge" and field in EDGES:
            body[field] = draw(EDGES[field])
        else:
            body[field] = draw(JSON_VALUES)
        return json.dumps(body).encode()

    return st.one_of(
        changed(),
        JSON_VALUES.map(lambda value: json.dumps(value).encode()),
        st.binary(max_size=200),
    )


@pytest.mark.parametrize("route", sorted(VALID))
def test_every_route_answers_generated_bodies_without_a_5xx(client: Client, route: str) -> None:
    """The valid body is answered 200 (the route works at all); then every generated body is
    answered below 500, a refusal with a JSON `error`; health answers 200 after each tenth."""
    status, _, data = client.request("POST", route, VALID[route])
    assert status == 200, (route, status, data)
    seen: list[int] = []

    @settings(
        max_examples=ROUTE_EXAMPLES.get(route, EXAMPLES),
        derandomize=True,
        database=None,
        deadline=None,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    )
    @given(body=body_for(route))
    def answered(body: bytes) -> None:
        status, headers, data = client.request("POST", route, body)
        assert status < 500, (route, body[:300], status, data)
        if status >= 400:
            assert headers.get("content-type", "").startswith("application/json"), headers
            assert isinstance(data, dict) and isinstance(data.get("error"), str), data
        seen.append(status)
        if len(seen) % 10 == 0:
            assert client.get("/api/health")[0] == 200

    answered()
    assert client.get("/api/health")[0] == 200
    print(f"\n{route}: {len(seen)} bodies, statuses {sorted(set(seen))}")


@settings(max_examples=EXAMPLES, derandomize=True, database=None, deadline=None)
@given(name=st.text(min_size=1, max_size=40).filter(lambda n: "/" not in n and n not in ".."))
def test_studio_files_answer_any_name_without_a_5xx(client: Client, name: str) -> None:
    """GET /studio/<name>: one of the studio's files, or 404 with a JSON error."""
    from urllib.parse import quote

    status, _, data = client.request("GET", "/studio/" + quote(name, safe=""))
    assert status in (200, 404), (name, status, data)
