"""Request bodies read and checked: what each route takes from its JSON body.

A body is read within the engine's limits (`links_ray.engine.inputs`): 408 for a body that
pauses `BODY_TIMEOUT_S` or falls behind `MIN_BODY_BYTES_PER_S` and 413 for a body over
`MAX_BODY_BYTES` (`json_body.read_body`), 413 for a mechanism over `MAX_REQUEST_JOINTS` or a
simulation over `MAX_REQUEST_JOINT_STEPS`, 415 for a body not declared as JSON (`Content-Type:
application/json`). Each route's converter (`CONVERTERS`) checks what JSON alone can get wrong
(types, booleans for numbers, array lengths) first; the values are checked by the engine's own
validators, whose ValueErrors become 400s. Each refusal is an `ApiError` naming the problem.
`serve.http.schemas` describes the same bodies for `/openapi.json`, and
tests/serve/test_bodies_agree.py holds the two to each other, bound by bound.

Counts come before contents: a body's brackets are counted before it is parsed
(`MAX_BODY_CONTAINERS`), and each list's length before any of its entries is looked at, so
that a body over a limit costs what its bytes do to refuse, not what its entries do to read.
A large body is parsed and turned into a route's arguments (`read_args`) in `JSON_POOL`,
where it is freed too.
"""

import asyncio
import math
from collections.abc import Callable
from dataclasses import fields
from typing import Any, TypeVar

import numpy as np
from fastapi import Request

from links_ray.engine.fabrication.kit import KitOptions
from links_ray.engine.fabrication.limits import DEFAULT_CRANK_MM, as_crank_mm
from links_ray.engine.inputs import (
    DEFAULT_K,
    DEFAULT_STEPS,
    MAX_COORDINATE,
    MAX_POINTS,
    as_flag,
    as_graph,
    as_int,
    as_max_joints,
    as_steps,
    as_transmission_deg,
    check_point_count,
    validate_query,
)
from links_ray.engine.synthesis.options import DEFAULT_SYNTHESIS_TRANSMISSION_DEG, SynthesisOptions
from links_ray.serve.http.json_body import json_kind as _kind
from links_ray.serve.http.json_body import parse_json_object, read_body
from links_ray.serve.http.limits import (
    MAX_BODY_BYTES,
    MAX_BODY_CONTAINERS,
    MAX_CURVE_NAME_CHARS,
    MAX_KIT_JOINTS,
    MAX_REQUEST_JOINT_STEPS,
    MAX_REQUEST_JOINTS,
)
from links_ray.serve.http.responses import INLINE_JSON_BYTES, JSON_POOL, ApiError
from links_ray.serve.http.schemas import REQUEST_MODELS


def _is_number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _is_finite(value: int | float) -> bool:
    try:
        return math.isfinite(float(value))
    except OverflowError:  # an integer beyond float64
        return False


#: What a route makes of its body (`read_args`).
Args = TypeVar("Args")

#: Routes whose bodies carry free text (a drawing's file), in which brackets are characters.
TEXT_ROUTES = frozenset({"/api/curve"})


async def read_json_object(request: Request, route: str) -> dict[str, Any]:
    """The body of a request to `route` as a JSON object, or ApiError (400, 408, 413 or 415)
    naming the problem: a field the route's model (`models.REQUEST_MODELS`) does not name is
    refused, so that a misspelled option is never silently dropped. A large body is parsed in
    JSON_POOL, off the event loop."""
    return await read_args(request, route, _as_is)


def _as_is(body: dict[str, Any]) -> dict[str, Any]:
    return body


async def read_route_args(request: Request, route: str) -> Any:
    """The arguments of a POST to `route`: its body read by `read_args` with the route's
    converter in `CONVERTERS`."""
    return await read_args(request, route, CONVERTERS[route])


