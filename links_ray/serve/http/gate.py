"""The request gate `links serve` puts before Ray Serve (`RequestGate`): every request is read
whole, under bounds, before it is passed to Serve on loopback, so that a client that sends
slowly or not at all holds the gate's memory, never one of Serve's places (which Serve gives a
request as soon as its headers arrive; docs/design/architecture.md says why).

A head keeps to the head limits of `serve.http.limits` (414, 431, 408) and names an allowed Host
(`guards.host_allowed`, before any route, Serve's `/-/` ones too); a body keeps to the body
pace (`limits.body_deadline`, 408) and size (413), within the gate's bounds on bodies and bytes
at once (503). Then at most MAX_PASSED requests at once go to Serve (health skips that line),
whose whole answer is taken and sent on within a pace. A client that goes away closes the
gate's connection to Serve, so the app sees it leave. Refusals are JSON `{"error"}` answers
(`gate_wire`); HTTP is parsed by h11.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
from collections.abc import Iterable

import h11

from links_ray.serve.http import limits
from links_ray.serve.http.gate_wire import (
    HOP_HEADERS,
    BodyBudget,
    Refusal,
    RequestLine,
    head_message,
    head_status,
    header_value,
    refusal_bytes,
)
from links_ray.serve.http.limits import (
    HEAD_TIMEOUT_S,
    MAX_ANSWER_BYTES,
    MAX_ANSWER_BYTES_HELD,
    MAX_BODIES_READING,
    MAX_BODY_BYTES,
    MAX_BODY_BYTES_BUFFERED,
    MAX_CONNECTIONS,
    MAX_HEAD_BYTES,
    MAX_HEADERS,
    MAX_PASSED,
    MAX_URL_BYTES,
    MIN_SEND_BYTES_PER_S,
    PASS_WAIT_S,
    SEND_TIMEOUT_S,
    body_deadline,
)
from links_ray.serve.http.middleware import host_allowed, host_refusal

logger = logging.getLogger("links_ray.serve.http.gate")

#: An idle kept-alive connection is closed after KEEP_ALIVE_S without a byte.
KEEP_ALIVE_S = 5.0
#: Seconds Serve may take to answer a request passed on (syntheses are bounded far below it).
ANSWER_TIMEOUT_S = 600.0
#: Requests that skip the line for Serve: health checks, which must never wait behind work.
HEALTH_TARGETS = frozenset({b"/api/health", b"/-/healthz"})
#: Bytes read from a socket at a time.
READ_BYTES = 64 * 1024


class _Conn:
    """One client connection: its streams, its h11 state, and bytes read ahead of h11."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer = reader, writer
        self.h11 = h11.Connection(h11.SERVER, max_incomplete_event_size=MAX_HEAD_BYTES)
        self.answering = False  # an answer to the current request has begun


