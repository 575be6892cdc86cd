"""A request body's bytes, read and parsed: within its size and pace (413 over `MAX_BODY_BYTES`,
408 for a body that pauses `BODY_TIMEOUT_S` or falls behind `MIN_BODY_BYTES_PER_S`), and parsed
as a JSON object (400 naming what is wrong). What each route takes from the object is
`serve.http.bodies`'. No Ray.
"""

import asyncio
import json
from typing import Any

import orjson
from fastapi import Request
from starlette.requests import ClientDisconnect

from links_ray.serve.http.limits import (
    BODY_TIMEOUT_S,
    MAX_BODY_BYTES,
    MAX_JSON_DEPTH,
    MIN_BODY_BYTES_PER_S,
    body_deadline,
)
from links_ray.serve.http.responses import ApiError


def json_kind(value: object) -> str:
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


class _NotANumber(ValueError):
    """NaN, Infinity or -Infinity in a body: words JavaScript's JSON.stringify never writes."""


def _refuse_constant(name: str) -> float:
    raise _NotANumber(f"{name} is not a JSON number (numbers must be finite)")


async def read_body(request: Request) -> bytes:
    """The request body, at most MAX_BODY_BYTES (else ApiError 413), cut off with 408 when it
    pauses for BODY_TIMEOUT_S or falls behind MIN_BODY_BYTES_PER_S (`limits.body_deadline`,
    as `links serve`'s request gate reads it first)."""
    loop = asyncio.get_running_loop()
    start = loop.time()
    chunks: list[bytes] = []
    size = 0
    try:
        # A point in the loop's time, from the start: a client that sends the headers and
        # nothing more is cut off as surely as one that stops halfway.
        async with asyncio.timeout_at(start + BODY_TIMEOUT_S) as deadline:
            async for chunk in request.stream():
                size += len(chunk)
                if size > MAX_BODY_BYTES:
                    raise ApiError(413, f"the body is over the limit of {MAX_BODY_BYTES} bytes")
                chunks.append(chunk)
                deadline.reschedule(body_deadline(start, loop.time(), size))
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
    """`body` parsed as a JSON object, or ApiError 400 naming the problem.

    orjson is the one parser of request bodies: it holds the GIL for its whole call too, but
    for several times less than json on a large body of numbers, and it bounds what a body can
    ask of it (nesting 1024 deep at most; every number a float64 or a 64-bit integer, larger
    integers read as floats, infinite ones refused). json reads a refused body again only to
    word the refusal better (NaN, a line and column), and its answer is never used: a body
    one parser refuses is refused."""
    if not body.strip():
        raise ApiError(400, "the body is empty: expected a JSON object")
    try:
        data = orjson.loads(body)
    except orjson.JSONDecodeError as exc:
        raise ApiError(400, _refusal(body, exc)) from None
    if not isinstance(data, dict):
        raise ApiError(400, f"the body must be a JSON object, got {json_kind(data)}")
    return data


def _refusal(body: bytes, refused: orjson.JSONDecodeError) -> str:
    """Why orjson refused `body`, in json's words where they say more (NaN and Infinity, a
    line and column), else in orjson's."""
    not_json = "the body is not valid JSON"
    if refused.msg == "depth limit exceeded":
        return f"{not_json}: nested too deeply (more than {MAX_JSON_DEPTH} levels)"
    try:
        json.loads(body, parse_constant=_refuse_constant)
    except UnicodeDecodeError:
        return "the body is not UTF-8 text"
    except json.JSONDecodeError as exc:
        return f"{not_json}: {exc.msg} (line {exc.lineno}, column {exc.colno})"
    except _NotANumber as exc:
        return f"{not_json}: {exc}"
    except RecursionError:
        return f"{not_json}: nested too deeply (more than {MAX_JSON_DEPTH} levels)"
    except ValueError:  # an integer of too many digits, which orjson's words say
        pass
    return f"{not_json}: {refused.msg} (line {refused.lineno}, column {refused.colno})"
