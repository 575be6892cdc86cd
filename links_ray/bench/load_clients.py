"""HTTP clients that load a running server, for `links bench serve` and the tests of serving
under load: retrieval (or any POST) clients in a process of their own, a probing client that
checks health and simulates meanwhile, the largest body a simulation may have, and a wait for
a port to come free.

The clients speak plain HTTP/1.1 to 127.0.0.1, and their process imports no Ray.
"""

from __future__ import annotations

import http.client
import json
import os
import subprocess
import sys
import threading
import time
from decimal import Decimal

import numpy as np

from links_ray.serve.http.limits import MAX_BODY_BYTES, MAX_REQUEST_JOINT_STEPS, MAX_REQUEST_JOINTS

#: Seconds a load client waits after a 503 that names no `Retry-After` (it waits as long as
#: one asks, as a well-behaved client does).
LOAD_PAUSE_S = 1.0
#: Seconds the probing client waits between its health checks and simulations.
PROBE_PAUSE_S = 0.02
#: The mechanism the probing client simulates.
PROBE_FOUR_BAR = {
    "adjacency": [[0, 1, 0, 0], [1, 0, 0, 1], [0, 0, 0, 1], [0, 1, 1, 0]],
    "node_types": [0, 2, 0, 1],
    "positions": [[0.5, 0.5], [0.55, 0.5], [0.8, 0.5], [0.6, 0.7]],
}


def retrieval_load(
    port: int, queries: list[np.ndarray], seconds: float, clients: int = 32, k: int = 3
) -> subprocess.Popen:
    """Start `clients` clients that post retrievals of `queries` (in rotation, `k` results each) to
    http://127.0.0.1:port/api/retrieve for `seconds`, each on a kept-alive connection.

    They run in a process of their own, so that their threads do not slow the caller's own
    requests; this returns the process once they have started (RuntimeError if they could
    not). After a 503 a client waits what its `Retry-After` asks (or `LOAD_PAUSE_S`), and so
    keeps its place in the load: the server stays full as long as more clients want in than
    it holds. `finish_load` gives what they saw.
    """
    bodies = [json.dumps({"points": np.asarray(q).tolist(), "k": k}) for q in queries]
    return post_load(port, "/api/retrieve", bodies, seconds, clients)


