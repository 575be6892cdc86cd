"""The request gate (`links_ray.serve.http.gate`) before a real HTTP server (uvicorn, as under
Serve), over real sockets on loopback: requests pass whole and answers come back; heads and
bodies over their limits are refused as they arrive (414, 431, 408, 413, 400); crowds of idle
and trickling clients hold only the gate, while health and real requests are answered; a
client that goes away is seen by the app; and the gate's own bounds (bodies at once, requests
passed on at once) refuse with 503 and Retry-After, never holding health.

Timeouts are made short here (monkeypatched) so that the crowds finish in seconds; the limits
in bytes and counts are the shipped ones.
"""

from __future__ import annotations

import asyncio
import http.client
import json
import socket
import threading
import time
from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import pytest
import uvicorn
from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import JSONResponse, Response
from starlette.routing import Route

from links_ray.bench import hostile_clients
from links_ray.serve.http import gate as gate_module
from links_ray.serve.http import limits
from links_ray.serve.http.gate import GateThread, RequestGate
from tests.support.serving import links_serve, low_port

#: The short timeouts of these tests (seconds): the head's, the body's pause, a send's.
HEAD_S, BODY_S, SEND_S = 1.5, 1.5, 1.5


class Backend:
    """A real uvicorn server with a small app, in a thread: what the gate passes requests to.
    `disconnected` is set when the app sees a client of `/wait` go away."""

    def __init__(self) -> None:
        self.disconnected = threading.Event()
        self.waiting = threading.Event()
        self.release = threading.Event()
        app = Starlette(
            routes=[
                Route("/api/health", self.health),
                Route("/echo", self.echo, methods=["POST", "GET"]),
                Route("/wait", self.wait, methods=["POST"]),
                Route("/hold", self.hold),
                Route("/big", self.big),
            ]
        )
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.server = uvicorn.Server(uvicorn.Config(app, log_level="warning", lifespan="off"))
        self.thread = threading.Thread(
            target=lambda: self.server.run(sockets=[self.sock]), daemon=True
        )

    async def health(self, request: Request) -> Response:
        return JSONResponse({"status": "ok"})

    async def echo(self, request: Request) -> Response:
        body = await request.body()
        return JSONResponse(
            {
                "bytes": len(body),
                "head": body[:20].decode("latin-1"),
                "host": request.headers.get("host"),
                "path": request.url.path,
                "query": request.url.query,
            }
        )

    async def wait(self, request: Request) -> Response:
        await request.body()
        self.waiting.set()
        while not await request.is_disconnected():
            await asyncio.sleep(0.05)
        self.disconnected.set()
        return JSONResponse({"status": "gone"})

    async def hold(self, request: Request) -> Response:
        self.waiting.set()
        while not self.release.is_set():
            await asyncio.sleep(0.05)
        return JSONResponse({"status": "released"})

    async def big(self, request: Request) -> Response:
        return Response(b"x" * (8 * 1024 * 1024), media_type="application/octet-stream")


@pytest.fixture(scope="module")
def backend() -> Iterator[Backend]:
    server = Backend()
    server.thread.start()
    deadline = time.monotonic() + 30
    while not server.server.started and time.monotonic() < deadline:
        time.sleep(0.05)
    yield server
    server.server.should_exit = True
    server.thread.join(timeout=10)


@pytest.fixture
def short_timeouts(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(gate_module, "HEAD_TIMEOUT_S", HEAD_S)
    monkeypatch.setattr(limits, "BODY_TIMEOUT_S", BODY_S)
    monkeypatch.setattr(gate_module, "SEND_TIMEOUT_S", SEND_S)


@pytest.fixture
def gate(backend: Backend, short_timeouts: None) -> Iterator[RequestGate]:
    running = GateThread(RequestGate("127.0.0.1", 0, backend.port, {"links.test"}))
    running.start()
    yield running.gate
    running.stop()


def request(
    port: int, method: str, path: str, body: bytes | None = None, headers: dict | None = None
) -> tuple[int, dict, bytes]:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=60)
    try:
        conn.request(method, path, body=body, headers=headers or {})
        response = conn.getresponse()
        return response.status, dict(response.getheaders()), response.read()
    finally:
        conn.close()


def raw(port: int, data: bytes, wait: float = 60.0) -> dict:
    """Send `data` on a new connection; the answer (`hostile_clients.read_answer`)."""
    began = time.perf_counter()
    with socket.create_connection(("127.0.0.1", port), timeout=wait) as sock:
        sock.sendall(data)
        return hostile_clients.read_answer(sock, began)


