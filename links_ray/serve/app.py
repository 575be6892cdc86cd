"""The Ray Serve application behind `links serve`: the HTTP API of docs/CONTRACT.md.

| route | answers |
|---|---|
| `GET /api/health` | `{"status": "ok", "paths": <indexed paths>}`; sharded also `"shards"` |
| `POST /api/simulate` | 200 `{"trajectories"}`, 422 `{"error": "locking", "step", "node"}` |
| `POST /api/retrieve` | 200 `{"results", "took_ms"}`, best first; 503 when busy |
| `POST /api/synthesize` | 200 `{"results", "took_ms", "queued_ms"}`, refined; 503 when busy |
| `POST /api/analyze` | 200 the studio's analysis: mobility, dyadic solvability, where it locks |
| `POST /api/export` | 200 the mechanism as an SVG, DXF or table file in mm (an attachment) |
| `GET /api/limits` | the limits a request meets (`engine.inputs.request_limits`) |
| `GET /openapi.json` | the API described, bodies and bounds included (`serve.models`) |
| `GET /` | the web studio (`links_ray/serve/studio/index.html`) |
| `GET /studio/<file>` | the studio's scripts and style sheet, from the package |

Every bad request gets a 4xx with a JSON `{"error": "<what is wrong>"}`: 400 for malformed
input, 404/405 for unknown routes and methods, 408 for a body that pauses `BODY_TIMEOUT_S` or
falls behind `MIN_BODY_BYTES_PER_S` (`read_body`), 413 for a body over `MAX_BODY_BYTES`, a
mechanism over `MAX_REQUEST_JOINTS` or a simulation over `MAX_REQUEST_JOINT_STEPS`, 415 for a
body that is declared as something other than JSON. The limits and the checks of the values
are the engine's (`links_ray.engine.inputs`, whose ValueErrors become 400s); this module checks
only what JSON alone can get wrong (types, booleans for numbers, array lengths) first. Anything
unexpected is logged by exception type and location only (never a request body) and answered
500 `{"error": "internal error"}`; the replica keeps serving. Bodies over `INLINE_JSON_BYTES`
are parsed, and large answers rendered in pieces, in `JSON_POOL`'s one thread, off the event
loop that answers health checks (`json_answer`).

Each replica opens the retrieval index once, in its constructor. Retrievals run one at a time
per replica (the index's compiled kernels are parallel, and the JIT's workqueue threading layer,
its fallback without TBB or OpenMP, cannot take concurrent callers), in a thread of their own,
so health checks and simulations, in the default thread pool, are answered meanwhile. A replica
holds at most `MAX_RETRIEVALS` retrievals, running or waiting; one more is answered 503 with
`Retry-After` at once, and Serve's own `max_ongoing_requests` and `max_queued_requests` bound
everything else.

Syntheses (`engine.synthesis`) retrieve their candidates as retrievals do (counted against
the same limit), then refine them in a thread of their own at `RETRIEVAL_NICENESS`, one at a
time, for at most their `seconds` counted from when their refinement starts (`queued_ms` says
how long they waited), or for their fixed `iterations`; a replica holds at most
`MAX_SYNTHESES`, running or waiting, answers one more 503 at once, and one that would wait
longer than its own budget 503 too. Each replica's threads are its `num_cpus`
(`use_replica_cpus`).

Sharded (`build_app(root, shards=N)`, `links serve --shards N`): N `IndexShard` deployments
each open part P of the index (`RetrievalIndex.open(root, part=P, parts=N)`: the curated
shards numbered P modulo N), and the front, `LinksApi`, holds no index: it asks every part for
its own top k through their deployment handles, at once, and keeps the k best by (chamfer,
path id), the order of one index: no worse than one index's answer, since each part passes on
a larger share of its paths to the exact distance (the same answer where every search is
exhaustive; docs/CONTRACT.md). A part that is unavailable, or parts that do
not all answer within `SHARD_TIMEOUT_S`, give 503 with `Retry-After`.

`run_server` (what `links serve` runs) starts its own Ray and, with one replica, has the replica
(the front, with shards) answer HTTP itself, on the port asked for: Ray Serve's *direct
ingress*, which its throughput mode uses. Through Serve's HTTP proxy every request costs about
12 ms more here (an actor hop and a second one to fetch the body). Serve's proxy then listens on
another loopback port. With several replicas, or on a cluster that Ray was already running, the
proxy answers on the port and balances the replicas. On Ctrl-C or SIGTERM it stops in bounded
time (`stop_serving`): the replicas drain the requests under way for at most
`SHUTDOWN_DRAIN_S`, then Serve and the Ray it started stop.
"""

import asyncio
import functools
import gc
import importlib.resources
import json
import logging
import math
import os
import signal
import socket
import sys
import threading
import time
from collections.abc import AsyncIterator, Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
import orjson
import ray
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.utils import get_openapi
from fastapi.responses import HTMLResponse, JSONResponse, Response, StreamingResponse
from ray import serve
from ray.exceptions import (
    NodeDiedError,
    ObjectLostError,
    RayActorError,
    RayTaskError,
    TaskCancelledError,
    WorkerCrashedError,
)
from ray.serve.deployment import Application
from ray.serve.exceptions import (
    BackPressureError,
    DeploymentUnavailableError,
    ReplicaUnavailableError,
)
from ray.serve.handle import DeploymentHandle, DeploymentResponse
from starlette.concurrency import run_in_threadpool
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from links_ray import __version__
from links_ray.data.commit import committed_shards
from links_ray.data.dataset import open_table
from links_ray.data.store import Store
from links_ray.engine.cpus import set_given_cpus
from links_ray.engine.fabrication import fabrication
from links_ray.engine.inputs import (
    BODY_TIMEOUT_S,
    DEFAULT_CRANK_MM,
    DEFAULT_K,
    DEFAULT_STEPS,
    MAX_BODY_BYTES,
    MAX_REQUEST_JOINT_STEPS,
    MAX_REQUEST_JOINTS,
    MAX_SYNTHESIS_SECONDS,
    MIN_BODY_BYTES_PER_S,
    as_crank_mm,
    as_flag,
    as_steps,
    as_transmission_deg,
    request_limits,
    validate_query,
    validate_synthesis,
    validate_synthesis_work,
)
from links_ray.engine.mechanism import (
    InvalidMechanismError,
    LockingError,
    analyze_topology,
    dataset_rule_violations,
    mobility,
)
from links_ray.engine.solver import simulate, simulate_until_lock
from links_ray.engine.synthesis import CANDIDATES, refine_retrieved
from links_ray.search.index import RetrievalIndex
from links_ray.serve import models

logger = logging.getLogger("ray.serve")

#: The studio's files (plain HTML, CSS and JavaScript modules; no build step) and their types.
STUDIO_MEDIA_TYPES = {
    ".html": "text/html; charset=utf-8",
    ".css": "text/css; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
}
#: Same-origin only: no inline scripts or styles, no third-party requests.
STUDIO_CSP = (
    "default-src 'self'; img-src 'self' data: blob:; object-src 'none'; base-uri 'none'; "
    "form-action 'none'; frame-ancestors 'none'"
)


@functools.cache
def studio_files() -> dict[str, tuple[bytes, str]]:
    """The studio's files by name, as (content, media type), read once from the package."""
    folder = importlib.resources.files("links_ray.serve") / "studio"
    files = {}
    for entry in folder.iterdir():
        media_type = STUDIO_MEDIA_TYPES.get("." + entry.name.rpartition(".")[2])
        if entry.is_file() and media_type is not None:
            files[entry.name] = (entry.read_bytes(), media_type)
    if "index.html" not in files:
        raise FileNotFoundError(f"the studio's index.html is missing from {folder}")
    return files


def studio_response(name: str) -> Response:
    """One studio file, or 404 `{"error"}` for a name the studio does not have."""
    found = studio_files().get(name)
    if found is None:
        raise ApiError(404, f"the studio has no file {name[:80]!r}")
    content, media_type = found
    headers = {"Cache-Control": "no-cache", "X-Content-Type-Options": "nosniff"}
    if name.endswith(".html"):
        headers["Content-Security-Policy"] = STUDIO_CSP
    return Response(content, media_type=media_type, headers=headers)