def post_load(
    port: int, route: str, bodies: list[str], seconds: float, clients: int, niceness: int = 0
) -> subprocess.Popen:
    """`retrieval_load`'s clients, posting `bodies` (in rotation: client i starts with body i) to
    any `route`, their process `niceness` lower in priority than this one."""
    spec = {
        "niceness": niceness,
        "port": port,
        "route": route,
        "bodies": bodies,
        "seconds": seconds,
        "clients": clients,
        "pause_s": LOAD_PAUSE_S,
    }
    process = subprocess.Popen(
        [sys.executable, "-c", "from links_ray.bench.load_clients import _load; _load()"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert process.stdin is not None and process.stdout is not None
    process.stdin.write(json.dumps(spec))
    process.stdin.close()
    process.stdin = None  # all sent: `communicate` must not flush it
    ready = process.stdout.readline()
    if ready.strip() != "ready":
        process.kill()
        process.wait()
        raise RuntimeError(f"the load clients did not start: {ready!r}")
    return process


def finish_load(process: subprocess.Popen, timeout: float = 120.0) -> dict:
    """What the clients of `retrieval_load` saw: `statuses` (count by HTTP status, or by
    exception name for a request that got no answer), `latencies` (seconds, of the 200s),
    `seconds` (how long they ran), and the 503s that lacked a `Retry-After` header
    (`no_retry_after`) or a JSON `error` (`not_json`). Waits up to `timeout` seconds for
    them to end; RuntimeError if their process failed."""
    out, _ = process.communicate(timeout=timeout)
    if process.returncode != 0:
        raise RuntimeError(f"the load clients failed with exit status {process.returncode}")
    return json.loads(out)


def _load() -> None:
    """The load clients' process (`retrieval_load`): the spec on stdin, the record on
    stdout."""
    spec = json.loads(sys.stdin.read())
    os.nice(spec.get("niceness", 0))  # before the clients' threads, which inherit it
    bodies = [body.encode() for body in spec["bodies"]]
    clients, pause_s = spec["clients"], spec["pause_s"]
    lock = threading.Lock()
    statuses: dict[str, int] = {}
    latencies: list[float] = []
    faults = {"no_retry_after": 0, "not_json": 0}

    def client(number: int, stop: float) -> None:
        conn = None
        next_body = number
        while time.monotonic() < stop:
            body = bodies[next_body % len(bodies)]
            next_body += clients
            if conn is None:
                conn = http.client.HTTPConnection("127.0.0.1", spec["port"], timeout=60)
            start = time.perf_counter()
            try:
                conn.request("POST", spec["route"], body, {"Content-Type": "application/json"})
                response = conn.getresponse()
                raw = response.read()
            except (OSError, http.client.HTTPException) as exc:
                conn.close()
                conn = None
                with lock:
                    statuses[type(exc).__name__] = statuses.get(type(exc).__name__, 0) + 1
                continue
            elapsed = time.perf_counter() - start
            with lock:
                statuses[str(response.status)] = statuses.get(str(response.status), 0) + 1
                if response.status == 200:
                    latencies.append(elapsed)
                elif response.status == 503:
                    faults["no_retry_after"] += response.getheader("Retry-After") is None
                    faults["not_json"] += not _json_error(raw)
            if response.status == 503:
                time.sleep(_seconds(response.getheader("Retry-After"), pause_s))
        if conn is not None:
            conn.close()

    print("ready", flush=True)
    start = time.monotonic()
    threads = [
        threading.Thread(target=client, args=(number, start + spec["seconds"]))
        for number in range(clients)
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    seconds = time.monotonic() - start
    print(json.dumps({"statuses": statuses, "latencies": latencies, "seconds": seconds, **faults}))


def _seconds(retry_after: str | None, default: float) -> float:
    """The seconds a `Retry-After` header asks for (`default` if none or not a number)."""
    try:
        return max(0.0, float(retry_after)) if retry_after is not None else default
    except ValueError:
        return default


def _json_error(raw: bytes) -> bool:
    """Whether a body is a JSON object with an `error` message."""
    try:
        data = json.loads(raw)
    except ValueError:
        return False
    return isinstance(data, dict) and isinstance(data.get("error"), str)


def probe_loop(port: int, seconds: float) -> dict:
    """Health checks and simulations, alternately, on one kept-alive connection to
    127.0.0.1:port for `seconds`: their `health` and `simulate` latencies (seconds) and
    `statuses` (count by route and HTTP status, e.g. "health 200")."""
    body = json.dumps(PROBE_FOUR_BAR).encode()
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=60)
    found: dict = {"health": [], "simulate": [], "statuses": {}}
    stop = time.monotonic() + seconds
    asked = 0
    try:
        while time.monotonic() < stop:
            kind = ("health", "simulate")[asked % 2]
            asked += 1
            start = time.perf_counter()
            if kind == "health":
                conn.request("GET", "/api/health")
            else:
                conn.request("POST", "/api/simulate", body, {"Content-Type": "application/json"})
            response = conn.getresponse()
            response.read()
            found[kind].append(time.perf_counter() - start)
            key = f"{kind} {response.status}"
            found["statuses"][key] = found["statuses"].get(key, 0) + 1
            time.sleep(PROBE_PAUSE_S)
    finally:
        conn.close()
    return found


def largest_simulation() -> dict:
    """A /api/simulate body at the request limits: MAX_REQUEST_JOINTS joints (a crank and
    rigid triangles on it, so it never locks) and the most steps they may take, written out to
    exactly MAX_BODY_BYTES. The routes refuse fields they do not take, so the padding is in
    the positions themselves: each coordinate is written as its exact decimal expansion and
    then zeros, the same number, and digits cost a parser more than spaces would."""
    n = MAX_REQUEST_JOINTS
    steps = MAX_REQUEST_JOINT_STEPS // n
    adjacency = np.zeros((n, n), dtype=int)
    adjacency[0, 1:] = adjacency[1:, 0] = 1
    adjacency[1, 2:] = adjacency[2:, 1] = 1
    rng = np.random.default_rng(11)
    positions = [[0.0, 0.0], [0.1, 0.0], *rng.uniform(-1, 1, (n - 2, 2)).tolist()]
    body = {
        "adjacency": adjacency.tolist(),
        "node_types": [0, 2] + [1] * (n - 2),
        "positions": positions,
        "steps": steps,
    }
    exact = [format(Decimal(value), "f") for pair in positions for value in pair]
    exact = [digits if "." in digits else digits + "." for digits in exact]

    def written(zeros: list[int]) -> str:
        coordinates = [digits + "0" * more for digits, more in zip(exact, zeros, strict=True)]
        pairs = ", ".join(
            f"[{x}, {y}]" for x, y in zip(coordinates[::2], coordinates[1::2], strict=True)
        )
        return (
            f'{{"adjacency": {json.dumps(body["adjacency"])}, '
            f'"node_types": {json.dumps(body["node_types"])}, '
            f'"positions": [{pairs}], "steps": {steps}}}'
        )

    spare = MAX_BODY_BYTES - len(written([0] * len(exact)))
    share, extra = divmod(spare, len(exact))
    text = written([share + (i < extra) for i in range(len(exact))])
    assert len(text.encode()) == MAX_BODY_BYTES
    assert json.loads(text) == body
    return {"body": body, "text": text}


def health_probes(port: int, seconds: float) -> dict:
    """Health checks one after another (PROBE_PAUSE_S apart) on one kept-alive connection to
    127.0.0.1:port for `seconds`: their `latencies` (seconds) and `statuses` (count by HTTP
    status)."""
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=60)
    found: dict = {"latencies": [], "statuses": {}}
    stop = time.monotonic() + seconds
    try:
        while time.monotonic() < stop:
            start = time.perf_counter()
            conn.request("GET", "/api/health")
            response = conn.getresponse()
            response.read()
            found["latencies"].append(time.perf_counter() - start)
            found["statuses"][response.status] = found["statuses"].get(response.status, 0) + 1
            time.sleep(PROBE_PAUSE_S)
    finally:
        conn.close()
    return found


def wait_for_port(port: int, timeout: float = 60.0) -> None:
    """Wait until `port` of 127.0.0.1 can be bound, checking every half second; ValueError
    (naming why) once `timeout` seconds have passed."""
    from links_ray.serve.app import bindable_port

    deadline = time.monotonic() + timeout
    while True:
        try:
            bindable_port("127.0.0.1", port)
            return
        except ValueError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.5)
