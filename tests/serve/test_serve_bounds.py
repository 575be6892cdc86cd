"""Bounds a request meets before its work: list lengths counted before any entry is read, large
bodies parsed and converted off the event loop, and drawings read with tokens of their own.

No Ray: the request bodies go through `serve.http.bodies` as the routes read them (real starlette
requests over an ASGI receive channel), and drawings through `serve.http.admission.CurveReads` and
real reader processes.
"""

from __future__ import annotations

import asyncio
import os
import threading
from typing import Any

import anyio
import anyio.to_thread
import numpy as np
import orjson
import pytest
from starlette.concurrency import run_in_threadpool
from starlette.requests import Request

from links_ray.engine.inputs import MAX_POINTS
from links_ray.engine.kinematics.solver import simulate
from links_ray.interop.curve_files import read_curve_text
from links_ray.interop.curve_limits import CURVE_READER_NICENESS, CURVE_READERS, MAX_SVG_ELEMENTS
from links_ray.interop.curve_worker import read_curve_isolated, warm_curve_readers
from links_ray.serve.http.admission import RETRIEVAL_NICENESS, Admission, CurveReads
from links_ray.serve.http.bodies import read_args, retrieve_args, simulate_args, synthesize_request
from links_ray.serve.http.limits import MAX_BODY_CONTAINERS, MAX_CURVE_READS
from links_ray.serve.http.responses import INLINE_JSON_BYTES, ApiError
from tests.support.fourbars import stretched_four_bar

#: A drawn curve within every limit.
CIRCLE = [[float(np.cos(t)), float(np.sin(t))] for t in np.linspace(0, 6.2, 100)]
#: A drawing of half the elements a drawing may hold: about half a second of a reader's work.
HEAVY = (
    '<svg xmlns="http://www.w3.org/2000/svg">'
    + '<path d="M0 0 L1 1 L2 0"/>' * (MAX_SVG_ELEMENTS // 2)
    + "</svg>"
)


def request_of(body: bytes, route: str) -> Request:
    """A POST of `body` to `route` as JSON, received in 64 KiB pieces as a server receives it."""
    scope = {
        "type": "http",
        "method": "POST",
        "path": route,
        "query_string": b"",
        "headers": [
            (b"content-type", b"application/json"),
            (b"content-length", str(len(body)).encode()),
        ],
    }
    pieces = [body[i : i + 65536] for i in range(0, len(body), 65536)] or [b""]

    async def receive() -> dict[str, Any]:
        piece = pieces.pop(0)
        return {"type": "http.request", "body": piece, "more_body": bool(pieces)}

    return Request(scope, receive)


def refusal(body: dict[str, Any], route: str, convert: Any) -> ApiError:
    """The ApiError reading `body` for `route` raises."""
    with pytest.raises(ApiError) as caught:
        asyncio.run(read_args(request_of(orjson.dumps(body), route), route, convert))
    return caught.value


def test_200000_points_are_refused_by_their_brackets_before_any_parse() -> None:
    """200,000 [x, y] pairs (2.2 MB would be over the body limit; 1.4 MB of small integers is
    not) are refused 400 naming the point limit, from the brackets counted, never parsed."""
    body = {"points": [[i % 7, i % 5] for i in range(200_000)]}
    assert len(orjson.dumps(body)) < 2 * 1024 * 1024
    refused = refusal(body, "/api/retrieve", retrieve_args)
    assert refused.status == 400
    assert refused.message == (
        f"the body holds 200002 brackets, more arrays and objects than any /api/retrieve body "
        f"within the limits (at most {MAX_POINTS} points, 100 joints)"
    )


def test_points_are_counted_before_any_pair_is_read() -> None:
    """200,000 entries that are no pairs at all (strings: two brackets in the whole body) are
    refused for their count: had any pair been read first, the message would name it."""
    body = {"points": ["x"] * 200_000}
    refused = refusal(body, "/api/retrieve", retrieve_args)
    assert (refused.status, refused.message) == (
        400,
        "points must hold 3 to 10000 pairs, got 200000",
    )
    refused = refusal(body, "/api/synthesize", synthesize_request)
    assert refused.message == "points must hold 3 to 10000 pairs, got 200000"


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (
            {"timing": ["x"] * 200_000},
            "timing must give one angle per point, at most 10000, got 200000",
        ),
        ({"timing": ["no angle"] * 101}, "timing must give one angle per point: 100, got 101"),
    ],
    ids=["timing-over-any-count", "timing-not-one-a-point"],
)
def test_other_lists_are_counted_before_their_entries(extra: dict, message: str) -> None:
    """Entries that could not be read as numbers, in lists of the wrong length: refused for
    the length, so no entry was read before it."""
    refused = refusal({"points": CIRCLE, **extra}, "/api/synthesize", synthesize_request)
    assert (refused.status, refused.message) == (400, message)


