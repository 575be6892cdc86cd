"""The clients of `links bench hostile`: each a way a single machine's clients can try to hold
or exhaust a server, written at the socket level so that nothing between them and the server
makes them kinder.

Each attack takes the server's port and returns what every client got: its `status` (None if
the server closed without an answer, or the client gave up), the `seconds` it took, and the
first answer's `error` message.
"""

from __future__ import annotations

import json
import socket
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any

#: How long a client waits for an answer before it gives up (status None).
ANSWER_WAIT_S = 120.0

Answer = dict[str, Any]


def read_answer(sock: socket.socket, began: float) -> Answer:
    """The status and JSON error of the answer on `sock`, however far it came."""
    data = b""
    try:
        while b"\r\n\r\n" not in data or len(data) < _wanted(data):
            piece = sock.recv(65536)
            if not piece:
                break
            data += piece
    except OSError:
        pass
    seconds = time.perf_counter() - began
    if not data.startswith(b"HTTP/"):
        return {"status": None, "seconds": seconds, "error": None}
    head, _, body = data.partition(b"\r\n\r\n")
    error = None
    try:
        error = json.loads(body).get("error")
    except (ValueError, AttributeError):
        pass
    return {"status": int(head.split()[1]), "seconds": seconds, "error": error}


def _wanted(data: bytes) -> int:
    """Bytes of the whole answer, once its head says (its Content-Length), else the head's."""
    head, _, _ = data.partition(b"\r\n\r\n")
    for line in head.split(b"\r\n")[1:]:
        name, _, value = line.partition(b":")
        if name.strip().lower() == b"content-length" and value.strip().isdigit():
            return len(head) + 4 + int(value)
    return len(head) + 4


def _connect(port: int) -> socket.socket:
    return socket.create_connection(("127.0.0.1", port), timeout=ANSWER_WAIT_S)


