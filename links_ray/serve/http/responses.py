"""What the API answers with: `ApiError` for a refused request, and compact JSON.

Every bad request gets a 4xx with a JSON `{"error": "<what is wrong>"}`: routes raise
`ApiError`, which the app (`serve.http.asgi`) turns into that answer (`error_response`).

Answers are compact JSON that refuses NaN and infinity (`JsonResponse`). A large answer is rendered
in pieces (`render_json`) in `JSON_POOL`'s one thread, off the event loop that answers health checks
(`json_answer`); large request bodies are parsed there too (`serve.http.bodies`). Every answer says
`X-Content-Type-Options: nosniff` (`nosniff`, which `serve.http.middleware.HostGuard` applies to
all).
"""

import asyncio
import json
import logging
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
from fastapi.responses import JSONResponse, Response
from starlette.types import Message, Send

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
    """`json.dumps` fallback for numpy scalars and arrays: where a retrieval result's arrays
    become lists, the numbers `tolist` gives (those of a list made before rendering)."""
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


async def json_line(content: Any) -> bytes:
    """One NDJSON line, as compact as JsonResponse's bodies."""
    return await rendered_json(content) + b"\n"


#: The header every answer of the app carries: a browser takes each answer for the type it
#: names and never guesses another (an error quoting a request is never read as HTML).
NOSNIFF = (b"x-content-type-options", b"nosniff")


def nosniff(send: Send) -> Send:
    """`send` that adds NOSNIFF to the headers of a response that lacks it."""

    async def sending(message: Message) -> None:
        if message["type"] == "http.response.start":
            headers = list(message.get("headers", ()))
            if all(name.lower() != NOSNIFF[0] for name, _ in headers):
                message = {**message, "headers": [*headers, NOSNIFF]}
        await send(message)

    return sending


def error_response(status: int, message: str, **extra: Any) -> JsonResponse:
    """The answer to a refused request: `{"error": message, **extra}` with `status`."""
    return JsonResponse({"error": message, **extra}, status_code=status)