def test_requests_pass_whole_and_answers_come_back(gate: RequestGate) -> None:
    status, _, body = request(gate.port, "POST", "/echo?x=1", b"a" * 100_000)
    assert status == 200
    answer = json.loads(body)
    assert answer["bytes"] == 100_000 and answer["path"] == "/echo" and answer["query"] == "x=1"
    assert answer["host"] == f"127.0.0.1:{gate.port}"
    # Kept alive: three requests on one connection, and a chunked body.
    conn = http.client.HTTPConnection("127.0.0.1", gate.port, timeout=30)
    for size in (0, 3, 70_000):
        conn.request("POST", "/echo", body=b"b" * size)
        response = conn.getresponse()
        assert response.status == 200 and json.loads(response.read())["bytes"] == size
    conn.request("POST", "/echo", body=iter([b"ab", b"cd" * 40_000]), encode_chunked=True)
    response = conn.getresponse()
    assert json.loads(response.read())["bytes"] == 80_002
    conn.close()
    # A client that waits for 100 Continue before its body (as curl does for large ones).
    with socket.create_connection(("127.0.0.1", gate.port), timeout=30) as sock:
        sock.sendall(
            b"POST /echo HTTP/1.1\r\nHost: localhost\r\nContent-Length: 5\r\n"
            b"Expect: 100-continue\r\n\r\n"
        )
        assert sock.recv(100).startswith(b"HTTP/1.1 100 ")
        sock.sendall(b"hello")
        answer = hostile_clients.read_answer(sock, time.perf_counter())
    assert answer["status"] == 200
    # A large answer, whole.
    status, _, body = request(gate.port, "GET", "/big")
    assert status == 200 and len(body) == 8 * 1024 * 1024


def test_heads_over_their_limits_are_refused_as_they_arrive(gate: RequestGate) -> None:
    # The request line: refused once it passes its limit, long before the client is done.
    with socket.create_connection(("127.0.0.1", gate.port), timeout=30) as sock:
        sock.sendall(b"GET /echo?q=")
        sent = 0
        try:
            while sent < 6 * 1024 * 1024:
                sock.sendall(b"a" * 1024)
                sent += 1024
        except OSError:
            pass
        answer = hostile_clients.read_answer(sock, time.perf_counter())
    assert answer["status"] == 414 and str(limits.MAX_URL_BYTES) in answer["error"]
    assert sent < 4 * 1024 * 1024  # the gate stopped reading, the client could not go on
    many = b"".join(b"x-h%d: v\r\n" % i for i in range(limits.MAX_HEADERS + 1))
    answer = raw(gate.port, b"GET /echo HTTP/1.1\r\nHost: localhost\r\n" + many + b"\r\n")
    assert answer["status"] == 431 and f"{limits.MAX_HEADERS} headers" in answer["error"]
    big = b"x-big: " + b"v" * limits.MAX_HEAD_BYTES + b"\r\n"
    answer = raw(gate.port, b"GET /echo HTTP/1.1\r\nHost: localhost\r\n" + big + b"\r\n")
    assert answer["status"] == 431 and str(limits.MAX_HEAD_BYTES) in answer["error"]
    # Headers that never end: 408 at the head's timeout, not when the client stops.
    answer = hostile_clients.endless_headers(gate.port, seconds=30)
    assert answer["status"] == 408 and "head" in answer["error"]
    assert answer["seconds"] < 10


def test_malformed_framing_is_400_and_large_bodies_413_unread(gate: RequestGate) -> None:
    answer = hostile_clients.padded_content_length(gate.port, digits=5000)
    assert answer["status"] == 400 and "Content-Length" in answer["error"]
    answer = raw(gate.port, b"GET /echo HTTP/1.1\r\nHost: localhost\r\nContent-Length: -1\r\n\r\n")
    assert answer["status"] == 400
    answer = raw(gate.port, b"NOT HTTP AT ALL\r\n\r\n")
    assert answer["status"] == 400
    declared = str(limits.MAX_BODY_BYTES + 1).encode()
    answer = raw(
        gate.port,
        b"POST /echo HTTP/1.1\r\nHost: localhost\r\nContent-Length: " + declared + b"\r\n\r\n",
    )
    assert answer["status"] == 413  # at once: nothing of the body was sent
    conn = http.client.HTTPConnection("127.0.0.1", gate.port, timeout=30)
    try:
        conn.request("POST", "/echo", body=iter([b"a" * 1024 * 1024] * 3), encode_chunked=True)
    except OSError:
        pass  # the gate may close before the last piece
    response = conn.getresponse()
    status, body = response.status, response.read()
    conn.close()
    assert status == 413 and str(limits.MAX_BODY_BYTES) in json.loads(body)["error"]