async def read_args(
    request: Request, route: str, convert: Callable[[dict[str, Any]], Args]
) -> Args:
    """`convert(body)`, the body of a request to `route` read as `read_json_object` reads it,
    or ApiError naming the problem. A large body is parsed, converted and freed in
    JSON_POOL: neither its parse nor its walk holds up the event loop."""
    # A body of another type, or of none, is refused unread: it is what a page of another
    # site can send without the browser asking this server first (a CORS preflight).
    media = (request.headers.get("content-type") or "").split(";", 1)[0].strip().lower()
    if media != "application/json" and not media.endswith("+json"):
        got = f"got {media[:80]!r}" if media else "none was given"
        raise ApiError(415, f"the body must be JSON, sent as Content-Type application/json: {got}")
    declared = request.headers.get("content-length")
    if declared is not None:
        if not declared.strip().isdigit():
            raise ApiError(400, "Content-Length is not a byte count")
        if int(declared) > MAX_BODY_BYTES:
            raise ApiError(413, f"the body is over the limit of {MAX_BODY_BYTES} bytes")
    body = await read_body(request)
    if route not in TEXT_ROUTES:
        refuse_many_containers(body, route)
    if len(body) <= INLINE_JSON_BYTES:
        return _converted(body, route, convert)
    loop = asyncio.get_running_loop()
    return await loop.run_in_executor(JSON_POOL, _converted, body, route, convert)


def _converted(body: bytes, route: str, convert: Callable[[dict[str, Any]], Args]) -> Args:
    """`convert` of `body` parsed, its fields checked; the parsed body is freed in this thread."""
    data = parse_json_object(body)
    refuse_unknown_fields(data, route)
    return convert(data)


def refuse_many_containers(body: bytes, route: str) -> None:
    """ApiError 400 if `body` holds more brackets than MAX_BODY_CONTAINERS: more arrays and
    objects than any body of `route` (not one of TEXT_ROUTES) that keeps the limits holds."""
    brackets = body.count(b"[") + body.count(b"{")
    if brackets > MAX_BODY_CONTAINERS:
        raise ApiError(
            400,
            f"the body holds {brackets} brackets, more arrays and objects than any {route} body "
            f"within the limits (at most {MAX_POINTS} points, {MAX_REQUEST_JOINTS} joints)",
        )


def refuse_unknown_fields(body: dict[str, Any], route: str) -> None:
    """ApiError 400 naming the first field of `body` that `route`'s request model lacks."""
    known = REQUEST_MODELS[route].model_fields
    for name in body:
        if name not in known:
            shown = name if len(name) <= 80 else name[:80] + "..."
            raise ApiError(400, f"unknown field {shown!r}: {route} takes {', '.join(known)}")


def _required(body: dict[str, Any], name: str) -> Any:
    if name not in body:
        raise ApiError(400, f"missing field {name!r}")
    return body[name]


def _checked(check: Callable[..., Any], *args: Any) -> Any:
    """`check(*args)`, an engine validator, with its ValueError answered 400."""
    try:
        return check(*args)
    except ValueError as exc:
        raise ApiError(400, str(exc)) from None


def _numbers(name: str, value: object, count: int, entries: str) -> list:
    """`value` as an array of `count` JSON numbers (not booleans); `entries` says which."""
    if not isinstance(value, list):
        raise ApiError(400, f"{name} must be an array of {count} numbers, got {_kind(value)}")
    if len(value) != count:
        raise ApiError(400, f"{name} must hold {count} entries (one per joint), got {len(value)}")
    for i, entry in enumerate(value):
        if not _is_number(entry):
            raise ApiError(400, f"{name}[{i}] must be {entries}, got {_kind(entry)}")
    return value


def _plain_pairs(pairs: list) -> bool:
    """Whether `pairs` holds only [x, y] lists of JSON numbers within +-MAX_COORDINATE: one
    pass over a drawn curve's points, much quicker than `_pairs`' loop that names the first
    bad entry, which only a refused curve needs."""
    return all(
        type(pair) is list
        and len(pair) == 2
        and type(pair[0]) in (float, int)
        and type(pair[1]) in (float, int)
        and -MAX_COORDINATE <= pair[0] <= MAX_COORDINATE
        and -MAX_COORDINATE <= pair[1] <= MAX_COORDINATE
        for pair in pairs
    )


