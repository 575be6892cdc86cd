"""The FastAPI app `api` that the serve deployments answer with: its errors, JSON and OpenAPI.

Every bad request gets a 4xx with a JSON `{"error": "<what is wrong>"}`: handlers raise
`ApiError`, and FastAPI's own refusals (unknown routes and methods, malformed parameters) are
answered the same way. Anything unexpected is logged by exception type and location only
(never a request body) and answered 500 `{"error": "internal error"}` (`InternalErrorGuard`);
the replica keeps serving.

Answers are compact JSON that refuses NaN and infinity (`JsonResponse`). A large answer is
rendered in pieces (`render_json`) in `JSON_POOL`'s one thread, off the event loop that answers
health checks (`json_answer`); large request bodies are parsed there too (`serve.parsing`).

`GET /openapi.json` is FastAPI's document of the routes plus the request bodies' schemas from
`serve.models` (`api_openapi`), since the routes read their bodies themselves.
"""

import asyncio
import ipaddress
import json
import logging
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.utils import get_openapi
from fastapi.responses import JSONResponse, Response
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from links_ray import __version__
from links_ray.serve import models

#: Where the API logs what it cannot answer (Ray Serve's own logger, so its replicas' logs).
logger = logging.getLogger("ray.serve")


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


#: The most numbers one call of the JSON encoder renders. The encoder and the parser are C
#: code that holds the GIL until it returns, so in any thread one long call stalls the event
#: loop for its whole length; pieces of this size let it in between.
JSON_PIECE_NUMBERS = 1024
#: Bodies up to this many bytes are parsed on the event loop, too briefly to hold it up;
#: larger ones in `JSON_POOL`.
INLINE_JSON_BYTES = 64 * 1024
#: The one thread that parses large request bodies and renders large answers. One, so that
#: at most one long run of the GIL-holding JSON code is under way at a time, whatever the
#: number of clients: the event loop waits for at most one piece of it.
JSON_POOL = ThreadPoolExecutor(max_workers=1, thread_name_prefix="links-json")


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


#: Longest host name (RFC 1035), and the characters one may hold.
MAX_HOST_NAME_CHARS = 253
_HOST_NAME_CHARS = frozenset("abcdefghijklmnopqrstuvwxyz0123456789-.")


def as_host_names(names: object) -> frozenset[str]:
    """Host names a server answers to besides addresses and `localhost` (`HostGuard`), lower
    case; `*` for any. ValueError naming a name that is not one."""
    if isinstance(names, str) or not isinstance(names, list | tuple | set | frozenset):
        raise ValueError(f"allowed hosts must be a list of host names, got {type(names).__name__}")
    checked = set()
    for name in names:
        text = name.strip().lower().rstrip(".") if isinstance(name, str) else ""
        if text != "*" and not (
            0 < len(text) <= MAX_HOST_NAME_CHARS
            and set(text) <= _HOST_NAME_CHARS
            and not text.startswith(("-", "."))
        ):
            shown = repr(name)[:80]
            raise ValueError(f"allowed hosts: {shown} is not a host name (or * for any)")
        checked.add(text)
    return frozenset(checked)


def host_name(header: str) -> str:
    """The host of a Host header, lower case, without its port or an IPv6 address's brackets."""
    text = header.strip().lower()
    if text.startswith("["):
        return text[1 : text.find("]")] if "]" in text else text
    return text.rsplit(":", 1)[0] if text.count(":") == 1 else text


def host_allowed(header: str | None, names: frozenset[str]) -> bool:
    """Whether a request that says it is for host `header` may be answered: an address (no
    DNS answer can stand behind it), `localhost` or a name under it, or one of `names` (`*`
    takes any). A DNS name the server was not told of is how a web page reaches a loopback
    server through a name of its own (DNS rebinding), so it is refused."""
    if header is None:
        return False
    host = host_name(header).rstrip(".")
    if "*" in names or host in names or host == "localhost" or host.endswith(".localhost"):
        return True
    try:
        ipaddress.ip_address(host)
    except ValueError:
        return False
    return True


#: The host names this process's app answers to besides addresses and localhost: set by the
#: front replica's constructor (`allow_host_names`), read by `HostGuard` on every request.
_allowed_host_names: frozenset[str] = frozenset()


def allow_host_names(names: object) -> None:
    """Have this process's app answer requests for `names` too (`as_host_names`); the front
    replica calls it with its `allowed_hosts` when it starts."""
    global _allowed_host_names
    _allowed_host_names = as_host_names(names)


class HostGuard:
    """ASGI middleware: a request whose Host header `host_allowed` refuses gets 400 with a
    JSON error saying how to let it in, before anything reads its body."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        """Refuse the request, or pass it on."""
        if scope["type"] == "http":
            headers = dict(scope.get("headers") or ())
            raw = headers.get(b"host")
            header = raw.decode("latin-1") if raw is not None else None
            if not host_allowed(header, _allowed_host_names):
                said = "no Host header" if header is None else f"Host {header[:80]!r}"
                message = (
                    f"{said}: this server answers its addresses, localhost and the names it "
                    "is given (links serve --allow-host NAME, or the app's allowed_hosts)"
                )
                await _error(400, message)(scope, receive, send)
                return
        await self.app(scope, receive, send)


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
api.add_middleware(HostGuard)  # added last, so it runs first


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
    # The routes are declared in `handlers`, which imports this module: a document made
    # before they are would list none, and be kept.
    from links_ray.serve import handlers  # noqa: F401

    if api.openapi_schema is None:
        document = get_openapi(
            title=api.title,
            version=api.version,
            description="The HTTP API of docs/reference/contract.md. Every bound is a limit of "
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