class RequestGate:
    """An asyncio HTTP/1.1 server on (`host`, `port`) that reads requests whole, within the
    module's bounds, and passes them to the HTTP server at 127.0.0.1:`upstream_port`; Host
    headers are checked as `guards.host_allowed` does, against `allowed_hosts`."""

    def __init__(
        self,
        host: str,
        port: int,
        upstream_port: int,
        allowed_hosts: Iterable[str] = (),
        *,
        upstream_host: str = "127.0.0.1",
    ) -> None:
        self.host, self.port = host, port
        self.upstream = (upstream_host, upstream_port)
        self.allowed_hosts = frozenset(allowed_hosts)
        self.budget = BodyBudget(MAX_BODIES_READING, MAX_BODY_BYTES_BUFFERED)
        self.server: asyncio.Server | None = None
        self._passing: asyncio.Semaphore | None = None
        self.answer_bytes = 0  # of answers taken from Serve, not yet sent
        self._tasks: set[asyncio.Task] = set()
        self._serving: set[asyncio.Task] = set()  # those whose request is passed on
        self.closing = False

    @property
    def connections(self) -> int:
        """Connections held now."""
        return len(self._tasks)

    async def start(self) -> None:
        """Listen; `port` 0 takes a free one, which `port` then holds."""
        self._passing = asyncio.Semaphore(MAX_PASSED)
        self.server = await asyncio.start_server(
            self._accept, self.host, self.port, limit=READ_BYTES, backlog=1024
        )
        self.port = self.server.sockets[0].getsockname()[1]

    async def close(self, drain_s: float = 0.0) -> None:
        """Stop listening; let the requests passed on finish, for at most `drain_s` seconds
        (their connections then end), and end every other connection at once."""
        self.closing = True
        if self.server is not None:
            self.server.close()
        # Connections accepted just now have tasks that have not yet run (nor registered):
        # a moment on the loop lets them, so that they are ended as the others.
        await asyncio.sleep(0.05)
        for task in self._tasks - self._serving:
            task.cancel()
        if self._serving:
            await asyncio.wait(set(self._serving), timeout=drain_s)
        for task in list(self._tasks):
            task.cancel()
        if self._tasks:
            await asyncio.wait(set(self._tasks), timeout=5.0)
        if self.server is not None:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self.server.wait_closed(), 5.0)

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        self._tasks.add(task)
        try:
            if self.connections > MAX_CONNECTIONS:
                writer.write(refusal_bytes(503, "busy: too many connections at once"))
                with contextlib.suppress(Exception):
                    await asyncio.wait_for(writer.drain(), SEND_TIMEOUT_S)
                return
            await self._serve_connection(_Conn(reader, writer))
        except (ConnectionError, TimeoutError, asyncio.IncompleteReadError, h11.ProtocolError):
            pass  # the client went away, or would not read: nothing is left to answer
        except asyncio.CancelledError:
            pass
        except Exception as exc:  # the gate keeps serving whatever one connection does
            logger.error("links-ray gate: unexpected %s", type(exc).__name__)
        finally:
            self._tasks.discard(task)
            writer.close()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(writer.wait_closed(), 1.0)

    async def _serve_connection(self, conn: _Conn) -> None:
        """Requests of one connection, one after another, until it closes."""
        first = True
        while True:
            try:
                request = await self._read_head(conn, first)
                if request is None:
                    return
                first = False
                body = await self._read_body(conn, request)
            except Refusal as refusal:
                await self._refuse(conn, refusal)
                return
            task = asyncio.current_task()
            assert task is not None
            self._serving.add(task)
            try:
                await self._pass_on(conn, request, body)
            except Refusal as refusal:
                await self._refuse(conn, refusal)
                return
            finally:
                self._serving.discard(task)
                self.budget.give_back(len(body))  # held until the request is answered
            if self.closing:
                return
            conn.answering = False
            if conn.h11.our_state is h11.MUST_CLOSE or conn.h11.their_state is h11.MUST_CLOSE:
                return
            try:
                conn.h11.start_next_cycle()
            except h11.ProtocolError:
                return

    async def _read_head(self, conn: _Conn, first: bool) -> h11.Request | None:
        """The next request's head, or None if the client closed (or idled) between requests."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + HEAD_TIMEOUT_S
        idle_until = None if first else loop.time() + KEEP_ALIVE_S
        line = RequestLine()
        head_bytes = 0
        while True:
            try:
                event = conn.h11.next_event()
            except h11.RemoteProtocolError as exc:
                raise Refusal(head_status(exc), head_message(exc)) from None
            if isinstance(event, h11.Request):
                if len(event.headers) > MAX_HEADERS:
                    raise Refusal(431, f"more than {MAX_HEADERS} headers")
                # h11 bounds a head that arrives in pieces; one that came in a single read
                # is measured here.
                if (
                    sum(len(name) + len(value) + 4 for name, value in event.headers)
                    + len(event.target)
                    > MAX_HEAD_BYTES
                ):
                    raise Refusal(431, f"the request head is over {MAX_HEAD_BYTES} bytes")
                host = header_value(event.headers, b"host")
                if not host_allowed(host, self.allowed_hosts):
                    raise Refusal(400, host_refusal(host))
                return event
            if isinstance(event, h11.ConnectionClosed):
                return None
            if event is not h11.NEED_DATA:
                raise Refusal(400, "malformed request")
            timeout = (idle_until if head_bytes == 0 and idle_until else deadline) - loop.time()
            try:
                async with asyncio.timeout(max(0.0, timeout)):
                    data = await conn.reader.read(READ_BYTES)
            except TimeoutError:
                if head_bytes == 0 and not first:
                    return None  # an idle kept-alive connection: closed without a word
                raise Refusal(
                    408, f"the request's head did not arrive within {HEAD_TIMEOUT_S:g} s"
                ) from None
            if not data and head_bytes == 0:
                return None
            if head_bytes == 0 and not first:
                deadline = loop.time() + HEAD_TIMEOUT_S  # a new request's head starts now
            head_bytes += len(data)
            if line.over(data):
                raise Refusal(414, f"the request line is over {MAX_URL_BYTES} bytes")
            conn.h11.receive_data(data)

    async def _read_body(self, conn: _Conn, request: h11.Request) -> bytes:
        """The request's whole body, within the body bounds; its bytes stay counted in the
        budget until the caller gives them back."""
        declared = header_value(request.headers, b"content-length")
        chunked = header_value(request.headers, b"transfer-encoding") is not None
        if declared is not None and int(declared) > MAX_BODY_BYTES:
            raise Refusal(413, f"the body is over the limit of {MAX_BODY_BYTES} bytes")
        if (declared is not None and int(declared) == 0) or (declared is None and not chunked):
            event = conn.h11.next_event()  # EndOfMessage at once
            if not isinstance(event, h11.EndOfMessage):
                raise Refusal(400, "malformed request")
            return b""
        self.budget.start_body()
        loop = asyncio.get_running_loop()
        start = loop.time()
        pieces: list[bytes] = []
        size = 0
        try:
            if conn.h11.they_are_waiting_for_100_continue:
                await self._send(conn, h11.InformationalResponse(status_code=100, headers=[]))
            while True:
                try:
                    event = conn.h11.next_event()
                except h11.RemoteProtocolError as exc:
                    raise Refusal(400, f"malformed body: {exc}") from None
                if isinstance(event, h11.Data):
                    self.budget.take(len(event.data))
                    size += len(event.data)
                    pieces.append(bytes(event.data))
                    if size > MAX_BODY_BYTES:
                        raise Refusal(413, f"the body is over the limit of {MAX_BODY_BYTES} bytes")
                    continue
                if isinstance(event, h11.EndOfMessage):
                    return b"".join(pieces)
                if isinstance(event, h11.ConnectionClosed):
                    raise ConnectionError("the client closed before sending the whole body")
                now = loop.time()
                wait = body_deadline(start, now, size) - now
                try:
                    async with asyncio.timeout(max(0.0, wait)):
                        data = await conn.reader.read(READ_BYTES)
                except TimeoutError:
                    raise Refusal(
                        408,
                        f"the body came too slowly ({size} bytes in {loop.time() - start:.1f} s): "
                        f"it may pause at most {limits.BODY_TIMEOUT_S:g} s and must keep up "
                        f"{limits.MIN_BODY_BYTES_PER_S} bytes a second",
                    ) from None
                conn.h11.receive_data(data)
        except BaseException:
            self.budget.give_back(size)  # a whole body's bytes stay counted until answered
            raise
        finally:
            self.budget.end_body()

    async def _pass_on(self, conn: _Conn, request: h11.Request, body: bytes) -> None:
        """Pass the request to Serve, in its turn (health skips the line), take Serve's whole
        answer, then deliver it: Serve's place is held only while Serve works, never while a
        slow client reads."""
        assert self._passing is not None
        health = request.target.split(b"?", 1)[0] in HEALTH_TARGETS
        if not health:
            await self._take_turn()
        try:
            head, answer = await self._fetch_watching(conn, request, body)
        finally:
            if not health:
                self._passing.release()
        self.answer_bytes += len(answer)
        try:
            await self._deliver(conn, head, answer)
        finally:
            self.answer_bytes -= len(answer)

    async def _take_turn(self) -> None:
        """Wait, at most PASS_WAIT_S, until fewer than MAX_PASSED requests are passed on and
        fewer than MAX_ANSWER_BYTES_HELD of answers wait for their clients; then count this
        one passed on (the caller releases `_passing`). Else 503."""
        assert self._passing is not None
        acquired = False
        try:
            async with asyncio.timeout(PASS_WAIT_S):
                await self._passing.acquire()
                acquired = True
                while self.answer_bytes >= MAX_ANSWER_BYTES_HELD:
                    await asyncio.sleep(0.05)
        except BaseException as exc:
            if acquired:
                self._passing.release()
            if isinstance(exc, TimeoutError):
                raise Refusal(
                    503, f"busy: {MAX_PASSED} requests under way, the most passed on", retry=True
                ) from None
            raise

    async def _fetch_watching(
        self, conn: _Conn, request: h11.Request, body: bytes
    ) -> tuple[h11.Response, bytes]:
        """`_fetch`'s answer; if the client closes meanwhile, Serve's connection is closed
        (the app sees the client leave) and ConnectionError raised."""
        gone = asyncio.create_task(_closed(conn))
        fetch = asyncio.create_task(self._fetch(request, body))
        try:
            done, _ = await asyncio.wait({gone, fetch}, return_when=asyncio.FIRST_COMPLETED)
            if fetch not in done:
                fetch.cancel()
                with contextlib.suppress(BaseException):
                    await fetch
                raise ConnectionError("the client went away")
            return fetch.result()
        finally:
            gone.cancel()
            with contextlib.suppress(BaseException):
                await gone

    async def _fetch(self, request: h11.Request, body: bytes) -> tuple[h11.Response, bytes]:
        """Serve's whole answer to the request: its head and its body, at most
        MAX_ANSWER_BYTES (else 502)."""
        try:
            reader, writer = await asyncio.wait_for(
                asyncio.open_connection(*self.upstream, limit=READ_BYTES), PASS_WAIT_S
            )
        except (OSError, TimeoutError):
            raise Refusal(503, "the server is starting or restarting", retry=True) from None
        try:
            upstream = h11.Connection(h11.CLIENT, max_incomplete_event_size=MAX_ANSWER_BYTES)
            headers = [
                (name, value) for name, value in request.headers if name.lower() not in HOP_HEADERS
            ]
            headers += [(b"content-length", str(len(body)).encode()), (b"connection", b"close")]
            out = upstream.send(
                h11.Request(method=request.method, target=request.target, headers=headers)
            )
            out += upstream.send(h11.Data(data=body)) if body else b""
            out += upstream.send(h11.EndOfMessage())
            writer.write(out)
            await writer.drain()
            head: h11.Response | None = None
            pieces: list[bytes] = []
            size = 0
            async with asyncio.timeout(ANSWER_TIMEOUT_S):
                while True:
                    event = upstream.next_event()
                    if event is h11.NEED_DATA:
                        upstream.receive_data(await reader.read(READ_BYTES))
                    elif isinstance(event, h11.Response):
                        head = event
                    elif isinstance(event, h11.Data):
                        size += len(event.data)
                        if size > MAX_ANSWER_BYTES:
                            raise Refusal(502, f"the answer is over {MAX_ANSWER_BYTES} bytes")
                        pieces.append(bytes(event.data))
                    elif isinstance(event, h11.EndOfMessage) and head is not None:
                        return head, b"".join(pieces)
                    elif isinstance(event, h11.ConnectionClosed):
                        raise Refusal(503, "the server closed before answering", retry=True)
        except h11.ProtocolError:
            raise Refusal(502, "the server's answer was malformed") from None
        except TimeoutError:
            raise Refusal(504, f"no answer within {ANSWER_TIMEOUT_S:g} s") from None
        finally:
            writer.close()

    async def _deliver(self, conn: _Conn, head: h11.Response, answer: bytes) -> None:
        """Send the answer; a client that does not take it within SEND_TIMEOUT_S plus its
        size at MIN_SEND_BYTES_PER_S loses its connection."""
        headers = [
            (name, value)
            for name, value in head.headers
            if name.lower() not in HOP_HEADERS or name.lower() == b"content-length"
        ]
        conn.answering = True
        data = conn.h11.send(h11.Response(status_code=head.status_code, headers=headers))
        data += conn.h11.send(h11.Data(data=answer)) if answer else b""
        data += conn.h11.send(h11.EndOfMessage())
        conn.writer.write(data)
        await asyncio.wait_for(
            conn.writer.drain(), SEND_TIMEOUT_S + len(data) / MIN_SEND_BYTES_PER_S
        )

    async def _send(self, conn: _Conn, event: h11.Event) -> None:
        data = conn.h11.send(event)
        if data:
            conn.writer.write(data)
            await asyncio.wait_for(conn.writer.drain(), SEND_TIMEOUT_S)

    async def _refuse(self, conn: _Conn, refusal: Refusal) -> None:
        """Answer `refusal` as JSON, unless an answer has begun, and end the connection (the
        rest of the request is never read)."""
        if conn.answering:
            return
        conn.writer.write(refusal_bytes(refusal.status, refusal.message, refusal.retry))
        with contextlib.suppress(Exception):
            await asyncio.wait_for(conn.writer.drain(), SEND_TIMEOUT_S)


async def _closed(conn: _Conn) -> None:
    """Return once the client has closed its end; bytes it sends meanwhile (a next request)
    are kept for h11."""
    while True:
        data = await conn.reader.read(READ_BYTES)
        if not data:
            return
        conn.h11.receive_data(data)
        if len(conn.h11.trailing_data[0]) > MAX_HEAD_BYTES + MAX_BODY_BYTES:
            return  # more read ahead than one request may hold: treated as gone


class GateThread:
    """A `RequestGate` run on an event loop in a thread of its own (what `links serve` does:
    its main thread waits for Ctrl-C)."""

    def __init__(self, gate: RequestGate) -> None:
        self.gate = gate
        self.loop = asyncio.new_event_loop()
        self._started = threading.Event()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="links-gate", daemon=True)

    def start(self) -> None:
        """Start listening; raise what binding raised, if it failed."""
        self._thread.start()
        self._started.wait()
        if self._error is not None:
            raise self._error

    def _run(self) -> None:
        asyncio.set_event_loop(self.loop)
        try:
            self.loop.run_until_complete(self.gate.start())
        except BaseException as exc:
            self._error = exc
            self._started.set()
            return
        self._started.set()
        self.loop.run_forever()

    def stop(self, drain_s: float = 0.0) -> None:
        """Stop listening, let the requests passed on finish for at most `drain_s` seconds,
        end every connection and stop the thread."""
        if not self._thread.is_alive():
            return
        future = asyncio.run_coroutine_threadsafe(self.gate.close(drain_s), self.loop)
        with contextlib.suppress(Exception):
            future.result(timeout=drain_s + 15.0)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(timeout=10.0)
