"""Hard clients over real HTTP: bodies that stall or trickle (408 once the body timeout passes),
clients that send only headers, the worst small drawings and many clients at once, each while
health is answered; and large answers rendered in pieces (the `client` fixture's app)."""

import http.client
import json
import threading
import time
from typing import Any

import numpy as np
import pytest

import links_ray
from links_ray.serve.http import limits as http_limits
from tests.support.serving import FOUR_BAR, POINTS, Client


def test_large_answers_render_in_pieces_as_one_call_would() -> None:
    """`render_json` gives the bytes one `json.dumps` call gives (JsonResponse's), for answers
    of every shape, in pieces of at most about JSON_PIECE_NUMBERS numbers."""
    from links_ray.serve.http.responses import JSON_PIECE_NUMBERS, _dumps, _json_pieces, render_json

    rng = np.random.default_rng(3)
    trajectories = rng.uniform(-1, 1, (100, 1000, 2))
    results = [
        {"path_id": i, "points": rng.random((200, 2)).tolist(), "chamfer": np.float64(i / 7)}
        for i in range(100)
    ]
    for content in (
        {"trajectories": trajectories},
        {"trajectories": trajectories.tolist(), "lock": None},
        {"results": results, "took_ms": 1.25},
        {"x": list(range(10_000)), "y": rng.random(9_001), "e": [], "d": {}},
        [[1, 2]] * 5_000,
        {"status": "ok"},
    ):
        pieces: list[bytes] = []
        _json_pieces(content, pieces)
        assert render_json(content) == b"".join(pieces) == _dumps(content)
        assert max(len(piece) for piece in pieces) < 30 * JSON_PIECE_NUMBERS
    with pytest.raises(ValueError, match="not JSON compliant"):
        render_json({"trajectories": np.full((10, 1000, 2), np.nan)})


def raw_post(port: int, length: int, pieces: list[tuple[float, bytes]]) -> dict[str, Any]:
    """POST /api/retrieve over a plain socket: headers declaring `length` body bytes at once,
    then each (pause in seconds, bytes) of `pieces`, then nothing, the connection held open.
    What came back: `seconds` from the headers to the answer's first byte, the `status`, the
    `headers`, the JSON `body`, and whether the server then `closed` the connection."""
    import socket

    sock = socket.create_connection(("127.0.0.1", port), timeout=120)
    head = (
        f"POST /api/retrieve HTTP/1.1\r\nHost: 127.0.0.1\r\n"
        f"Content-Type: application/json\r\nContent-Length: {length}\r\n\r\n"
    )
    answered = threading.Event()

    def send() -> None:
        for pause, piece in pieces:
            if answered.wait(pause):
                return
            try:
                sock.sendall(piece)
            except OSError:  # the server has closed: it answered
                return

    start = time.monotonic()
    sock.sendall(head.encode())
    sender = threading.Thread(target=send, daemon=True)
    sender.start()
    received = b""
    seconds = None
    try:
        while True:
            chunk = sock.recv(65536)
            if seconds is None:
                seconds = time.monotonic() - start
                answered.set()
            if not chunk:
                closed = True
                break
            received += chunk
            header, _, rest = received.partition(b"\r\n\r\n")
            declared = [
                int(line.split(b":", 1)[1])
                for line in header.split(b"\r\n")
                if line.lower().startswith(b"content-length:")
            ]
            if declared and len(rest) >= declared[0] and b"connection: close" not in header:
                closed = False  # a whole answer on a connection kept alive
                break
    except TimeoutError:
        closed = False
    finally:
        answered.set()
        sock.close()
    header, _, rest = received.partition(b"\r\n\r\n")
    lines = header.decode().split("\r\n")
    headers = dict(line.lower().split(": ", 1) for line in lines[1:] if ": " in line)
    return {
        "seconds": seconds,
        "status": int(lines[0].split()[1]) if lines[0] else None,
        "headers": headers,
        "body": json.loads(rest) if rest else None,
        "closed": closed,
    }