def _pairs(name: str, value: object, count: int | None = None) -> list[list[float]]:
    """`value` as a list of [x, y] number pairs within +-MAX_COORDINATE (`count` of them if
    given), refused in the engine's words (`inputs.check_positions`, `as_drawn_points`)."""
    if not isinstance(value, list):
        raise ApiError(400, f"{name} must be an array of [x, y] pairs, got {_kind(value)}")
    if count is not None and len(value) != count:
        raise ApiError(
            400, f"{name} must hold {count} [x, y] pairs (one per joint), got {len(value)}"
        )
    if _plain_pairs(value):
        return value
    for i, pair in enumerate(value):
        if not isinstance(pair, list) or len(pair) != 2:
            what = f"{len(pair)} entries" if isinstance(pair, list) else _kind(pair)
            raise ApiError(400, f"{name}[{i}] must be an [x, y] pair, got {what}")
        for coordinate in pair:
            if not _is_number(coordinate):
                raise ApiError(400, f"{name}[{i}] must hold two numbers, got {_kind(coordinate)}")
            if not _is_finite(coordinate):
                raise ApiError(400, f"{name}[{i}] must hold finite numbers")
            if abs(coordinate) > MAX_COORDINATE:
                raise ApiError(400, f"{name} must lie within +-{MAX_COORDINATE:g}")
    return value


def _drawn_pairs(name: str, value: object) -> list[list[float]]:
    """`value` as drawn points' [x, y] pairs, their count (MIN_POINTS to MAX_POINTS) checked
    before any pair is looked at."""
    if isinstance(value, list):
        _checked(check_point_count, len(value), name)
    return _pairs(name, value)


def retrieve_args(body: dict[str, Any]) -> tuple[np.ndarray, int, float, int | None]:
    """The query points (T, 2), k, min_transmission and max_joints of a /api/retrieve body,
    or ApiError naming the problem."""
    points = _drawn_pairs("points", _required(body, "points"))
    k = body.get("k")
    points, k = _checked(validate_query, points, DEFAULT_K if k is None else k)
    return points, k, _min_transmission(body), _checked(as_max_joints, body.get("max_joints"))


def synthesize_args(body: dict[str, Any]) -> tuple[np.ndarray, SynthesisOptions]:
    """(points (T, 2), options) of a /api/synthesize body, or ApiError naming the problem: the
    points, k and min_transmission as /api/retrieve takes them, and the rest as `synthesize`
    takes them, checked once (`SynthesisOptions`)."""
    points = _drawn_pairs("points", _required(body, "points"))
    k = body.get("k")
    min_transmission = body.get("min_transmission")

    def checked() -> tuple[np.ndarray, SynthesisOptions]:
        options = SynthesisOptions(
            k=DEFAULT_K if k is None else k,
            seconds=body.get("seconds"),
            partial=body.get("partial", False),
            min_transmission_deg=(
                DEFAULT_SYNTHESIS_TRANSMISSION_DEG if min_transmission is None else min_transmission
            ),
            max_joints=body.get("max_joints"),
            front=body.get("front", False),
            constraints=body.get("constraints"),
            timing=body.get("timing"),
            seed=body.get("seed"),
            iterations=body.get("iterations"),
        )
        return options.drawing(points), options

    return _checked(checked)


def synthesize_request(body: dict[str, Any]) -> tuple[np.ndarray, SynthesisOptions, bool]:
    """(points, options, stream) of a /api/synthesize body (`synthesize_args`, `stream_arg`)."""
    return (*synthesize_args(body), stream_arg(body))


def stream_arg(body: dict[str, Any]) -> bool:
    """A body's `stream` flag (false when absent), or ApiError naming it."""
    return _checked(as_flag, body.get("stream", False), "stream")


