"""What the request gate (`serve.http.gate`) counts, reads and writes besides h11: its refusals,
whole JSON answers written as bytes; the bodies and bytes it holds at once; the request line's
length, counted as it arrives; the headers that belong to one connection, not passed on.
"""

from __future__ import annotations

import json
from collections.abc import Iterable

import h11

from links_ray.serve.http.limits import MAX_HEAD_BYTES, MAX_URL_BYTES, RETRY_AFTER_S

#: Headers that describe one connection, not the request or answer, and so are not passed on
#: (h11 frames each side's messages itself).
HOP_HEADERS = frozenset(
    {
        b"connection",
        b"keep-alive",
        b"proxy-connection",
        b"te",
        b"trailer",
        b"transfer-encoding",
        b"upgrade",
        b"content-length",
        b"expect",
    }
)


class Refusal(Exception):
    """A request the gate answers itself: its status, message and extra headers."""

    def __init__(self, status: int, message: str, retry: bool = False) -> None:
        super().__init__(message)
        self.status = status
        self.message = message
        self.retry = retry


class BodyBudget:
    """The bodies the gate reads at once, and their bytes; used on the event loop only."""

    def __init__(self, bodies: int, body_bytes: int) -> None:
        self.max_bodies, self.max_bytes = bodies, body_bytes
        self.bodies = 0
        self.bytes = 0

    def start_body(self) -> None:
        """Count one more body arriving, or refuse it 503."""
        if self.bodies >= self.max_bodies:
            raise Refusal(503, f"busy: {self.bodies} request bodies arriving at once", retry=True)
        self.bodies += 1

    def take(self, count: int) -> None:
        """Count `count` more bytes held, or refuse the body 503."""
        if self.bytes + count > self.max_bytes:
            raise Refusal(
                503, f"busy: {self.bytes} bytes of request bodies held at once", retry=True
            )
        self.bytes += count

    def end_body(self) -> None:
        """One body arriving fewer."""
        self.bodies -= 1

    def give_back(self, count: int) -> None:
        """`count` bytes held fewer."""
        self.bytes -= count


def header_value(headers: Iterable[tuple[bytes, bytes]], name: bytes) -> str | None:
    """The value of header `name` (lower case) among h11's `headers`, if given."""
    for key, value in headers:
        if key == name:
            return value.decode("latin-1")
    return None


class RequestLine:
    """Counts the request line's bytes as they arrive, piece by piece (never searching what
    came before again), skipping the empty lines a client may send before a request."""

    def __init__(self) -> None:
        self.length = 0
        self.seen = False

    def over(self, data: bytes) -> bool:
        """Take the next piece; whether the request line is now known to be over
        MAX_URL_BYTES."""
        start = 0
        while not self.seen:
            end = data.find(b"\n", start)
            if end < 0:
                self.length += len(data) - start
                break
            self.length += end - start
            if self.length > 1:  # more than a lone CR: the request line itself
                self.seen = True
            else:
                self.length = 0
            start = end + 1
        return self.length > MAX_URL_BYTES


def head_status(exc: h11.RemoteProtocolError) -> int:
    """431 for a head over the limit (h11's hint), else 400."""
    return 431 if exc.error_status_hint == 431 else 400


def head_message(exc: h11.RemoteProtocolError) -> str:
    """What a client whose head h11 refused is told."""
    if exc.error_status_hint == 431:
        return f"the request head is over {MAX_HEAD_BYTES} bytes"
    return f"malformed request head: {str(exc)[:120]}"


_REASONS = {
    400: "Bad Request",
    408: "Request Timeout",
    413: "Content Too Large",
    414: "URI Too Long",
    431: "Request Header Fields Too Large",
    503: "Service Unavailable",
}


def refusal_bytes(status: int, message: str, retry: bool = False) -> bytes:
    """A whole JSON refusal, written without h11 (for a head h11 could not read)."""
    body = json.dumps({"error": message}).encode()
    lines = [
        f"HTTP/1.1 {status} {_REASONS.get(status, 'Error')}",
        "Content-Type: application/json",
        f"Content-Length: {len(body)}",
        "X-Content-Type-Options: nosniff",
        "Connection: close",
    ]
    if retry:
        lines.append(f"Retry-After: {RETRY_AFTER_S}")
    return ("\r\n".join(lines) + "\r\n\r\n").encode() + body