def crowd(clients: int, attack: Callable[[], Answer]) -> list[Answer]:
    """`attack` run by `clients` threads at once: every answer."""
    answers: list[Answer] = []
    lock = threading.Lock()

    def run() -> None:
        try:
            answer = attack()
        except OSError as exc:
            answer = {"status": None, "seconds": 0.0, "error": type(exc).__name__}
        with lock:
            answers.append(answer)

    threads = [threading.Thread(target=run) for _ in range(clients)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    return answers


def _retrieval_head(length: int) -> bytes:
    return (
        b"POST /api/retrieve HTTP/1.1\r\nHost: 127.0.0.1\r\n"
        b"Content-Type: application/json\r\nContent-Length: " + str(length).encode() + b"\r\n\r\n"
    )


def headers_only(port: int) -> Answer:
    """A retrieval's headers, declaring a body that never comes."""
    began = time.perf_counter()
    with _connect(port) as sock:
        sock.sendall(_retrieval_head(300))
        return read_answer(sock, began)


def _drip(sock: socket.socket, pieces: Iterable[bytes]) -> None:
    """Send `pieces` a second apart, until the server answers or closes."""
    for piece in pieces:
        try:
            sock.sendall(piece)
        except OSError:
            return
        time.sleep(1.0)
        sock.setblocking(False)
        try:
            if sock.recv(1, socket.MSG_PEEK):
                return  # answered already
        except BlockingIOError:
            pass
        except OSError:
            return
        finally:
            sock.setblocking(True)
            sock.settimeout(ANSWER_WAIT_S)


def trickling(port: int, seconds: float) -> Answer:
    """A retrieval whose body comes a byte a second for `seconds` (or until refused)."""
    began = time.perf_counter()
    body = json.dumps({"points": [[0, 0], [1, 0.5], [2, 0], [1, -1]]}).encode().ljust(300)
    with _connect(port) as sock:
        sock.sendall(_retrieval_head(len(body)))
        _drip(sock, (bytes([byte]) for byte in body[: int(seconds)]))
        return read_answer(sock, began)


def many_headers(port: int, headers: int = 20_000) -> Answer:
    """A health check with `headers` small headers."""
    began = time.perf_counter()
    lines = b"".join(b"x-h%d: v\r\n" % index for index in range(headers))
    with _connect(port) as sock:
        try:
            sock.sendall(b"GET /api/health HTTP/1.1\r\nHost: 127.0.0.1\r\n" + lines + b"\r\n")
        except OSError:
            pass
        return read_answer(sock, began)


def long_url(port: int, total_bytes: int = 6 * 1024 * 1024, piece: int = 1024) -> Answer:
    """A request line of `total_bytes`, sent in pieces of `piece` bytes."""
    began = time.perf_counter()
    with _connect(port) as sock:
        try:
            sock.sendall(b"GET /api/health?q=")
            filler = b"a" * piece
            for _ in range(total_bytes // piece):
                sock.sendall(filler)
            sock.sendall(b" HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        except OSError:
            pass
        return read_answer(sock, began)


def endless_headers(port: int, seconds: float = 60.0) -> Answer:
    """Headers that never end: one more line a second, for up to `seconds`."""
    began = time.perf_counter()
    with _connect(port) as sock:
        sock.sendall(b"GET /api/health HTTP/1.1\r\nHost: 127.0.0.1\r\n")
        _drip(sock, (b"x-more-%d: v\r\n" % index for index in range(int(seconds))))
        return read_answer(sock, began)


def not_reading(port: int, body: bytes, hold_s: float) -> Answer:
    """A simulation asked for and its answer left unread for `hold_s` seconds, then read."""
    began = time.perf_counter()
    with _connect(port) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        sock.sendall(
            b"POST /api/simulate HTTP/1.1\r\nHost: 127.0.0.1\r\n"
            b"Content-Type: application/json\r\nContent-Length: "
            + str(len(body)).encode()
            + b"\r\n\r\n"
            + body
        )
        time.sleep(hold_s)
        return read_answer(sock, began)


def over_limit_body(port: int, points: int) -> Answer:
    """A retrieval of `points` points, over the point limit, sent whole."""
    began = time.perf_counter()
    body = json.dumps({"points": [[0.123456, 0.654321]] * points}).encode()
    with _connect(port) as sock:
        try:
            sock.sendall(_retrieval_head(len(body)) + body)
        except OSError:
            pass
        answer = read_answer(sock, began)
    return {**answer, "bytes": len(body)}


def padded_content_length(port: int, digits: int = 5000) -> Answer:
    """A retrieval whose Content-Length is `digits` digits, zero-padded."""
    began = time.perf_counter()
    body = b'{"points": [[0, 0], [1, 0.5], [2, 0], [1, -1]]}'
    length = str(len(body)).rjust(digits, "0").encode()
    with _connect(port) as sock:
        sock.sendall(
            b"POST /api/retrieve HTTP/1.1\r\nHost: 127.0.0.1\r\n"
            b"Content-Type: application/json\r\nContent-Length: " + length + b"\r\n\r\n" + body
        )
        return read_answer(sock, began)


def foreign_host(port: int, path: str) -> Answer:
    """GET `path` for a Host the server was not told of (how DNS rebinding reaches it)."""
    began = time.perf_counter()
    with _connect(port) as sock:
        sock.sendall(b"GET " + path.encode() + b" HTTP/1.1\r\nHost: rebound.example\r\n\r\n")
        return read_answer(sock, began)


def post_json(port: int, path: str, payload: Any) -> Answer:
    """One JSON POST, read whole."""
    began = time.perf_counter()
    body = json.dumps(payload).encode()
    with _connect(port) as sock:
        sock.sendall(
            b"POST " + path.encode() + b" HTTP/1.1\r\nHost: 127.0.0.1\r\n"
            b"Content-Type: application/json\r\nContent-Length: "
            + str(len(body)).encode()
            + b"\r\n\r\n"
            + body
        )
        return read_answer(sock, began)
