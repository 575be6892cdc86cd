"""Every refusal limit of the HTTP layer, in one place: what one request may hold (its size,
its head, its body's pace), what a gateway replica holds at once (retrievals, syntheses,
drawings, kits), what the request gate holds at once, Serve's own bounds on the deployments,
and what `GET /api/limits` tells clients. The engine's own limits (points, k, steps, synthesis
time) are the engine's; the ones here bound what requests may hold a server for.
"""

from __future__ import annotations

from links_ray.engine.inputs import (
    DEFAULT_K,
    DEFAULT_STEPS,
    MAX_COORDINATE,
    MAX_K,
    MAX_POINTS,
    MAX_STEPS,
    MAX_TRANSMISSION_DEG,
    MIN_JOINTS,
    MIN_K,
    MIN_POINTS,
    MIN_STEPS,
)
from links_ray.engine.synthesis.options import (
    DEFAULT_SYNTHESIS_SECONDS,
    DEFAULT_SYNTHESIS_TRANSMISSION_DEG,
    MAX_SYNTHESIS_ITERATIONS,
    MAX_SYNTHESIS_SECONDS,
    MAX_SYNTHESIS_WORK,
)
from links_ray.interop.curve_limits import CURVE_READERS

# -- one request -----------------------------------------------------------------------------------

#: Longest file name or element id (SVG id, DXF layer) a curve file is named by over HTTP.
MAX_CURVE_NAME_CHARS = 1000

#: Largest mechanism one request may carry, in joints. Smaller than MAX_JOINTS: a request holds
#: a replica's CPU while it runs, and the studio draws nothing larger.
MAX_REQUEST_JOINTS = 100
#: Largest mechanism `POST /api/kit` builds, in joints: a kit's check of its links' pairs over
#: the turn and its layer plan grow faster than the square of the joints, and the replica's
#: one kit thread is held meanwhile. Every mechanism the dataset holds and synthesis grows is
#: within it (20 joints at most), and the slowest of them plans within seconds of a core
#: (docs/benchmarks.md, Kits); past it the time grows steeply.
MAX_KIT_JOINTS = 20
#: Largest simulation one request may ask for: joints x steps (the answer holds twice as many
#: numbers, about 4 MB of JSON at the limit).
MAX_REQUEST_JOINT_STEPS = 100_000
#: Largest request body, in bytes (MAX_POINTS points take about 0.5 MB).
MAX_BODY_BYTES = 2 * 1024 * 1024
#: A request body must keep coming: a pause of BODY_TIMEOUT_S seconds with nothing of it, or
#: a body that falls behind MIN_BODY_BYTES_PER_S (after t seconds it must have sent
#: (t - BODY_TIMEOUT_S) x MIN_BODY_BYTES_PER_S bytes), is cut off with 408. A slow client
#: then holds a connection for at most BODY_TIMEOUT_S + MAX_BODY_BYTES / MIN_BODY_BYTES_PER_S
#: (138 s), however it sends.
BODY_TIMEOUT_S = 10.0
MIN_BODY_BYTES_PER_S = 16 * 1024
#: A request's head: its request line (method, target, version) at most MAX_URL_BYTES (else
#: 414), the whole head at most MAX_HEAD_BYTES and MAX_HEADERS headers (else 431), all of it
#: within HEAD_TIMEOUT_S of its first byte, or of the connection's opening (else 408).
MAX_URL_BYTES = 8 * 1024
MAX_HEAD_BYTES = 32 * 1024
MAX_HEADERS = 100
HEAD_TIMEOUT_S = 10.0


# -- admission: costly work a gateway replica holds at once ----------------------------------------

#: Retrievals one gateway replica holds at once, running or waiting for the index (its own
#: or the partitions'). One more is answered at once with 503, `Retry-After` and a JSON
#: `error`.
MAX_RETRIEVALS = 8
#: Syntheses one gateway replica holds at once, running or waiting. Each holds the replica's
#: cores for its whole budget (up to MAX_SYNTHESIS_SECONDS), so few; one more is answered 503.
#: One that would wait for the refinement thread longer than its own budget is answered 503
#: too: waiting does not shorten its refinement, whose budget starts when it starts.
MAX_SYNTHESES = 2
#: Seconds a refused client is asked to wait (`Retry-After`).
RETRY_AFTER_S = 1
#: Drawings one gateway replica holds at once, being read (CURVE_READERS at a time) or waiting
#: for a reader; one more is answered at once with 503.
MAX_CURVE_READS = 4 * CURVE_READERS


# -- kits ------------------------------------------------------------------------------------------

#: Kits one replica holds at once, made or waiting for its one kit thread.
MAX_KITS = 2


# -- bodies as JSON --------------------------------------------------------------------------------