def test_hosts_are_checked_before_any_route(gate: RequestGate) -> None:
    for path in ("/-/routes", "/-/healthz", "/api/health", "/echo"):
        answer = raw(
            gate.port, b"GET " + path.encode() + b" HTTP/1.1\r\nHost: rebound.example\r\n\r\n"
        )
        assert answer["status"] == 400 and "rebound.example" in answer["error"], path
    answer = raw(gate.port, b"GET /api/health HTTP/1.1\r\n\r\n")
    assert answer["status"] == 400 and "Host" in answer["error"]
    status, _, _ = request(gate.port, "GET", "/api/health", headers={"Host": "links.test:80"})
    assert status == 200


class HealthWatch:
    """Health asked for every 0.25 s, each answer's status and seconds kept, until `stop`."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.checks: list[tuple[int | None, float]] = []
        self.done = threading.Event()
        self.thread = threading.Thread(target=self.run)
        self.thread.start()

    def run(self) -> None:
        while not self.done.is_set():
            began = time.perf_counter()
            try:
                status = request(self.port, "GET", "/api/health")[0]
            except OSError:
                status = None
            self.checks.append((status, time.perf_counter() - began))
            self.done.wait(0.25)

    def stop(self) -> list[tuple[int | None, float]]:
        self.done.set()
        self.thread.join()
        return self.checks


def test_crowds_of_idle_and_trickling_clients_hold_only_the_gate(gate: RequestGate) -> None:
    """210 clients that send a head and no body, and 210 that send theirs a byte a second:
    each ends with 408 within the body's timeout, health is answered within 1 s throughout,
    and a real request meanwhile is answered."""
    watch = HealthWatch(gate.port)
    answers: list[dict] = []

    def both() -> None:
        answers.extend(hostile_clients.crowd(210, lambda: hostile_clients.headers_only(gate.port)))

    def trickle() -> None:
        answers.extend(hostile_clients.crowd(210, lambda: hostile_clients.trickling(gate.port, 20)))

    crowds = [threading.Thread(target=both), threading.Thread(target=trickle)]
    for thread in crowds:
        thread.start()
    time.sleep(0.5)
    assert gate.connections >= 100  # the crowds are held meanwhile
    status, _, body = request(gate.port, "POST", "/echo", b"real")
    for thread in crowds:
        thread.join()
    checks = watch.stop()
    assert status == 200 and json.loads(body)["bytes"] == 4
    assert Counter(answer["status"] for answer in answers) == {408: 420}
    assert all(answer["seconds"] < BODY_S + 5 for answer in answers)
    assert len(checks) >= 3
    assert all(status == 200 and seconds < 1.0 for status, seconds in checks), checks
    assert gate.connections <= 1  # every held connection has ended


def test_a_client_that_goes_away_is_seen_by_the_app(gate: RequestGate, backend: Backend) -> None:
    backend.disconnected.clear()
    backend.waiting.clear()
    with socket.create_connection(("127.0.0.1", gate.port), timeout=30) as sock:
        sock.sendall(b"POST /wait HTTP/1.1\r\nHost: localhost\r\nContent-Length: 2\r\n\r\n{}")
        assert backend.waiting.wait(10)
    assert backend.disconnected.wait(10)


def test_answers_a_client_does_not_read_end_its_connection(
    gate: RequestGate, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Serve's answer is taken whole at once (its place is free), and the client that leaves
    it unread loses its connection at the send deadline: SEND_TIMEOUT_S plus the answer's size
    at MIN_SEND_BYTES_PER_S."""
    monkeypatch.setattr(gate_module, "MIN_SEND_BYTES_PER_S", 2 * 1024 * 1024)
    deadline_s = SEND_S + 8 * 1024 * 1024 / (2 * 1024 * 1024)
    with socket.create_connection(("127.0.0.1", gate.port), timeout=30) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        began = time.monotonic()
        sock.sendall(b"GET /big HTTP/1.1\r\nHost: localhost\r\n\r\n")
        while gate.answer_bytes == 0 and time.monotonic() - began < 10:
            time.sleep(0.01)
        assert gate.answer_bytes == 8 * 1024 * 1024  # taken from Serve, waiting for the client
        assert gate._passing is not None and not gate._passing.locked()
        while gate.connections and time.monotonic() - began < 60:
            time.sleep(0.1)
        ended = time.monotonic() - began
        # Ended by the gate while the client still held its socket, unread.
        assert gate.connections == 0 and gate.answer_bytes == 0
        assert deadline_s - 1 < ended < deadline_s + 10
    assert request(gate.port, "GET", "/api/health")[0] == 200