class ApiError(Exception):
    """A request the API refuses: its HTTP status, the JSON body's `error` message, other
    fields of the body (`extra`) and headers of the answer (`headers`)."""

    def __init__(
        self, status: int, message: str, headers: dict[str, str] | None = None, **extra: Any
    ) -> None:
        super().__init__(message)
        self.status = status
        self.message = message
        self.headers = headers or {}
        self.extra = extra


def _jsonable(value: object) -> object:
    """`json.dumps` fallback for numpy scalars and arrays."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON serializable")


class JsonResponse(JSONResponse):
    """Compact JSON that refuses NaN and infinity and accepts numpy values."""

    def render(self, content: Any) -> bytes:
        """The body: compact JSON, NaN and infinity refused."""
        return _dumps(content)


def _dumps(content: Any) -> bytes:
    """`content` as JsonResponse renders it: compact JSON, NaN and infinity refused."""
    return json.dumps(content, allow_nan=False, separators=(",", ":"), default=_jsonable).encode(
        "utf-8"
    )


#: The most numbers one call of the JSON encoder renders (a few milliseconds). The encoder
#: and the parser are C code that holds the GIL until it returns, so in any thread one long
#: call stalls the event loop for its whole length; pieces of this size let it in between.
JSON_PIECE_NUMBERS = 1024
#: Bodies up to this many bytes are parsed on the event loop (well under a millisecond); larger
#: ones in `JSON_POOL`.
INLINE_JSON_BYTES = 64 * 1024
#: The one thread that parses large request bodies and renders large answers. One, so that
#: at most one long run of the GIL-holding JSON code is under way at a time, whatever the
#: number of clients: the event loop waits for at most one piece of it.
JSON_POOL = ThreadPoolExecutor(max_workers=1, thread_name_prefix="links-json")
#: The replica's GIL switch interval (seconds; `sys.setswitchinterval`).
GIL_SWITCH_S = 0.0005


def _json_size(value: Any) -> int:
    """About how many numbers `value` renders to: lists are taken to be alike throughout (their
    first item times their length), so this costs a few steps, not a walk."""
    if isinstance(value, np.ndarray):
        return value.size
    if isinstance(value, dict):
        return sum(_json_size(item) for item in value.values()) + len(value)
    if isinstance(value, list | tuple):
        return len(value) * _json_size(value[0]) if value else 1
    return 1


def _json_pieces(value: Any, out: list[bytes]) -> None:
    """Append `value`'s compact JSON to `out` in pieces of at most about JSON_PIECE_NUMBERS
    numbers each; their concatenation is `_dumps(value)`."""
    if _json_size(value) <= JSON_PIECE_NUMBERS:
        out.append(_dumps(value))
    elif isinstance(value, dict):
        out.append(b"{")
        for i, (key, item) in enumerate(value.items()):
            out.append((b"," if i else b"") + _dumps(str(key)) + b":")
            _json_pieces(item, out)
        out.append(b"}")
    else:  # a long list, tuple or array: runs of small items together, large items in pieces
        out.append(b"[")
        per_item = max(1, _json_size(value[0]))
        run = max(1, JSON_PIECE_NUMBERS // per_item)
        for start in range(0, len(value), run):
            if start:
                out.append(b",")
            if per_item > JSON_PIECE_NUMBERS:
                _json_pieces(value[start], out)
            else:
                part = value[start : start + run]
                out.append(_dumps(part.tolist() if isinstance(part, np.ndarray) else part)[1:-1])
        out.append(b"]")


def render_json(content: Any) -> bytes:
    """`content` as compact JSON (`_dumps`), rendered piece by piece (`_json_pieces`)."""
    out: list[bytes] = []
    _json_pieces(content, out)
    return b"".join(out)


async def rendered_json(content: Any) -> bytes:
    """`render_json(content)`, in JSON_POOL when it is large, so that the event loop keeps
    answering meanwhile (health checks, other requests)."""
    if _json_size(content) <= JSON_PIECE_NUMBERS:
        return _dumps(content)
    return await asyncio.get_running_loop().run_in_executor(JSON_POOL, render_json, content)


async def json_answer(content: Any, status: int = 200) -> Response:
    """A JSON answer (as JsonResponse's) rendered off the event loop when large."""
    return Response(await rendered_json(content), status, media_type="application/json")


async def _json_line(content: Any) -> bytes:
    """One NDJSON line, as compact as JsonResponse's bodies."""
    return await rendered_json(content) + b"\n"


def _error(status: int, message: str, **extra: Any) -> JsonResponse:
    return JsonResponse({"error": message, **extra}, status_code=status)


class InternalErrorGuard:
    """ASGI middleware: an exception no handler took becomes 500 `{"error": "internal error"}`.

    Only the exception's type and where it was raised are logged: never its message, which
    may quote the request.
    """

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        """Run the app; answer 500 if it raises before it has started its response."""
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = False

        async def tracked_send(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, receive, tracked_send)
        except Exception as exc:
            frame = exc.__traceback__
            while frame is not None and frame.tb_next is not None:
                frame = frame.tb_next
            where = f"{frame.tb_frame.f_code.co_filename}:{frame.tb_lineno}" if frame else "unknown"
            logger.error(
                "links-ray API: unexpected %s at %s on %s %s",
                type(exc).__name__,
                where,
                scope.get("method"),
                scope.get("path"),
            )
            if started:
                raise
            await _error(500, "internal error")(scope, receive, send)


# `/openapi.json` describes the routes; no interactive docs page, which would load its
# scripts from a CDN.
api = FastAPI(
    title="links-ray",
    version=__version__,
    docs_url=None,
    redoc_url=None,
    openapi_url="/openapi.json",
    default_response_class=JsonResponse,
)
api.add_middleware(InternalErrorGuard)


def request_body(path: str) -> dict[str, Any]:
    """The OpenAPI `requestBody` of a POST route: its model in `models.REQUEST_MODELS`.

    The routes read their bodies themselves (`read_json_object`: size, media type, the
    engine's checks), so FastAPI does not see the model; `api_openapi` adds it."""
    name = models.REQUEST_MODELS[path].__name__
    schema = {"$ref": f"#/components/schemas/{name}"}
    return {"requestBody": {"required": True, "content": {"application/json": {"schema": schema}}}}


ERROR_400 = {
    "description": "Bad Request",
    "content": {"application/json": {"schema": {"$ref": "#/components/schemas/ErrorResponse"}}},
}


def api_openapi() -> dict[str, Any]:
    """FastAPI's document of the routes, plus the request bodies' schemas; made once."""
    if api.openapi_schema is None:
        document = get_openapi(
            title=api.title,
            version=api.version,
            description="The HTTP API of docs/CONTRACT.md. Every bound is a limit of "
            'GET /api/limits; a refused request gets a 4xx and {"error": "<what is wrong>"}.',
            routes=api.routes,
        )
        schemas = document.setdefault("components", {}).setdefault("schemas", {})
        # FastAPI documents a 422 {"detail"} for routes with parameters; this API answers
        # those 400 {"error"} (`_validation_error`), as ErrorResponse says.
        for item in document["paths"].values():
            for operation in item.values():
                answers = operation.get("responses", {})
                if "HTTPValidationError" in json.dumps(answers.get("422", {})):
                    answers.pop("422")
                    answers.setdefault("400", ERROR_400)
        for name in ("HTTPValidationError", "ValidationError"):
            schemas.pop(name, None)
        for model in models.REQUEST_MODELS.values():
            schema = model.model_json_schema(ref_template="#/components/schemas/{model}")
            schemas.update(schema.pop("$defs", {}))
            schemas[model.__name__] = schema
        api.openapi_schema = document
    return api.openapi_schema


api.openapi = api_openapi  # type: ignore[method-assign]


@api.exception_handler(ApiError)
async def _api_error(request: Request, exc: ApiError) -> JsonResponse:
    response = _error(exc.status, exc.message, **exc.extra)
    response.headers.update(exc.headers)
    return response


@api.exception_handler(StarletteHTTPException)
async def _http_error(request: Request, exc: StarletteHTTPException) -> JsonResponse:
    response = _error(exc.status_code, str(exc.detail).lower())
    if exc.headers:
        response.headers.update(exc.headers)
    return response


@api.exception_handler(RequestValidationError)
async def _validation_error(request: Request, exc: RequestValidationError) -> JsonResponse:
    problems = [
        f"{'.'.join(str(part) for part in error.get('loc', ()))}: {error.get('msg', 'invalid')}"
        for error in exc.errors()[:5]
    ]
    return _error(400, "invalid request: " + "; ".join(problems))


# -- reading and checking request bodies ------------------------------------------------------


def _kind(value: object) -> str:
    """The JSON type of `value` for messages (never the value: it may be huge)."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, int | float):
        return "a number"
    if isinstance(value, str):
        return "a string"
    if isinstance(value, list):
        return "an array"
    if isinstance(value, dict):
        return "an object"
    return type(value).__name__


def _is_number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _is_finite(value: int | float) -> bool:
    try:
        return math.isfinite(float(value))
    except OverflowError:  # an integer beyond float64
        return False


def _refuse_constant(name: str) -> float:
    raise ValueError(f"{name} is not a JSON number (numbers must be finite)")


async def read_json_object(request: Request) -> dict[str, Any]:
    """The request body as a JSON object, or ApiError (400, 408, 413 or 415) naming the
    problem. A large body is parsed in JSON_POOL, off the event loop."""
    content_type = request.headers.get("content-type")
    if content_type is not None:
        media = content_type.split(";", 1)[0].strip().lower()
        if media and media != "application/json" and not media.endswith("+json"):
            raise ApiError(
                415, f"the body must be JSON (Content-Type application/json), got {media[:80]!r}"
            )
    declared = request.headers.get("content-length")
    if declared is not None:
        if not declared.strip().isdigit():
            raise ApiError(400, "Content-Length is not a byte count")
        if int(declared) > MAX_BODY_BYTES:
            raise ApiError(413, f"the body is over the limit of {MAX_BODY_BYTES} bytes")
    body = await read_body(request)
    if len(body) <= INLINE_JSON_BYTES:
        return parse_json_object(body)
    return await asyncio.get_running_loop().run_in_executor(JSON_POOL, parse_json_object, body)


async def read_body(request: Request) -> bytes:
    """The request body, at most MAX_BODY_BYTES (else ApiError 413), cut off with 408 when it
    pauses for BODY_TIMEOUT_S or falls behind MIN_BODY_BYTES_PER_S (engine.inputs)."""
    loop = asyncio.get_running_loop()
    start = loop.time()
    chunks: list[bytes] = []
    size = 0
    try:
        async with asyncio.timeout(start + BODY_TIMEOUT_S) as deadline:
            async for chunk in request.stream():
                size += len(chunk)
                if size > MAX_BODY_BYTES:
                    raise ApiError(413, f"the body is over the limit of {MAX_BODY_BYTES} bytes")
                chunks.append(chunk)
                behind = start + BODY_TIMEOUT_S + size / MIN_BODY_BYTES_PER_S
                deadline.reschedule(min(loop.time() + BODY_TIMEOUT_S, behind))
    except ClientDisconnect:  # nobody is left to answer; not a server error
        raise ApiError(400, "the client disconnected before sending the whole body") from None
    except TimeoutError:
        # The rest of the body is never read: the connection is closed after the answer.
        raise ApiError(
            408,
            f"the body came too slowly ({size} bytes in {loop.time() - start:.1f} s): it may "
            f"pause at most {BODY_TIMEOUT_S:g} s and must keep up {MIN_BODY_BYTES_PER_S} "
            "bytes a second",
            headers={"Connection": "close"},
        ) from None
    return b"".join(chunks)


def parse_json_object(body: bytes) -> dict[str, Any]:
    """`body` parsed as a JSON object, or ApiError 400 naming the problem."""
    if not body.strip():
        raise ApiError(400, "the body is empty: expected a JSON object")
    try:
        # orjson holds the GIL for its whole call too, but for several times less than json
        # on a large body of numbers: so much shorter is the stall it can cause the event
        # loop. It refuses what json's messages name (NaN, integers past 64 bits, encodings
        # other than UTF-8), so a body it refuses is parsed again by json, for the message.
        data = orjson.loads(body)
    except orjson.JSONDecodeError:
        data = _parse_json_slowly(body)
    if not isinstance(data, dict):
        raise ApiError(400, f"the body must be a JSON object, got {_kind(data)}")
    return data


def _parse_json_slowly(body: bytes) -> Any:
    """`body` parsed by json, for its messages: ApiError 400 naming the problem."""
    try:
        return json.loads(body, parse_constant=_refuse_constant)
    except UnicodeDecodeError:
        raise ApiError(400, "the body is not UTF-8 text") from None
    except json.JSONDecodeError as exc:
        raise ApiError(
            400, f"the body is not valid JSON: {exc.msg} (line {exc.lineno}, column {exc.colno})"
        ) from None
    except ValueError as exc:  # NaN / Infinity, or an integer with too many digits
        raise ApiError(400, f"the body is not valid JSON: {exc}") from None
    except RecursionError:
        raise ApiError(400, "the body is not valid JSON: nested too deeply") from None


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


#: Coordinates `_plain_pairs` passes: finite, and integers that NumPy reads as int64.
PLAIN_COORDINATE = float(2**62)


def _plain_pairs(pairs: list) -> bool:
    """Whether `pairs` holds only [x, y] lists of JSON numbers within +-PLAIN_COORDINATE: a
    drawn curve's 10,000 points pass in under a millisecond, where `_pairs`' loop that names
    the first bad entry takes several."""
    return all(
        type(pair) is list
        and len(pair) == 2
        and type(pair[0]) in (float, int)
        and type(pair[1]) in (float, int)
        and -PLAIN_COORDINATE < pair[0] < PLAIN_COORDINATE
        and -PLAIN_COORDINATE < pair[1] < PLAIN_COORDINATE
        for pair in pairs
    )


def _pairs(name: str, value: object, count: int | None = None) -> list[list[float]]:
    """`value` as a list of finite [x, y] number pairs (`count` of them if given)."""
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
    return value


def retrieve_args(body: dict[str, Any]) -> tuple[np.ndarray, int, float]:
    """The query points (T, 2), k and min_transmission of a /api/retrieve body, or ApiError
    naming the problem."""
    points = _pairs("points", _required(body, "points"))
    k = body.get("k")
    points, k = _checked(validate_query, points, DEFAULT_K if k is None else k)
    return points, k, _min_transmission(body)


def synthesize_args(
    body: dict[str, Any],
) -> tuple[np.ndarray, int, float | None, bool, float, int, int | None]:
    """(points (T, 2), k, seconds, partial, min_transmission, seed, iterations) of a
    /api/synthesize body, or ApiError naming the problem: the points, k and min_transmission
    as /api/retrieve takes them; seconds None when the work is fixed (iterations)."""
    points = _pairs("points", _required(body, "points"))
    k = body.get("k")
    seconds, seed, iterations = _checked(
        validate_synthesis_work, body.get("seconds"), body.get("seed"), body.get("iterations")
    )
    points, k, budget, partial = _checked(
        validate_synthesis,
        points,
        DEFAULT_K if k is None else k,
        seconds,
        body.get("partial", False),
    )
    budget = None if iterations is not None else budget
    return points, k, budget, partial, _min_transmission(body), seed, iterations


def stream_arg(body: dict[str, Any]) -> bool:
    """A body's `stream` flag (false when absent), or ApiError naming it."""
    return _checked(as_flag, body.get("stream", False), "stream")


def _min_transmission(body: dict[str, Any]) -> float:
    """A body's `min_transmission` in degrees (0 when absent), or ApiError naming it."""
    value = body.get("min_transmission")
    return 0.0 if value is None else _checked(as_transmission_deg, value, "min_transmission")


def topology_args(body: dict[str, Any]) -> tuple[list, list]:
    """(adjacency, node_types) of a /api/simulate or /api/analyze body, shapes checked."""
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
    return adjacency, node_types


def simulate_args(body: dict[str, Any]) -> tuple[list, list, list, int]:
    """(adjacency, node_types, positions, steps) of a /api/simulate body, shapes checked.

    The engine checks the rest (0/1 links, symmetry, joint types, solvability) and names
    what is wrong.
    """
    adjacency, node_types = topology_args(body)
    n = len(adjacency)
    positions = _pairs("positions", _required(body, "positions"), count=n)
    steps = body.get("steps")
    steps = DEFAULT_STEPS if steps is None else _checked(as_steps, steps)
    if n * steps > MAX_REQUEST_JOINT_STEPS:
        raise ApiError(
            413,
            f"simulation too large: {n} joints x {steps} steps = {n * steps}, "
            f"the limit is {MAX_REQUEST_JOINT_STEPS} joint-steps",
        )
    return adjacency, node_types, positions, steps


def analyze_mechanism(
    adjacency: list, node_types: list, positions: list | None, steps: int
) -> dict[str, Any]:
    """The studio's analysis of a mechanism, from the engine's own checks.

    Always: `joints`, `moving`, `links`, `dof` (2 x moving - links), `solvable` (dyadic),
    `problem` (the engine's message, or None), `order` (the solution path as [joint, a, b]
    rows) and `dataset_rules` (the dataset rules it breaks: docs/CONTRACT.md, Mechanisms).
    With positions and a solvable topology also `lock` (None, or `step`, `node` and `angle`,
    the crank's turn in degrees) and, when it locks, `trajectories` [n][step][2] of the steps
    before the lock.
    Raises InvalidMechanismError for degenerate positions, as /api/simulate does.
    """
    moving, links, dof = mobility(adjacency, node_types)
    found: dict[str, Any] = {"joints": len(node_types), "moving": moving, "links": links}
    found["dof"] = dof
    try:
        topology = analyze_topology(adjacency, node_types)
    except InvalidMechanismError as exc:
        return {**found, "solvable": False, "problem": str(exc), "order": [], "lock": None}
    found.update(solvable=True, problem=None, order=topology.order.tolist(), lock=None)
    pose = None if positions is None else np.asarray(positions, dtype=np.float64)
    found["dataset_rules"] = dataset_rule_violations(topology, pose)
    if positions is not None:
        trajectories, step, node = simulate_until_lock(adjacency, node_types, positions, steps)
        if step >= 0:
            found["lock"] = {"step": step, "node": node, "angle": 360.0 * step / steps}
            found["trajectories"] = trajectories  # rendered in pieces (`json_answer`)
    return found


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
    # The engine checks path_joint: an integer naming a moving joint.
    return adjacency, node_types, positions, chosen, crank_mm, body.get("path_joint")


def export_file(
    adjacency: list,
    node_types: list,
    positions: list,
    chosen: str,
    crank_mm: float,
    path_joint: Any,
) -> Response:
    """The mechanism as a file to download (engine.fabrication), or ValueError naming why not."""
    drawing = fabrication(adjacency, node_types, positions, crank_mm, path_joint)
    text = {"svg": drawing.svg, "dxf": drawing.dxf, "table": drawing.table_text}[chosen]()
    media_type, suffix = EXPORT_FORMATS[chosen]
    name = f"mechanism-{len(node_types)}-joints-{crank_mm:g}mm.{suffix}"
    return Response(
        text,
        media_type=media_type,
        headers={
            "Content-Disposition": f'attachment; filename="{name}"',
            "X-Content-Type-Options": "nosniff",
        },
    )


# -- the deployments ----------------------------------------------------------------------------


#: Ray starts worker processes at niceness 15, below its own control plane (GCS, raylet,
#: dashboard agent) at 0. A replica answers users, and its parallel kernels wait for their
#: slowest thread, so it runs at 0: in-replica time per retrieval fell from about 46 to 42 ms.
REPLICA_ENV = {"RAY_worker_niceness": "0"}
#: Retrievals are the throughput work; health checks and simulations must be answered at
#: once. So the thread that retrieves, and the kernels' worker threads it starts, run at this
#: niceness (Linux niceness is per thread, and new threads inherit it), below the replica's
#: event loop and thread pool and any front on the same node, still above Ray's workers.
RETRIEVAL_NICENESS = 5
#: Retrievals one front replica holds at once, running or waiting for the index (its own or
#: the shards'). One more is answered at once with 503, `Retry-After` and a JSON `error`: a
#: burst of retrievals neither piles up without bound nor holds what health checks and
#: simulations need.
MAX_RETRIEVALS = 8
#: Syntheses one front replica holds at once, running or waiting. Each holds the replica's
#: cores for its whole budget (up to MAX_SYNTHESIS_SECONDS), so few; one more is answered 503.
#: One that would wait for the refinement thread longer than its own budget is answered 503
#: too: waiting does not shorten its refinement, whose budget starts when it starts.
MAX_SYNTHESES = 2
#: Seconds a refused client is asked to wait (`Retry-After`).
RETRY_AFTER_S = 1
#: Serve's own bounds on a front replica: requests it runs at once, and requests waiting for
#: one of those slots. Beyond them Serve answers 503 with `Retry-After` itself (its body is
#: Serve's plain text, not JSON). Far above MAX_RETRIEVALS, so that health checks and
#: simulations never wait behind retrievals.
FRONT_MAX_ONGOING, FRONT_MAX_QUEUED = 100, 100
#: Retrievals a shard replica takes at once (it runs them one after another); further ones
#: wait in the callers' routers, which send them to the least busy replica of the shard.
SHARD_MAX_ONGOING = 4
#: How long the front waits for all the shards' answers before answering 503.
SHARD_TIMEOUT_S = 30.0
#: CPUs a shard replica reserves unless told otherwise (and unless `fit_shard_cpus` gives it
#: less on a Ray that `links serve` started itself); Ray counts CPUs in steps of 1 / CPU_STEPS.
SHARD_CPUS, CPU_STEPS = 1.0, 10_000
#: Seconds a stopping replica lets the requests under way finish (Serve's
#: `graceful_shutdown_timeout_s`); then it is stopped whatever it holds. Syntheses at their
#: default budget and every other request finish well within it.
SHUTDOWN_DRAIN_S = 20.0
#: How often a draining replica looks whether its requests are done (Serve's
#: `graceful_shutdown_wait_loop_s`, 2 s by default: an idle replica waited that long to stop).
SHUTDOWN_POLL_S = 0.2
#: Seconds `links serve` gives Serve's controller beyond the drain to stop the replicas and
#: proxies, before it stops Ray under them.
SHUTDOWN_STOP_S = 5.0
#: Shard failures that mean "not there now" (a replica that died or is restarting, a shard
#: with no replica, backpressure): answered 503 with `Retry-After`, not 500.
SHARD_UNAVAILABLE = (
    RayActorError,
    WorkerCrashedError,
    NodeDiedError,
    ObjectLostError,
    TaskCancelledError,  # RequestCancelledError too: a replica stopping under it
    BackPressureError,
    DeploymentUnavailableError,
    ReplicaUnavailableError,
)
#: A four-bar the front simulates once at start, so the solver is loaded before any user asks.
WARM_FOUR_BAR = (
    [[0, 1, 0, 0], [1, 0, 0, 1], [0, 0, 0, 1], [0, 1, 1, 0]],
    [0, 2, 0, 1],
    [[0.5, 0.5], [0.55, 0.5], [0.8, 0.5], [0.6, 0.7]],
)


def _busy(message: str, retry_after: float = RETRY_AFTER_S) -> ApiError:
    """503 with `Retry-After` (whole seconds, at least RETRY_AFTER_S): come back then."""
    seconds = max(RETRY_AFTER_S, math.ceil(retry_after))
    return ApiError(503, message, headers={"Retry-After": str(seconds)})


def replica_cpus() -> float:
    """The CPUs Ray gave this process (a replica's `num_cpus`, fractions kept; 0 if none)."""
    return float(ray.get_runtime_context().get_assigned_resources().get("CPU", 0.0))


def use_replica_cpus() -> None:
    """Have the engine's and the index's threads keep to the CPUs Ray gave this replica
    (`engine.cpus.usable_cpus`), not the machine's."""
    set_given_cpus(replica_cpus())


class _Turn:
    """A synthesis's place in the line for a replica's refinement thread: its refinement
    budget (None for fixed work, whose length is unknown), when its refinement began, and the
    future set when its turn comes."""

    def __init__(self, budget: float | None) -> None:
        self.budget = budget
        self.began: float | None = None
        self.ready: asyncio.Future[None] = asyncio.get_running_loop().create_future()


def _synthesis_answer(results: list[dict], took_ms: float, queued_s: float) -> dict[str, Any]:
    """A synthesis's answer: its results, and the milliseconds it took and waited in them."""
    return {"results": results, "took_ms": round(took_ms, 3), "queued_ms": round(queued_s * 1e3, 3)}


def merge_results(answers: list[list[dict]], k: int) -> list[dict]:
    """The k best of several shards' answers (each best first), ordered as one index orders
    them: by chamfer distance, ties to the lower path id."""
    merged = [result for answer in answers for result in answer]
    merged.sort(key=lambda result: (result["chamfer"], result["path_id"]))
    return merged[:k]


class _Retrieving:
    """An index and the one thread its retrievals run in: one at a time (the index's compiled
    kernels are parallel, and the JIT's workqueue threading layer, its fallback without TBB
    or OpenMP, cannot take concurrent callers), never in the thread pool that simulations
    and analyses run in, and at `RETRIEVAL_NICENESS`. The index is warmed in that thread, so
    the kernels' worker threads exist, at that niceness, before the first user asks."""

    def __init__(self, index: RetrievalIndex) -> None:
        self.index = index
        self.pool = ThreadPoolExecutor(
            max_workers=1, thread_name_prefix="links-retrieve", initializer=_lower_priority
        )
        self.pool.submit(index.warm).result()

    async def retrieve(self, points: np.ndarray, k: int, min_transmission: float) -> list[dict]:
        return await asyncio.get_running_loop().run_in_executor(
            self.pool, self.index.retrieve, points, k, min_transmission
        )

    async def retrieve_waited(
        self, points: np.ndarray, k: int, min_transmission: float
    ) -> tuple[list[dict], float]:
        """`retrieve`'s answer, and the seconds it waited behind other retrievals."""
        asked = time.perf_counter()
        began: list[float] = []

        def run() -> list[dict]:
            began.append(time.perf_counter())
            return self.index.retrieve(points, k, min_transmission)

        results = await asyncio.get_running_loop().run_in_executor(self.pool, run)
        return results, began[0] - asked

    def close(self) -> None:
        self.pool.shutdown(wait=False, cancel_futures=True)


def _lower_priority() -> None:
    """This thread (and the threads it starts) at RETRIEVAL_NICENESS, if that is lower
    priority than it has; where threads have no niceness of their own, nothing."""
    try:
        thread = threading.get_native_id()
        if os.getpriority(os.PRIO_PROCESS, thread) < RETRIEVAL_NICENESS:
            os.setpriority(os.PRIO_PROCESS, thread, RETRIEVAL_NICENESS)
    except (AttributeError, OSError):  # not Linux
        pass


@serve.deployment(
    name="IndexShard",
    max_ongoing_requests=SHARD_MAX_ONGOING,
    graceful_shutdown_timeout_s=SHUTDOWN_DRAIN_S,
    graceful_shutdown_wait_loop_s=SHUTDOWN_POLL_S,
    ray_actor_options={"num_cpus": 1, "runtime_env": {"env_vars": REPLICA_ENV}},
)
class IndexShard:
    """One part of the retrieval index: the curated shards numbered `part` modulo `parts`.

    Called by the front (`LinksApi`) through its deployment handle, never over HTTP. It opens
    (or builds and saves, under `_links/index/part-P-of-N/`) its part once, warms it, and
    answers each query with its own top k, as a whole index over its paths would.
    """

    def __init__(self, root: str, part: int, parts: int) -> None:
        use_replica_cpus()
        self.part, self.parts = part, parts
        self._retrieving = _Retrieving(RetrievalIndex.open(root, part=part, parts=parts))

    async def info(self) -> dict[str, int]:
        """`{"part", "parts", "paths"}` of this shard."""
        return {"part": self.part, "parts": self.parts, "paths": len(self._retrieving.index)}

    async def retrieve(
        self, points: np.ndarray, k: int, min_transmission: float = 0.0
    ) -> list[dict]:
        """The k best results of this part, best first (`RetrievalIndex.retrieve`)."""
        return await self._retrieving.retrieve(points, k, min_transmission)

    def __del__(self) -> None:
        if hasattr(self, "_retrieving"):
            self._retrieving.close()


@serve.deployment(
    name="LinksApi",
    max_ongoing_requests=FRONT_MAX_ONGOING,
    max_queued_requests=FRONT_MAX_QUEUED,
    backpressure_config={"status_code": 503, "retry_after_s": RETRY_AFTER_S},
    graceful_shutdown_timeout_s=SHUTDOWN_DRAIN_S,
    graceful_shutdown_wait_loop_s=SHUTDOWN_POLL_S,
    ray_actor_options={"num_cpus": 1, "runtime_env": {"env_vars": REPLICA_ENV}},
)
@serve.ingress(api)
class LinksApi:
    """The HTTP API of one replica: the retrieval index of `root`, opened once; or, given
    `shards` (deployment handles of `IndexShard` parts 0..N-1, in order), the front that asks
    them all and merges their answers, holding no index itself."""

    def __init__(
        self,
        root: str,
        shards: list[DeploymentHandle] | None = None,
        max_retrievals: int = MAX_RETRIEVALS,
        shard_timeout_s: float = SHARD_TIMEOUT_S,
    ) -> None:
        use_replica_cpus()
        self.root = root
        self.shards = list(shards or [])
        self.max_retrievals = max_retrievals
        self.shard_timeout_s = shard_timeout_s
        self._retrievals = 0  # running or waiting; only the event loop's thread counts
        self._shard_paths: list[int] | None = None  # learned from the shards once
        self._retrieving: _Retrieving | None = None
        self._syntheses = 0  # running or waiting; only the event loop's thread counts
        self._line: list[_Turn] = []  # for the refinement thread: the first holds it
        # Refinement runs here, one synthesis at a time (each uses every core itself), at the
        # retrievals' niceness, never in the thread pool health checks and simulations use.
        self._refining = ThreadPoolExecutor(
            max_workers=1, thread_name_prefix="links-synthesize", initializer=_lower_priority
        )
        if self.shards:
            simulate(*WARM_FOUR_BAR, steps=8)  # loads the solver /api/simulate uses
        else:  # warming the index also loads the solver /api/simulate uses
            self._retrieving = _Retrieving(RetrievalIndex.open(root))
        studio_files()  # a package without the studio fails here, not on a user's first visit
        # What the replica holds from here on (the index, the compiled kernels, the libraries'
        # objects) is not garbage: out of the collector's sight, a full collection (which the
        # objects of large bodies and answers set off) walks only what requests made, not a
        # quarter of a million objects, which held the GIL for 0.3 s.
        gc.collect()
        gc.freeze()
        # A thread that wants the GIL (the event loop's, to answer a health check) waits this
        # long before the holder must yield it: 5 ms by default, paid at every hop of a request
        # while JSON is parsed or rendered in JSON_POOL.
        sys.setswitchinterval(GIL_SWITCH_S)

    def __del__(self) -> None:
        if getattr(self, "_retrieving", None) is not None:
            self._retrieving.close()
        if hasattr(self, "_refining"):
            self._refining.shutdown(wait=False, cancel_futures=True)

    @api.get("/", response_class=HTMLResponse)
    async def api_studio(self) -> Response:
        """The web studio's page."""
        return studio_response("index.html")

    @api.get("/studio/{name}")
    async def api_studio_file(self, name: str) -> Response:
        """One of the studio's scripts or its style sheet; 404 for any other name."""
        return studio_response(name)

    @api.get("/api/health", response_model=models.HealthResponse)
    async def api_health(self) -> JsonResponse:
        """`{"status": "ok", "paths": <indexed paths>}`, and with shards their parts' paths."""
        if self._retrieving is not None:
            return JsonResponse({"status": "ok", "paths": len(self._retrieving.index)})
        counts = await self._shard_counts()
        shards = [{"part": part, "paths": paths} for part, paths in enumerate(counts)]
        return JsonResponse({"status": "ok", "paths": sum(counts), "shards": shards})

    @api.get("/api/limits", response_model=models.LimitsResponse)
    async def api_limits(self) -> JsonResponse:
        """The limits every request meets (the studio reads its own from here)."""
        return JsonResponse(request_limits())

    @api.post(
        "/api/simulate",
        response_model=models.SimulateResponse,
        responses={
            422: {"model": models.LockingResponse, "description": "it locks"},
            **models.error_responses(400, 413, 415),
        },
        openapi_extra=request_body("/api/simulate"),
    )
    async def api_simulate(self, request: Request) -> Response:
        """Trajectories [n][steps][2] of a mechanism, 422 if it locks, 4xx if malformed."""
        args = simulate_args(await read_json_object(request))
        try:
            trajectories = await run_in_threadpool(simulate, *args)
        except LockingError as exc:
            return _error(422, "locking", step=exc.step, node=exc.node)
        except ValueError as exc:  # InvalidMechanismError names the problem
            raise ApiError(400, str(exc)) from None
        return await json_answer({"trajectories": trajectories})

    @api.post(
        "/api/analyze",
        response_model=models.AnalyzeResponse,
        responses=models.error_responses(400, 413, 415),
        openapi_extra=request_body("/api/analyze"),
    )
    async def api_analyze(self, request: Request) -> Response:
        """Degree of freedom, dyadic solvability and, given positions, where it locks."""
        body = await read_json_object(request)
        if body.get("positions") is None:
            adjacency, node_types = topology_args(body)
            args = (adjacency, node_types, None, DEFAULT_STEPS)
        else:
            args = simulate_args(body)
        try:
            found = await run_in_threadpool(analyze_mechanism, *args)
        except ValueError as exc:  # degenerate positions: named as /api/simulate names them
            raise ApiError(400, str(exc)) from None
        return await json_answer(found)

    @api.post(
        "/api/export",
        response_class=Response,
        responses={
            200: {
                "description": "the file, as an attachment",
                "content": {media: {} for media, _ in EXPORT_FORMATS.values()},
            },
            **models.error_responses(400, 413, 415),
            422: {"model": models.LockingResponse},
        },
        openapi_extra=request_body("/api/export"),
    )
    async def api_export(self, request: Request) -> Response:
        """The mechanism as an SVG, DXF or table file in millimetres, its crank `crank_mm`
        long (default 20), with the path of `path_joint` if given; 422 if that path locks,
        other 4xx JSON if it cannot."""
        args = export_args(await read_json_object(request))
        try:
            return await run_in_threadpool(export_file, *args)
        except LockingError as exc:  # only with a path: a locking mechanism has none
            return _error(422, f"{exc}: it has no full path to draw", step=exc.step, node=exc.node)
        except ValueError as exc:  # the engine's message: the mechanism, the scale, path_joint
            raise ApiError(400, str(exc)) from None

    @api.post(
        "/api/retrieve",
        response_model=models.RetrieveResponse,
        responses=models.error_responses(400, 413, 415, 503),
        openapi_extra=request_body("/api/retrieve"),
    )
    async def api_retrieve(self, request: Request) -> Response:
        """The k curated paths nearest to a drawn curve, best first, with their mechanisms;
        503 with `Retry-After` when MAX_RETRIEVALS are already under way here."""
        self._claim_retrieval()  # refused before reading the body
        try:
            points, k, floor = retrieve_args(await read_json_object(request))
            start = time.perf_counter()
            if self._retrieving is not None:
                try:
                    results = await self._retrieving.retrieve(points, k, floor)
                except ValueError as exc:
                    raise ApiError(400, str(exc)) from None
            else:
                answers = await self._ask_shards("retrieve", points, k, floor)
                results = merge_results(answers, k)
            took_ms = (time.perf_counter() - start) * 1e3
        finally:
            self._retrievals -= 1
        return await json_answer({"results": results, "took_ms": round(took_ms, 3)})

    @api.post(
        "/api/synthesize",
        response_model=models.SynthesizeResponse,
        responses=models.error_responses(400, 413, 415, 503),
        openapi_extra=request_body("/api/synthesize"),
    )
    async def api_synthesize(self, request: Request) -> Response:
        """Mechanisms retrieved for a drawn curve and refined onto it, best first, within the
        request's `seconds` (or for its fixed `iterations`); 503 with `Retry-After` when
        MAX_SYNTHESES are under way here, when its retrieval would pass the retrieval limit,
        or when it would wait longer than its own budget. The budget starts when its
        refinement does (its retrieval counted), and `queued_ms` says how long it waited.
        With `"stream": true` the answer is NDJSON: a `{"progress": ...}` line each time the
        best so far improves, then the answer's own line (`_synthesis_lines`)."""
        if self._syntheses >= MAX_SYNTHESES:  # refused before reading the body
            raise _busy(
                f"busy: {self._syntheses} syntheses under way, the most this server holds; "
                f"retry after {RETRY_AFTER_S} s"
            )
        self._syntheses += 1
        turn: _Turn | None = None
        released = True  # until the refinement, once submitted, releases its place itself
        try:
            body = await read_json_object(request)
            points, k, seconds, partial, floor, seed, iterations = synthesize_args(body)
            stream = stream_arg(body)
            start = time.perf_counter()
            retrieved, waited = await self._synthesis_candidates(points, max(CANDIDATES, k), floor)
            retrieved_at = time.perf_counter()
            retrieval_s = retrieved_at - start - waited
            budget = None if seconds is None else max(0.0, seconds - retrieval_s)
            # Fixed work is not weakened by waiting; it waits as long as a request may take.
            patience = (MAX_SYNTHESIS_SECONDS if seconds is None else seconds) - waited
            turn = await self._wait_for_refiner(budget, patience)
            loop = asyncio.get_running_loop()
            reports: asyncio.Queue[dict[str, Any]] = asyncio.Queue()

            def refine() -> tuple[list[dict], float]:
                began = time.perf_counter()
                results = refine_retrieved(
                    points,
                    retrieved,
                    k,
                    seconds,
                    partial,
                    started=began - retrieval_s,  # waiting spent none of the budget
                    seed=seed,
                    margin_deg=floor,
                    progress=(
                        (lambda best: loop.call_soon_threadsafe(reports.put_nowait, best))
                        if stream
                        else None
                    ),
                    iterations=iterations,
                )
                return results, waited + began - retrieved_at

            turn.began = time.perf_counter()
            refining = loop.run_in_executor(self._refining, refine)
            # The place is freed when the refinement ends, whether or not anyone still
            # reads its stream (a client gone mid-stream must not hold it for good).
            refining.add_done_callback(functools.partial(self._synthesis_done, turn))
            released = False
            if stream:
                return StreamingResponse(
                    self._synthesis_lines(reports, refining, start),
                    media_type="application/x-ndjson",
                )
            results, queued_s = await refining
            took_ms = (time.perf_counter() - start) * 1e3
        finally:
            if released:
                self._syntheses -= 1
                if turn is not None:
                    self._next_turn(turn)
        return await json_answer(_synthesis_answer(results, took_ms, queued_s))

    async def _synthesis_candidates(
        self, points: np.ndarray, count: int, floor: float
    ) -> tuple[list[dict], float]:
        """A synthesis's retrieved candidates, counted against the retrieval limit as any
        retrieval (503 beyond it), and the seconds they waited behind other retrievals (0
        with shards: they wait in the shards' replicas)."""
        self._claim_retrieval()
        try:
            if self._retrieving is not None:
                return await self._retrieving.retrieve_waited(points, count, floor)
            answers = await self._ask_shards("retrieve", points, count, floor)
            return merge_results(answers, count), 0.0
        finally:
            self._retrievals -= 1

    def _claim_retrieval(self) -> None:
        """Count one more retrieval under way, or refuse it 503 at the limit."""
        if self._retrievals >= self.max_retrievals:
            raise _busy(
                f"busy: {self._retrievals} retrievals under way, the most this server "
                f"holds; retry after {RETRY_AFTER_S} s"
            )
        self._retrievals += 1

    def _expected_wait(self) -> float | None:
        """Seconds until the syntheses in line end their budgets; None if one does fixed work
        (its length is not known beforehand)."""
        now = time.perf_counter()
        wait = 0.0
        for turn in self._line:
            if turn.budget is None:
                return None
            wait += turn.budget if turn.began is None else max(0.0, turn.began + turn.budget - now)
        return wait

    async def _wait_for_refiner(self, budget: float | None, patience: float) -> _Turn:
        """This synthesis's turn at the refinement thread, once the ones before it are done;
        503 with `Retry-After` if it would wait longer than `patience` seconds: at once when
        the wait is known beforehand, else once it has waited that long."""
        expected = self._expected_wait()
        if expected is not None and expected > patience:
            raise _busy(
                f"busy: the syntheses under way end in about {expected:.1f} s, longer than "
                f"this one may wait ({max(0.0, patience):.1f} s of its budget)",
                retry_after=expected - max(0.0, patience),
            )
        turn = _Turn(budget)
        self._line.append(turn)
        if len(self._line) == 1:
            turn.ready.set_result(None)
        try:
            await asyncio.wait({turn.ready}, timeout=max(0.0, patience))
        except BaseException:  # the client went away: its place, or its turn, goes on
            self._next_turn(turn)
            raise
        if not turn.ready.done():
            self._next_turn(turn)
            raise _busy(
                f"busy: waited {max(0.0, patience):.1f} s for the syntheses under way, as "
                "long as this one may wait; retry after they end"
            )
        return turn

    def _next_turn(self, turn: _Turn) -> None:
        """`turn` is done with the refinement thread: the next in line takes it."""
        self._line.remove(turn)
        if self._line and not self._line[0].ready.done():
            self._line[0].ready.set_result(None)

    def _synthesis_done(self, turn: _Turn, _: object = None) -> None:
        self._syntheses -= 1
        self._next_turn(turn)

    async def _synthesis_lines(
        self,
        reports: asyncio.Queue[dict[str, Any]],
        refining: asyncio.Future[tuple[list[dict], float]],
        start: float,
    ) -> AsyncIterator[bytes]:
        """A streamed synthesis: `{"progress": best so far}` lines while it refines, then
        `{"results", "took_ms", "queued_ms"}` (or `{"error"}` if it failed after the stream
        began)."""
        while not refining.done() or not reports.empty():
            waiting = asyncio.ensure_future(reports.get())
            await asyncio.wait({waiting, refining}, return_when=asyncio.FIRST_COMPLETED)
            if waiting.done():
                yield await _json_line({"progress": waiting.result()})
            else:
                waiting.cancel()
        try:
            results, queued_s = refining.result()
        except Exception as exc:  # the status is sent: the failure can only be a line
            logger.warning("links-ray API: a streamed synthesis failed (%s)", type(exc).__name__)
            yield await _json_line({"error": "synthesis failed"})
            return
        took_ms = (time.perf_counter() - start) * 1e3
        yield await _json_line(_synthesis_answer(results, took_ms, queued_s))

    async def _shard_counts(self) -> list[int]:
        """Each shard's paths, asked once (a shard's index does not change while it serves)."""
        if self._shard_paths is None:
            infos = await self._ask_shards("info")
            self._shard_paths = [info["paths"] for info in infos]
        return self._shard_paths

    async def _ask_shards(self, method: str, *args: Any) -> list[Any]:
        """Every shard's answer to `method(*args)`, in part order, asked at once; ApiError
        503 if one is unavailable or they do not all answer within `shard_timeout_s`."""
        tasks = [
            asyncio.ensure_future(self._ask_shard(part, getattr(shard, method).remote(*args)))
            for part, shard in enumerate(self.shards)
        ]
        try:
            return await asyncio.wait_for(asyncio.gather(*tasks), self.shard_timeout_s)
        except TimeoutError:
            raise _busy(
                f"the index shards did not answer within {self.shard_timeout_s:g} s"
            ) from None
        finally:
            for task in tasks:  # after a failure, stop asking the others
                task.cancel()

    async def _ask_shard(self, part: int, response: DeploymentResponse) -> Any:
        """One shard's answer; its failures as ApiErrors: 503 for a shard that is not there
        now, 400 for a query it refuses, else 500 (logged by type, never the request)."""
        try:
            return await response
        except asyncio.CancelledError:  # another part failed, or time ran out: stop this one
            response.cancel()
            raise
        except SHARD_UNAVAILABLE as exc:
            logger.warning(
                "links-ray API: shard %d of %d unavailable (%s)",
                part,
                len(self.shards),
                type(exc).__name__,
            )
            raise _busy(f"index shard {part} of {len(self.shards)} is unavailable") from None
        except RayTaskError as exc:  # the shard's own exception
            if isinstance(exc.cause, ValueError):
                raise ApiError(400, str(exc.cause)) from None
            logger.error(
                "links-ray API: shard %d of %d failed with %s",
                part,
                len(self.shards),
                type(exc.cause).__name__,
            )
            raise ApiError(500, "internal error") from None


def check_root(root: str, shards: int | None = None) -> None:
    """Fail early, with ValueError naming the problem, if `root` has no curated table, or has
    a part without curated shards when split in `shards` parts."""
    store = Store.open(root, writable=False)
    open_table(store, "curated")
    if shards:
        numbers = [
            shard
            for shard, marker in committed_shards(store, "curation").items()
            if "curated" in marker["files"]
        ]
        empty = sorted(set(range(shards)) - {shard % shards for shard in numbers})
        if empty:
            raise ValueError(
                f"{store.uri} has {len(numbers)} curated shards: split in {shards} parts, "
                f"part {empty[0]} would have none; use fewer shards"
            )


def _positive(name: str, value: object, kind: type = int) -> Any:
    """`value` if it is a positive integer (`kind` int) or a positive finite number (`kind`
    float, which takes integers too), else ValueError naming `name`."""
    accepted = (int, float) if kind is float else (int,)
    if (
        isinstance(value, bool)
        or not isinstance(value, accepted)
        or not (value > 0 and math.isfinite(value))
    ):
        what = "integer" if kind is int else "number"
        raise ValueError(f"{name} must be a positive {what}, got {value!r}")
    return value


def build_app(
    root: str,
    replicas: int = 1,
    shards: int | None = None,
    shard_cpus: float = SHARD_CPUS,
    shard_memory_gb: float | None = None,
    max_retrievals: int = MAX_RETRIEVALS,
    shard_timeout_s: float = SHARD_TIMEOUT_S,
) -> Application:
    """The Serve application for dataset `root` (not yet running).

    Without `shards`, `replicas` replicas of `LinksApi`, each holding the whole index. With
    `shards` = N, N `IndexShard` deployments (`IndexShard-P-of-N`), each of `replicas`
    replicas holding part P, with `shard_cpus` CPUs and `shard_memory_gb` GB of memory
    reserved in Ray per replica, placed wherever the cluster has room; and `replicas`
    replicas of the front, `LinksApi`, which asks them all.
    """
    _positive("replicas", replicas)
    _positive("max_retrievals", max_retrievals)
    _positive("shard_timeout_s", shard_timeout_s, float)
    front = LinksApi.options(num_replicas=replicas)
    if shards is None:
        return front.bind(root, max_retrievals=max_retrievals, shard_timeout_s=shard_timeout_s)
    _positive("shards", shards)
    options: dict[str, Any] = {
        "num_cpus": _positive("shard_cpus", shard_cpus, float),
        "runtime_env": {"env_vars": REPLICA_ENV},
    }
    if shard_memory_gb is not None:
        options["memory"] = round(_positive("shard_memory_gb", shard_memory_gb, float) * 1e9)
    parts = [
        IndexShard.options(
            name=f"IndexShard-{part}-of-{shards}",
            num_replicas=replicas,
            ray_actor_options=options,
        ).bind(root, part, shards)
        for part in range(shards)
    ]
    return front.bind(root, parts, max_retrievals=max_retrievals, shard_timeout_s=shard_timeout_s)


#: The args of the Serve config application (`app_builder`), and how each is read.
APP_ARGS = {
    "root": str,
    "replicas": int,
    "shards": int,
    "shard_cpus": float,
    "shard_memory_gb": float,
    "max_retrievals": int,
}


def _arg(args: dict[str, Any], name: str) -> Any:
    """Config arg `name`, checked as its type in APP_ARGS (`serve run ... replicas=2` passes
    strings, which are read as numbers first)."""
    value, kind = args[name], APP_ARGS[name]
    if isinstance(value, str):
        try:
            value = kind(value.strip())
        except ValueError:
            pass
    try:
        return _positive(name, value, kind)
    except ValueError:
        what = "integer" if kind is int else "number"
        raise ValueError(f"args.{name} must be a positive {what}, got {args[name]!r}") from None


def app_builder(args: dict[str, Any]) -> Application:
    """Application builder for Serve config files: args `root` (required), `replicas`,
    `shards`, `shard_cpus`, `shard_memory_gb` and `max_retrievals` (see `build_app`)."""
    if "root" not in args or not str(args["root"]).strip():
        raise ValueError("the links application needs args.root: a dataset folder or s3://...")
    unknown = sorted(set(args) - set(APP_ARGS))
    if unknown:
        raise ValueError(f"unknown args for the links application: {unknown}")
    given = {name: _arg(args, name) for name in args if name != "root"}
    check_root(str(args["root"]), given.get("shards"))
    return build_app(str(args["root"]), **given)


def direct_ingress_env(port: int) -> dict[str, str]:
    """The environment under which Ray Serve's HTTP ingress replica serves on `port` itself.

    Ray reads it when it starts (its controller and replicas inherit it). A released port is
    taken back at once, so a restarted replica answers on the same port; and a stopping
    replica drains for a second, not 30: there is no load balancer in front to leave.
    """
    return {
        "RAY_SERVE_ENABLE_DIRECT_INGRESS": "1",
        "RAY_SERVE_DIRECT_INGRESS_MIN_HTTP_PORT": str(port),
        "RAY_SERVE_DIRECT_INGRESS_MAX_HTTP_PORT": str(port + 1),  # exclusive
        "RAY_SERVE_PORT_QUARANTINE_S": "0",
        "RAY_SERVE_DIRECT_INGRESS_MIN_DRAINING_PERIOD_S": "1",
    }


def bindable_port(host: str, port: int) -> int:
    """`port` (a free one if 0) if it can be bound on `host`, else ValueError naming why."""
    try:
        with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as probe:
            # As servers bind: connections that just closed do not hold the port.
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            probe.bind((host, port))
            return probe.getsockname()[1]
    except OSError as exc:
        raise ValueError(f"cannot serve on {host} port {port}: {exc.strerror}") from None


def check_fits(
    replicas: int,
    shards: int | None,
    shard_cpus: float,
    shard_memory_gb: float | None,
    resources: dict[str, float],
) -> None:
    """ValueError unless the app of `build_app` fits in a Ray of these total `resources`."""
    cpus = float(replicas)  # the front: one CPU a replica
    memory = 0.0
    if shards:
        cpus += shards * replicas * shard_cpus
        memory = shards * replicas * (shard_memory_gb or 0.0) * 1e9
    have_cpus = resources.get("CPU", 0.0)
    if cpus > have_cpus + 1e-9:
        each = "1 a front replica" + (f", {shard_cpus:g} a shard replica" if shards else "")
        raise ValueError(
            f"the app needs {cpus:g} CPUs ({each}) and this Ray has {have_cpus:g}: "
            "serve fewer replicas or shards, or give shards fewer CPUs (--shard-cpus)"
        )
    have_memory = resources.get("memory", 0.0)
    if memory > have_memory:
        raise ValueError(
            f"the shards reserve {memory / 1e9:.1f} GB and this Ray has "
            f"{have_memory / 1e9:.1f} GB to give: lower --shard-memory-gb"
        )


def fit_shard_cpus(replicas: int, shards: int, resources: dict[str, float]) -> float:
    """CPUs each shard replica reserves on one machine's Ray of these `resources`: SHARD_CPUS
    if the app fits so, else an equal share of what the front's replicas (one CPU each) leave,
    rounded down to Ray's steps (1 / CPU_STEPS); ValueError if they leave none."""
    have = resources.get("CPU", 0.0)
    if float(replicas) + shards * replicas * SHARD_CPUS <= have + 1e-9:
        return SHARD_CPUS
    left = math.floor(round((have - replicas) * CPU_STEPS, 6))  # in steps
    share = max(left, 0) // (shards * replicas)
    if share == 0:
        raise ValueError(
            f"this Ray has {have:g} CPUs and the front takes {replicas} (one a replica): none "
            "is left for the shards; serve fewer replicas, or no shards"
        )
    return share / CPU_STEPS


def run_server(
    root: str,
    host: str = "127.0.0.1",
    port: int = 8000,
    replicas: int = 1,
    blocking: bool = True,
    shards: int | None = None,
    shard_cpus: float | None = None,
    shard_memory_gb: float | None = None,
) -> None:
    """Serve `root` on http://host:port/ (Ray local unless RAY_ADDRESS) until Ctrl-C; with
    `shards`, split the index into that many `IndexShard` deployments (`build_app`), each
    replica reserving `shard_cpus` CPUs (default SHARD_CPUS).

    When this call starts Ray and serves one replica (of the front, with shards), the replica
    answers on `port` directly (`direct_ingress_env`) and Serve's proxy takes a free port;
    otherwise the proxy answers. On a Ray it starts itself, shards given no `shard_cpus`
    share what the front leaves when SHARD_CPUS each would not fit (`fit_shard_cpus`, said
    in one line on stderr), and an app that cannot fit is refused at once (ValueError naming
    what it needs), where Serve would wait for resources forever.
    """
    import ray

    from links_ray.cluster.connect import connect

    check_root(root, shards)  # a wrong ROOT is one line here, not a replica failing to start
    cpus = SHARD_CPUS if shard_cpus is None else shard_cpus
    app = build_app(root, replicas, shards, cpus, shard_memory_gb)  # checks the numbers first
    local = not ray.is_initialized() and not os.environ.get("RAY_ADDRESS")
    direct = replicas == 1 and local
    proxy_port = port
    if direct:
        bindable_port(host, port)  # else the replica retries and fails without saying why
        os.environ.update(direct_ingress_env(port))
        proxy_port = bindable_port(host, 0)
    if blocking:
        # A service manager stops with SIGTERM: shut down as on Ctrl-C, not with a stack
        # trace, from the start on (set again once Ray has started: it sets its own).
        signal.signal(signal.SIGTERM, signal.default_int_handler)
    stop = True
    try:
        connect()
        if blocking:
            signal.signal(signal.SIGTERM, signal.default_int_handler)
        if local:
            resources = ray.cluster_resources()
            if shards and shard_cpus is None:
                cpus = fit_shard_cpus(replicas, shards, resources)
                if cpus < SHARD_CPUS:
                    print(
                        f"links-ray: this Ray has {resources.get('CPU', 0.0):g} CPUs and the "
                        f"front takes {replicas}: each of the {shards * replicas} shard "
                        f"replicas reserves {cpus:g} CPU (--shard-cpus to choose)",
                        file=sys.stderr,
                        flush=True,
                    )
                    app = build_app(root, replicas, shards, cpus, shard_memory_gb)
            check_fits(replicas, shards, cpus, shard_memory_gb, resources)
        no_access_log = {"enable_access_log": False}
        serve.start(http_options={"host": host, "port": proxy_port}, logging_config=no_access_log)
        serve.run(app, name="links", route_prefix="/", logging_config=no_access_log)
        shown = f"[{host}]" if ":" in host else host
        print(f"links-ray: serving {root} at http://{shown}:{port}/ (API under /api)", flush=True)
        if not blocking:
            stop = False
            return
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        print("links-ray: shutting down", flush=True)
    finally:
        if stop:
            stop_serving(ray_started=local)
            if blocking:
                # The process ends next: the interpreter's last collections need not walk
                # the whole heap of the libraries it loaded, which takes seconds.
                gc.freeze()


def stop_serving(ray_started: bool) -> None:
    """Stop Serve, then Ray if this process started it, in bounded time: the replicas drain
    the requests under way for at most SHUTDOWN_DRAIN_S (a replica with none stops at once),
    Serve's controller gets SHUTDOWN_STOP_S more to stop them and the proxies, then Ray stops.
    `serve.shutdown()` alone waited for the controller for 30 s, and the replicas for 20 s
    each, and left Ray to the interpreter's exit."""
    import ray

    signal.signal(signal.SIGTERM, signal.SIG_IGN)  # a second one must not cut the drain short
    # `serve.shutdown()` with a bound: it takes none; its client's `shutdown` does.
    client = serve.context._get_global_client(raise_if_no_controller_running=False)
    if client is not None:
        client.shutdown(timeout_s=SHUTDOWN_DRAIN_S + SHUTDOWN_STOP_S)
    serve.context._disconnect()
    if ray_started:
        ray.shutdown()