def test_mechanism_lists_are_counted_before_their_entries() -> None:
    four_bar = stretched_four_bar(0, 16, 0.5)
    body = {
        "adjacency": np.asarray(four_bar["adjacency"]).tolist(),
        "node_types": np.asarray(four_bar["node_types"]).tolist(),
        "positions": ["x"] * 200_000,
    }
    refused = refusal(body, "/api/simulate", simulate_args)
    n = len(body["node_types"])
    assert refused.message == f"positions must hold {n} [x, y] pairs (one per joint), got 200000"


def test_bodies_at_the_limits_are_taken_and_large_ones_converted_off_the_event_loop() -> None:
    """The bracket count refuses no body within the limits: MAX_POINTS pairs with a timing
    list and both boxes read as they are. A body larger than INLINE_JSON_BYTES is parsed and
    converted in the JSON thread; a small one on the loop."""
    rng = np.random.default_rng(3)
    points = rng.random((MAX_POINTS, 2)).tolist()
    body = {
        "points": points,
        "timing": np.linspace(0.0, 359.0, MAX_POINTS).tolist(),
        "constraints": {"pivots": [-1, -1, 2, 2], "footprint": [-5, -5, 5, 5]},
    }
    raw = orjson.dumps(body)
    assert raw.count(b"[") + raw.count(b"{") == MAX_POINTS + 6 <= MAX_BODY_CONTAINERS
    assert len(raw) > INLINE_JSON_BYTES
    threads: list[str] = []

    def convert(parsed: dict[str, Any]) -> Any:
        threads.append(threading.current_thread().name)
        return synthesize_request(parsed)

    async def read(raw: bytes) -> Any:
        return await read_args(request_of(raw, "/api/synthesize"), "/api/synthesize", convert)

    drawn, options, stream = asyncio.run(read(raw))
    np.testing.assert_array_equal(drawn, np.asarray(points))
    assert len(options.timing) == MAX_POINTS and options.constraints.pivots == (-1, -1, 2, 2)
    assert stream is False
    small = orjson.dumps({"points": CIRCLE})
    asyncio.run(read(small))
    assert threads[0].startswith("links-json") and threads[1] == threading.main_thread().name


# -- drawings: their own tokens, below the replica's threads ----------------------------------


def niceness(pid: int) -> int:
    return os.getpriority(os.PRIO_PROCESS, pid)


def test_drawings_wait_on_tokens_of_their_own_and_run_below_the_replica() -> None:
    """MAX_CURVE_READS drawings at once: CURVE_READERS are read, the rest wait, and none holds
    a token of the thread pool simulations use (a simulation is answered meanwhile, as the
    readers are still busy); one more is refused 503 at once, with Retry-After. The reader
    processes run at CURVE_READER_NICENESS, below the replica's threads and its retrievals'."""
    reads = Admission().curves
    expected = read_curve_text("heavy.svg", HEAVY).points
    four_bar = stretched_four_bar(0, 16, 0.5)
    simulate(**four_bar, steps=16)  # compiled before the readers are busy
    warm_curve_readers()  # as a replica does when it starts

    async def burst() -> tuple[list[Any], int, ApiError, list[int]]:
        limiter = anyio.to_thread.current_default_thread_limiter()
        tasks = [
            asyncio.create_task(reads.read("heavy.svg", HEAVY, None))
            for _ in range(MAX_CURVE_READS)
        ]
        while reads.reading < CURVE_READERS:
            await asyncio.sleep(0.005)
        assert reads.held == MAX_CURVE_READS
        with pytest.raises(ApiError) as turned_away:
            await reads.read("heavy.svg", HEAVY, None)
        borrowed = limiter.borrowed_tokens
        trajectories = await run_in_threadpool(simulate, **four_bar, steps=16)
        assert np.asarray(trajectories).shape[1] == 16
        assert reads.reading == CURVE_READERS  # the simulation came back while they read
        busy_readers = read_curve_pids()
        results = await asyncio.gather(*tasks, return_exceptions=True)
        return results, borrowed, turned_away.value, busy_readers

    results, borrowed, turned_away, pids = asyncio.run(burst())
    assert borrowed == 0
    assert turned_away.status == 503 and turned_away.headers == {"Retry-After": "1"}
    assert turned_away.message.startswith(f"busy: {MAX_CURVE_READS} drawings being read")
    done = [result for result in results if not isinstance(result, BaseException)]
    assert len(done) >= CURVE_READERS  # the rest read, or waited their time and were told 503
    for curve in done:
        np.testing.assert_array_equal(curve.points, expected)
    for result in results:
        if isinstance(result, BaseException):
            assert isinstance(result, ApiError) and result.status == 503
    assert reads.held == 0 and reads.reading == 0
    assert pids and all(niceness(pid) >= CURVE_READER_NICENESS for pid in pids)
    assert CURVE_READER_NICENESS > RETRIEVAL_NICENESS > niceness(0)