def test_the_gates_bounds_refuse_with_503_and_never_hold_health(
    backend: Backend, short_timeouts: None, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(gate_module, "MAX_BODIES_READING", 3)
    monkeypatch.setattr(gate_module, "MAX_PASSED", 1)
    monkeypatch.setattr(gate_module, "PASS_WAIT_S", 0.5)
    running = GateThread(RequestGate("127.0.0.1", 0, backend.port))
    running.start()
    port = running.gate.port
    try:
        held = [socket.create_connection(("127.0.0.1", port)) for _ in range(3)]
        for sock in held:
            sock.sendall(b"POST /echo HTTP/1.1\r\nHost: localhost\r\nContent-Length: 9\r\n\r\n{")
        time.sleep(0.3)
        answer = hostile_clients.post_json(port, "/echo", {"a": 1})
        assert answer["status"] == 503 and "bodies" in answer["error"]
        for sock in held:
            sock.close()
        # One request passed on and held by the app: the next waits, then 503; health passes.
        backend.release.clear()
        backend.waiting.clear()
        holder = threading.Thread(target=lambda: request(port, "GET", "/hold"))
        holder.start()
        assert backend.waiting.wait(10)
        status, headers, body = request(port, "GET", "/echo")
        assert status == 503 and headers["Retry-After"] == "1"
        assert "under way" in json.loads(body)["error"]
        assert request(port, "GET", "/api/health")[0] == 200
        backend.release.set()
        holder.join()
        assert request(port, "GET", "/echo")[0] == 200
    finally:
        running.stop()


@pytest.mark.ray
def test_links_serve_holds_crowds_of_idle_clients_in_its_gate(
    lean_dataset: str, tmp_path: Path
) -> None:
    """`links serve` as a user starts it: 210 clients that send a retrieval's head and no
    body, and 210 that send theirs a byte a second. Health, asked every 0.25 s, answers 200
    within 1 s throughout; each held connection ends with 408 within the body timeout; a real
    retrieval meanwhile gets 200."""
    port = low_port()
    with links_serve(lean_dataset, port, tmp_path / "stderr.txt") as served:
        watch = HealthWatch(port)
        answers: list[dict] = []

        def idle() -> None:
            answers.extend(hostile_clients.crowd(210, lambda: hostile_clients.headers_only(port)))

        def trickle() -> None:
            answers.extend(hostile_clients.crowd(210, lambda: hostile_clients.trickling(port, 40)))

        crowds = [threading.Thread(target=idle), threading.Thread(target=trickle)]
        for thread in crowds:
            thread.start()
        time.sleep(2.0)
        status, data = served.post("/api/retrieve", {"points": [[0, 0], [1, 0.5], [2, 0], [1, -1]]})
        for thread in crowds:
            thread.join()
        checks = watch.stop()
    assert status == 200 and len(data["results"]) == 3
    assert Counter(answer["status"] for answer in answers) == {408: 420}
    assert all(answer["seconds"] < limits.BODY_TIMEOUT_S + 5 for answer in answers)
    assert len(checks) >= 20
    assert all(status == 200 and seconds < 1.0 for status, seconds in checks), checks


def test_closing_lets_the_requests_passed_on_finish(backend: Backend) -> None:
    """At shutdown the gate stops listening, ends idle connections at once, and lets a request
    already passed on finish (within its drain), its client answered in full."""
    running = GateThread(RequestGate("127.0.0.1", 0, backend.port))
    running.start()
    port = running.gate.port
    backend.release.clear()
    backend.waiting.clear()
    answer: dict = {}

    def hold() -> None:
        status, _, body = request(port, "GET", "/hold")
        answer.update(status=status, body=body)

    holder = threading.Thread(target=hold)
    holder.start()
    idle = socket.create_connection(("127.0.0.1", port), timeout=30)
    assert backend.waiting.wait(10)
    threading.Timer(1.0, backend.release.set).start()
    began = time.monotonic()
    running.stop(drain_s=20.0)
    holder.join(timeout=30)
    assert answer["status"] == 200 and json.loads(answer["body"])["status"] == "released"
    assert 0.5 < time.monotonic() - began < 10
    try:
        ended = idle.recv(10)
    except ConnectionResetError:  # reset, never accepted: ended as surely
        ended = b""
    assert ended == b""  # the idle connection was ended, unanswered
    idle.close()
    with pytest.raises(OSError):
        socket.create_connection(("127.0.0.1", port), timeout=5).close()