def test_a_body_that_stalls_or_trickles_is_cut_off_with_408(client: Client) -> None:
    """A body that stops coming, or trickles in a byte at a time, is answered 408 with a JSON
    error once BODY_TIMEOUT_S have passed (not before), and the connection is closed; a body
    sent in pieces with pauses shorter than that, at more than MIN_BODY_BYTES_PER_S, is
    answered as usual though it takes longer than BODY_TIMEOUT_S in all."""
    timeout, rate = http_limits.BODY_TIMEOUT_S, http_limits.MIN_BODY_BYTES_PER_S
    stall = ([(0.0, b'{"points": [[0, 0], ')], 1000)
    trickle = ([(0.0 if i == 0 else 0.25, b" ") for i in range(400)], 100_000)
    # Four pieces of 2 x rate bytes, 0.4 x timeout apart (12 s in all): each pause well within
    # the timeout, and each piece buys 2 s at the rate, so the last comes 4 s before the rate
    # would cut the body off.
    whole = json.dumps({"points": POINTS, "k": 2}).encode()
    piece = 2 * rate
    body = whole.ljust(4 * piece)
    pieces = [(0.4 * timeout if i else 0.0, body[i * piece : (i + 1) * piece]) for i in range(4)]
    paced = (pieces, len(body))
    found: dict[str, dict[str, Any]] = {}

    def run(name: str, case: tuple[list[tuple[float, bytes]], int]) -> None:
        found[name] = raw_post(client.port, case[1], case[0])

    threads = [
        threading.Thread(target=run, args=(name, case))
        for name, case in (("stall", stall), ("trickle", trickle), ("paced", paced))
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    for name in ("stall", "trickle"):
        answer = found[name]
        assert answer["status"] == 408, (name, answer)
        assert answer["headers"]["content-type"].startswith("application/json")
        assert set(answer["body"]) == {"error"}, answer
        assert answer["body"]["error"].startswith("the body came too slowly"), answer
        assert f"pause at most {timeout:g} s" in answer["body"]["error"]
        assert answer["closed"], (name, answer)
        # Not before the timeout; the upper bound is loose, for a busy machine.
        assert timeout - 0.5 <= answer["seconds"] < timeout + 20, (name, answer)
    answer = found["paced"]
    assert answer["status"] == 200 and len(answer["body"]["results"]) == 2, answer
    assert answer["seconds"] > timeout, answer
    assert client.get("/api/health")[0] == 200


def test_the_worst_small_drawings_are_answered_and_health_stays_up(client: Client) -> None:
    """The drawings that once froze a replica for minutes or filled its memory (`links bench
    hostile` sends the same) are each answered: read, or refused 413 naming the limit they
    pass; health is answered between them, and the replica's readers are ready for more."""
    from links_ray.bench.hostile_inputs import hostile_drawings

    expected = {
        "style 40,000 chars": 200,
        "style 300,000 chars": 200,
        "uses 5 levels": 413,
        "uses 6 levels": 413,
        "bulges 1,000 vertices": 200,
        "spline 1,000 fit points": 200,
    }
    drawings = hostile_drawings()
    assert set(drawings) == set(expected)
    for what, (name, text) in drawings.items():
        status, data = client.post("/api/curve", {"name": name, "text": text})
        assert status == expected[what], (what, status, data)
        if status == 413:
            assert "MAX_SVG_ELEMENTS" in data["error"] or "10,000" in data["error"], data
        else:
            assert len(data["points"]) == 400 and np.isfinite(data["points"]).all()
        assert client.get("/api/health")[0] == 200
    status, data = client.post("/api/curve", {"name": "a.csv", "text": "0,0\n1,1\n2,0\n"})
    assert status == 200 and len(data["points"]) == 400


def test_clients_that_send_only_headers_hold_no_place(client: Client, curated: Any) -> None:
    """Ten clients that send a retrieval's headers and never its body each get 408 once
    BODY_TIMEOUT_S have passed, and meanwhile an eleventh, real retrieval is answered 200:
    a place among a replica's MAX_RETRIEVALS is claimed only once a body has been read."""
    from links_ray.serve.http.limits import MAX_RETRIEVALS

    timeout = http_limits.BODY_TIMEOUT_S
    silent = MAX_RETRIEVALS + 2
    found: list[dict[str, Any]] = []
    lock = threading.Lock()

    def headers_only() -> None:
        answer = raw_post(client.port, 100, [])
        with lock:
            found.append(answer)

    threads = [threading.Thread(target=headers_only) for _ in range(silent)]
    for thread in threads:
        thread.start()
    time.sleep(1.0)  # every one of them has sent its headers and waits
    status, data = client.post("/api/retrieve", {"points": curated.points.iloc[0].tolist()})
    assert status == 200 and len(data["results"]) == 3, (status, data)
    for thread in threads:
        thread.join()
    assert len(found) == silent
    for answer in found:
        assert answer["status"] == 408, answer
        assert answer["body"]["error"].startswith("the body came too slowly (0 bytes"), answer
        assert answer["closed"], answer
        assert timeout - 0.5 <= answer["seconds"] < timeout + 20, answer


def test_concurrent_clients(client: Client, curated: Any) -> None:
    """8 threads x 25 requests (retrieve, simulate, health), each thread on a kept-alive
    connection: every answer is 200 and correct, and every thread finishes (a hang fails the
    join's bound of 120 s, far above the seconds this takes on a busy machine)."""
    queries = [curated.points.iloc[i % len(curated)].astype(float).tolist() for i in range(8)]
    expected_sim = links_ray.simulate(**FOUR_BAR).tolist()
    failures: list[str] = []
    latencies: list[float] = []
    lock = threading.Lock()

    def worker(t: int) -> None:
        conn = http.client.HTTPConnection("127.0.0.1", client.port, timeout=60)
        try:
            for i in range(25):
                kind = ("retrieve", "simulate", "health")[(t + i) % 3]
                start = time.perf_counter()
                if kind == "retrieve":
                    status, _, data = client.request(
                        "POST", "/api/retrieve", {"points": queries[t], "k": 3}, connection=conn
                    )
                    ok = status == 200 and data["results"][0]["chamfer"] < 1e-6
                elif kind == "simulate":
                    status, _, data = client.request(
                        "POST", "/api/simulate", FOUR_BAR, connection=conn
                    )
                    ok = status == 200 and data["trajectories"] == expected_sim
                else:
                    status, _, data = client.request("GET", "/api/health", connection=conn)
                    ok = status == 200 and data["paths"] == len(curated)
                with lock:
                    latencies.append(time.perf_counter() - start)
                    if not ok:
                        failures.append(f"thread {t} request {i} {kind}: {status}")
        except Exception as exc:  # a dropped connection is a failure too
            with lock:
                failures.append(f"thread {t}: {type(exc).__name__}: {exc}")
        finally:
            conn.close()

    start = time.perf_counter()
    threads = [threading.Thread(target=worker, args=(t,)) for t in range(8)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=120)
    elapsed = time.perf_counter() - start
    assert not any(thread.is_alive() for thread in threads)
    assert not failures, failures[:5]
    assert len(latencies) == 200
    print(
        f"\n200 requests from 8 threads in {elapsed:.2f} s "
        f"(p50 {np.median(latencies) * 1e3:.0f} ms, max {max(latencies) * 1e3:.0f} ms)"
    )