def read_curve_pids() -> list[int]:
    """The process's own reader processes (`read_curve_isolated`'s)."""
    from links_ray.interop import curve_worker

    shared = curve_worker._shared_readers
    assert shared is not None
    return shared[1].pids()


def test_a_drawing_that_finds_no_token_in_time_is_told_busy() -> None:
    reads = CurveReads(readers=1, most=4, wait_s=0.05)

    async def two() -> ApiError:
        first = asyncio.create_task(reads.read("heavy.svg", HEAVY, None))
        while not reads.reading:
            await asyncio.sleep(0.005)
        with pytest.raises(ApiError) as caught:
            await reads.read("tiny.csv", "0,0\n1,1\n2,0\n", None)
        await first
        return caught.value

    refused = asyncio.run(two())
    assert (refused.status, refused.headers) == (503, {"Retry-After": "1"})
    assert refused.message == "busy: no curve reader came free within 0.05 s (all 1 busy)"
    assert read_curve_isolated("tiny.csv", "0,0\n1,1\n2,0\n").points.shape == (400, 2)


def _points_body(inner: bytes) -> bytes:
    return b'{"points":' + inner + b"}"


#: The worst small bodies found for the body readers, each as large as the limits let it be
#: (or as small as it can be), and what its refusal says. Measured with their time in
#: docs/benchmarks.md (Hostile input): at most about 0.1 s and 34 MiB a 2 MB body.
_FULL = 2 * 1024 * 1024 - 64
WORST_BODIES = {
    "open brackets": (b"[" * _FULL, "brackets"),
    "arrays of numbers under the bracket count": (
        _points_body(b"[" + b",".join([b"[" + b",".join([b"1"] * 90) + b"]"] * 2000) + b"]"),
        "got 90 entries",
    ),
    "an integer of 2 million digits": (_points_body(b"1" * (_FULL - 12)), "infinity"),
    "a float of 2 million digits": (_points_body(b"0." + b"1" * (_FULL - 14)), "got a number"),
    "an exponent past float64": (_points_body(b"[[1e999999,1],[2,2],[3,1]]"), "infinity"),
    "a string of escapes": (
        _points_body(b'"' + b"\\u0000" * ((_FULL - 14) // 6) + b'"'),
        "got a string",
    ),
    "a key repeated 190,000 times": (
        b"{" + b",".join([b'"points":1'] * 190_000) + b"}",
        "got a number",
    ),
    "150,000 distinct keys": (
        b"{" + b",".join([b'"k%d":1' % i for i in range(150_000)]) + b"}",
        "unknown field 'k0'",
    ),
    "pairs as strings": (
        _points_body(b"[" + b",".join([b'["1","2"]'] * 10_000) + b"]"),
        "two numbers",
    ),
    "nesting past the parser's depth": (
        _points_body(b"[" * 1025 + b"]" * 1025),
        "nested too deeply",
    ),
    "coordinates past the limit": (
        _points_body(b"[[1e308,1e308],[-1e308,-1e308],[0,1]]"),
        "within",
    ),
}


@pytest.mark.parametrize("route", ["/api/retrieve", "/api/synthesize"])
@pytest.mark.parametrize("name", list(WORST_BODIES))
def test_the_worst_small_bodies_are_refused_within_a_bounded_memory(name: str, route: str) -> None:
    """Each is refused 400 naming its problem, and reading it never holds more than 32 times
    its bytes and a MiB (traced): no body amplifies in the parser or the checks after it."""
    import tracemalloc

    body, said = WORST_BODIES[name]
    convert = retrieve_args if route == "/api/retrieve" else synthesize_request
    tracemalloc.start()
    try:
        with pytest.raises(ApiError) as caught:
            asyncio.run(read_args(request_of(body, route), route, convert))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert caught.value.status == 400 and said in caught.value.message, caught.value.message
    assert peak <= 32 * len(body) + 2**20, (peak, len(body))