#: The most brackets (`[` and `{`) a body may hold, but a drawing's (`bodies.TEXT_ROUTES`):
#: each array and object opens with one, and no body that keeps the limits holds more than its
#: points' MAX_POINTS pairs, or a mechanism's rows and positions, and a few lists and objects
#: besides. Counting them takes a millisecond on a 2 MB body; parsing one of that many arrays
#: holds the GIL (orjson's, in any thread) about a hundred times as long.
MAX_BODY_CONTAINERS = max(MAX_POINTS, 2 * MAX_REQUEST_JOINTS) + 16
#: How deep orjson reads nested arrays and objects.
MAX_JSON_DEPTH = 1024


# -- the request gate: connections, bodies and answers at once -------------------------------------

#: Connections the gate holds at once; one more is answered 503 and closed.
MAX_CONNECTIONS = 1024
#: Bodies being read at once, and their bytes held at once: one more is refused 503.
MAX_BODIES_READING = 512
MAX_BODY_BYTES_BUFFERED = 128 * 1024 * 1024
#: Requests passed to Serve at once; more wait, up to PASS_WAIT_S, then 503. Below Serve's
#: places for the gateway (`deployments.GATEWAY_MAX_ONGOING`), so that health, which does not
#: wait in this line, always finds one.
MAX_PASSED = 16
PASS_WAIT_S = 10.0
#: The gate takes Serve's whole answer before sending it, so that a client that does not
#: read holds the gate's memory, not a place in Serve: at most MAX_ANSWER_BYTES an answer
#: (else 502), and no request is passed on while MAX_ANSWER_BYTES_HELD of answers wait for
#: their clients. A client must take its answer within SEND_TIMEOUT_S, plus its size at
#: MIN_SEND_BYTES_PER_S, or its connection ends.
MAX_ANSWER_BYTES = 64 * 1024 * 1024
MAX_ANSWER_BYTES_HELD = 128 * 1024 * 1024
SEND_TIMEOUT_S = 10.0
MIN_SEND_BYTES_PER_S = 64 * 1024


# -- Serve's own bounds on the deployments ---------------------------------------------------------

#: Serve's own bounds on a gateway replica: requests it runs at once, and requests waiting
#: for one of those slots. Beyond them Serve answers 503 with `Retry-After` itself (its body is
#: Serve's plain text, not JSON). Far above MAX_RETRIEVALS, so that health checks and
#: simulations never wait behind retrievals.
GATEWAY_MAX_ONGOING, GATEWAY_MAX_QUEUED = 100, 100
#: Retrievals a partition replica takes at once (it runs them one after another); further
#: ones wait in the callers' routers, which send them to the partition's least busy replica.
PARTITION_MAX_ONGOING = 4
#: How long the gateway waits for all the partitions' answers before answering 503.
PARTITION_TIMEOUT_S = 30.0


def body_deadline(start: float, now: float, received: int) -> float:
    """When a body begun at `start` that has `received` bytes by `now` is cut off with 408
    if nothing more arrives: BODY_TIMEOUT_S after its last bytes, and no later than its pace
    of MIN_BODY_BYTES_PER_S allows (all times in one clock's seconds)."""
    return min(now + BODY_TIMEOUT_S, start + BODY_TIMEOUT_S + received / MIN_BODY_BYTES_PER_S)


def request_limits() -> dict[str, float | int]:
    """The limits an HTTP request meets, by name, as `GET /api/limits` gives them to clients
    (the studio reads its own from there)."""
    return {
        "min_points": MIN_POINTS,
        "max_points": MAX_POINTS,
        "min_k": MIN_K,
        "max_k": MAX_K,
        "default_k": DEFAULT_K,
        "min_joints": MIN_JOINTS,
        "max_joints": MAX_REQUEST_JOINTS,
        "min_steps": MIN_STEPS,
        "max_steps": MAX_STEPS,
        "default_steps": DEFAULT_STEPS,
        "max_joint_steps": MAX_REQUEST_JOINT_STEPS,
        "max_seconds": MAX_SYNTHESIS_SECONDS,
        "max_iterations": MAX_SYNTHESIS_ITERATIONS,
        "max_synthesis_work": MAX_SYNTHESIS_WORK,
        "max_kit_joints": MAX_KIT_JOINTS,
        "default_seconds": DEFAULT_SYNTHESIS_SECONDS,
        "max_transmission_deg": MAX_TRANSMISSION_DEG,
        "default_transmission_deg": DEFAULT_SYNTHESIS_TRANSMISSION_DEG,
        "max_coordinate": MAX_COORDINATE,
        "max_body_bytes": MAX_BODY_BYTES,
        "body_timeout_s": BODY_TIMEOUT_S,
        "min_body_bytes_per_s": MIN_BODY_BYTES_PER_S,
        "max_url_bytes": MAX_URL_BYTES,
        "max_head_bytes": MAX_HEAD_BYTES,
        "max_headers": MAX_HEADERS,
        "head_timeout_s": HEAD_TIMEOUT_S,
    }