def _min_transmission(body: dict[str, Any]) -> float:
    """A body's `min_transmission` in degrees (0 when absent), or ApiError naming it."""
    value = body.get("min_transmission")
    return 0.0 if value is None else _checked(as_transmission_deg, value, "min_transmission")


def topology_args(body: dict[str, Any]) -> tuple[list, list]:
    """(adjacency, node_types) of a /api/simulate or /api/analyze body: shapes checked, then
    entries, kinds and joint count as the engine checks a graph (`inputs.as_graph`)."""
    adjacency = _required(body, "adjacency")
    node_types = _required(body, "node_types")
    if not isinstance(adjacency, list) or not adjacency:
        got = "an empty array" if adjacency == [] else _kind(adjacency)
        raise ApiError(400, f"adjacency must be an n x n array of 0/1, got {got}")
    n = len(adjacency)
    if n > MAX_REQUEST_JOINTS:
        raise ApiError(413, f"at most {MAX_REQUEST_JOINTS} joints per request, got {n}")
    for i, row in enumerate(adjacency):
        _numbers(f"adjacency[{i}]", row, n, "0 or 1")
    _numbers("node_types", node_types, n, "0, 1 or 2")
    _checked(as_graph, adjacency, node_types)
    return adjacency, node_types


def analyze_args(body: dict[str, Any]) -> tuple[list, list, list | None, int]:
    """(adjacency, node_types, positions, steps) of a /api/analyze body: as /api/simulate's,
    positions None when it gives none (its steps checked all the same)."""
    if body.get("positions") is None:
        adjacency, node_types = topology_args(body)
        return adjacency, node_types, None, _steps(body)
    return simulate_args(body)


def simulate_args(body: dict[str, Any]) -> tuple[list, list, list, int]:
    """(adjacency, node_types, positions, steps) of a /api/simulate body, shapes checked.

    The engine checks the rest (0/1 links, symmetry, joint types, solvability) and names
    what is wrong.
    """
    adjacency, node_types = topology_args(body)
    n = len(adjacency)
    positions = _pairs("positions", _required(body, "positions"), count=n)
    steps = _steps(body)
    if n * steps > MAX_REQUEST_JOINT_STEPS:
        raise ApiError(
            413,
            f"simulation too large: {n} joints x {steps} steps = {n * steps}, "
            f"the limit is {MAX_REQUEST_JOINT_STEPS} joint-steps",
        )
    return adjacency, node_types, positions, steps


def _steps(body: dict[str, Any]) -> int:
    """A body's `steps` (DEFAULT_STEPS when absent or null), or ApiError naming it."""
    steps = body.get("steps")
    return DEFAULT_STEPS if steps is None else _checked(as_steps, steps)


#: /api/export's formats: (media type, file suffix) of each.
EXPORT_FORMATS = {
    "svg": ("image/svg+xml", "svg"),
    "dxf": ("image/vnd.dxf", "dxf"),
    "table": ("text/plain; charset=utf-8", "txt"),
}


def export_args(body: dict[str, Any]) -> tuple[list, list, list, str, float, Any]:
    """(adjacency, node_types, positions, format, crank_mm, path_joint) of a /api/export body,
    or ApiError naming the problem; the engine checks the mechanism itself."""
    adjacency, node_types = topology_args(body)
    positions = _pairs("positions", _required(body, "positions"), count=len(adjacency))
    chosen = body.get("format", "svg")
    if not isinstance(chosen, str) or chosen not in EXPORT_FORMATS:
        raise ApiError(
            400, f"format must be one of {', '.join(EXPORT_FORMATS)}, got {_kind(chosen)}"
        )
    crank = body.get("crank_mm")
    crank_mm = DEFAULT_CRANK_MM if crank is None else _checked(as_crank_mm, crank)
    path_joint = body.get("path_joint")
    if path_joint is not None:  # a joint; the engine says whether it moves
        path_joint = _checked(as_int, "path_joint", path_joint, 0, len(adjacency) - 1)
    return adjacency, node_types, positions, chosen, crank_mm, path_joint


#: /api/kit's formats: (media type, file suffix) of each; "bom" answers JSON.
KIT_FORMATS = {
    "bom": ("application/json", "json"),
    "glb": ("model/gltf-binary", "glb"),
    "zip": ("application/zip", "zip"),
}
#: The sizes and flags of an /api/kit body: `KitOptions`' fields but the crank's.
KIT_OPTIONS = tuple(field.name for field in fields(KitOptions) if field.name != "crank_mm")


def kit_args(body: dict[str, Any]) -> tuple[list, list, list, KitOptions, str]:
    """(adjacency, node_types, positions, options, format) of a /api/kit body, or
    ApiError naming the problem: at most MAX_KIT_JOINTS joints, the options checked once
    (`KitOptions`), the crank DEFAULT_CRANK_MM long when not given; the engine checks the
    mechanism itself."""
    adjacency, node_types = topology_args(body)
    if len(node_types) > MAX_KIT_JOINTS:  # before the kit takes one of the replica's places
        raise ApiError(
            400,
            f"a kit is built of at most {MAX_KIT_JOINTS} joints here (MAX_KIT_JOINTS), got "
            f"{len(node_types)}: its layer plan would hold the server too long",
        )
    positions = _pairs("positions", _required(body, "positions"), count=len(adjacency))
    chosen = body.get("format", "bom")
    if not isinstance(chosen, str) or chosen not in KIT_FORMATS:
        raise ApiError(400, f"format must be one of {', '.join(KIT_FORMATS)}, got {_kind(chosen)}")
    crank = body.get("crank_mm")
    given = {name: body[name] for name in KIT_OPTIONS if body.get(name) is not None}
    crank_mm = DEFAULT_CRANK_MM if crank is None else crank
    options = _checked(lambda: KitOptions(crank_mm=crank_mm, **given))
    return adjacency, node_types, positions, options, chosen


def curve_args(body: dict[str, Any]) -> tuple[str, str, str | None]:
    """(name, text, id) of a /api/curve body, or ApiError naming the problem; the file itself
    is read by `interop.curve_files`, whose ValueErrors name what is wrong with it."""
    name = _string(body, "name", _required(body, "name"))
    text = _string(body, "text", _required(body, "text"))
    part = body.get("id")
    return name, text, None if part is None else _string(body, "id", part)


def _string(body: dict[str, Any], field: str, value: object) -> str:
    """`value`, a string: 1 to MAX_CURVE_NAME_CHARS characters but for the file's `text`."""
    if not isinstance(value, str):
        raise ApiError(400, f"{field} must be a string, got {_kind(value)}")
    if field != "text" and not 1 <= len(value) <= MAX_CURVE_NAME_CHARS:
        raise ApiError(400, f"{field} must be 1 to {MAX_CURVE_NAME_CHARS} characters long")
    return value


#: The converter of each POST route's body (`read_route_args`): the one place a route's name
#: meets its converter, for exactly the routes of `REQUEST_MODELS` (checked at import), whose
#: models tests/serve/test_bodies_agree.py holds to the converters field by field.
CONVERTERS: dict[str, Callable[[dict[str, Any]], Any]] = {
    "/api/simulate": simulate_args,
    "/api/analyze": analyze_args,
    "/api/retrieve": retrieve_args,
    "/api/synthesize": synthesize_request,
    "/api/export": export_args,
    "/api/curve": curve_args,
    "/api/kit": kit_args,
}
if CONVERTERS.keys() != REQUEST_MODELS.keys():  # at import: a route without both never serves
    raise RuntimeError(
        f"bodies.CONVERTERS names {sorted(CONVERTERS)}, schemas.REQUEST_MODELS "
        f"{sorted(REQUEST_MODELS)}: every POST route needs its converter and its model"
    )
