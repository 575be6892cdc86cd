"""Helpers for tests of the Serve app: a small JSON client over `http.client`, running an app
(in this process, or `links serve` in a child), checks of its answers, and mechanisms and curves
the tests share."""

from __future__ import annotations

import contextlib
import http.client
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

FOUR_BAR = {
    "adjacency": [[0, 1, 0, 0], [1, 0, 0, 1], [0, 0, 0, 1], [0, 1, 1, 0]],
    "node_types": [0, 2, 0, 1],
    "positions": [[0.5, 0.5], [0.55, 0.5], [0.8, 0.5], [0.6, 0.7]],
}
#: The coupler (1-3) and rocker (2-3) are too short to span joints 1 and 2 over a full turn.
LOCKING_FOUR_BAR = {**FOUR_BAR, "positions": [[0.5, 0.5], [0.55, 0.5], [0.62, 0.5], [0.585, 0.52]]}
#: Four points of a curve: the drawing the HTTP tests send where any will do.
POINTS = [[0.0, 0.0], [1.0, 0.5], [2.0, 0.0], [3.0, 1.0]]
#: What `links serve` may take to exit after SIGTERM once no request is under way.
EXIT_S = 10.0


class Client:
    """A tiny JSON client for one server: a fresh connection per request unless given one."""

    def __init__(self, port: int, proxy: Client | None = None) -> None:
        self.port = port
        self.proxy = proxy  # the same app through another way in, if any

    def request(
        self,
        method: str,
        path: str,
        body: bytes | Any = None,
        headers: dict[str, str | None] | None = None,
        connection: http.client.HTTPConnection | None = None,
        chunked: bool = False,
    ) -> tuple[int, dict[str, str], Any]:
        """(status, headers, JSON body or text) of one request; a header given as None is
        not sent (a body's Content-Type is application/json unless given)."""
        headers = dict(headers or {})
        if body is not None and not isinstance(body, bytes):
            body = json.dumps(body).encode()
        if body is not None:
            headers.setdefault("Content-Type", "application/json")
        headers = {name: value for name, value in headers.items() if value is not None}
        conn = connection or http.client.HTTPConnection("127.0.0.1", self.port, timeout=60)
        try:
            if chunked:
                pieces = [body[i : i + 65536] for i in range(0, len(body), 65536)]
                conn.request(method, path, body=iter(pieces), headers=headers, encode_chunked=True)
            else:
                conn.request(method, path, body=body, headers=headers)
            response = conn.getresponse()
            raw = response.read()
            reply_headers = {k.lower(): v for k, v in response.getheaders()}
        finally:
            if connection is None:
                conn.close()
        if reply_headers.get("content-type", "").startswith("application/json"):
            return response.status, reply_headers, json.loads(raw)
        return response.status, reply_headers, raw.decode()

    def get(self, path: str) -> tuple[int, Any]:
        status, _, data = self.request("GET", path)
        return status, data

    def post(self, path: str, body: Any) -> tuple[int, Any]:
        status, _, data = self.request("POST", path, body)
        return status, data


def post_ok(client: Client, path: str, body: Any) -> tuple[int, Any]:
    """(status, JSON body) of a POST that must be answered 200."""
    status, data = client.post(path, body)
    assert status == 200, data
    return status, data


def check_error(status: int, headers: dict[str, str], data: Any, expected: int, words: str) -> None:
    """A refusal: status `expected` (never a 5xx) with a JSON {"error"} holding `words`."""
    assert status < 500, (status, data)
    assert status == expected, (status, data)
    assert headers.get("content-type", "").startswith("application/json")
    assert isinstance(data, dict) and set(data) == {"error"}, data
    assert words in data["error"], data["error"]


def curated_shards(root: str) -> int:
    """How many shards the curation of the dataset at `root` committed."""
    from links_ray.data.commit import committed_shards
    from links_ray.data.store import Store

    return len(committed_shards(Store.open(root), "curation"))


def low_port() -> int:
    """A free loopback port in [23000, 29999], below Linux's ephemeral range (32768 and up),
    where outgoing connections take theirs: a free port found there (port 0) was once taken
    by one before Serve's proxy could bind it, failing a test for nothing it tested."""
    import random

    from links_ray.serve.app import bindable_port

    rng = random.Random()
    for _ in range(200):
        try:
            return bindable_port("127.0.0.1", rng.randint(23_000, 29_999))
        except ValueError:
            continue
    raise RuntimeError("no free port for Serve's proxy")


@contextlib.contextmanager
def serving(app: Any, port: int) -> Iterator[Client]:
    """Run the Serve application `app`, its HTTP replica answering on `port` (Serve's direct
    ingress, as under `links serve`: the `ray_cluster` fixture set Ray up for it) and Serve's
    HTTP proxy on a port of its own (the client's `proxy`); shut Serve down after. The
    `client` fixture's app is shut down first; no other app may be running."""
    from ray import serve

    from links_ray.bench.load_clients import wait_for_port
    from tests.support.serve_app import stop_shared_app

    stop_shared_app()  # the `client` fixture's app, kept between modules, holds `port`
    wait_for_port(port)  # the last app's replica may still be letting go of it
    no_access_log = {"enable_access_log": False}
    proxy_port = low_port()
    serve.start(
        http_options={"host": "127.0.0.1", "port": proxy_port},
        logging_config=no_access_log,
    )
    try:
        start = time.perf_counter()
        serve.run(app, name="links", route_prefix="/", logging_config=no_access_log)
        print(f"\nServe app ready in {time.perf_counter() - start:.1f} s")
        yield Client(port, proxy=Client(proxy_port))
    finally:
        serve.shutdown()


def hand_drawn() -> list[np.ndarray]:
    """Curves as a user draws them: an ellipse, a figure eight, a zigzag of five clicks, an
    arc and a kidney, in screen-like coordinates."""
    t = np.linspace(0, 2 * np.pi, 120)
    kidney = np.column_stack(
        [(1 + 0.4 * np.cos(t)) * np.cos(t), 0.7 * np.sin(t) + 0.2 * np.sin(2 * t)]
    )
    return [
        np.column_stack([300 + 120 * np.cos(t), 200 + 50 * np.sin(t)]),
        np.column_stack([np.sin(t), np.sin(t) * np.cos(t)]),
        np.array([[0, 0], [1, 0.4], [2, 0.1], [1.5, -0.6], [0.3, -0.4]], dtype=float),
        np.column_stack([np.cos(t[:50]), np.sin(t[:50])]) * 40,
        kidney,
    ]


#: `links serve` starts its own Ray: of 2 CPUs, as the suite's.
TWO_CPU_RAY = {"RAY_OVERRIDE_RESOURCES": json.dumps({"CPU": 2})}


@contextlib.contextmanager
def links_serve(
    root: str, port: int, log: Path, options: tuple[str, ...] = (), stop: int = signal.SIGINT
) -> Iterator[Client]:
    """`links serve ROOT --port PORT OPTIONS` in a child process, as a user runs it (its stderr
    to `log`), until it says it is serving; then the signal `stop` (Ctrl-C by default), which
    must stop it cleanly, saying so."""
    command = [sys.executable, "-m", "links_ray.cli", "serve", root, "--port", str(port)]
    with log.open("w") as stderr:
        server = subprocess.Popen(
            [*command, *options],
            stdout=subprocess.PIPE,
            stderr=stderr,
            text=True,
            env={**os.environ, **TWO_CPU_RAY},
        )
    try:
        lines = []
        for line in server.stdout:  # until it says it is serving (or exits)
            lines.append(line)
            if "links-ray: serving" in line:
                break
        said = "".join(lines[-20:]) + log.read_text()[-3000:]
        assert lines and f"http://127.0.0.1:{port}/" in lines[-1], said
        yield Client(port)
        server.send_signal(stop)
        rest, _ = server.communicate(timeout=120)
        assert server.returncode == 0, rest
        assert "links-ray: shutting down" in rest and "Traceback" not in rest, rest
    finally:
        if server.poll() is None:
            server.kill()
            server.wait()


def retrieved(client: Client, query: np.ndarray, k: int) -> list[dict]:
    """The results of a retrieval that must succeed."""
    status, data = client.post("/api/retrieve", {"points": np.asarray(query).tolist(), "k": k})
    assert status == 200, data
    return data["results"]


def as_served(results: list[dict]) -> list[dict]:
    """Results as they come back over HTTP, rendered as the routes render them (their arrays
    as lists; JSON round-trips floats exactly)."""
    from links_ray.serve.http.responses import render_json

    return json.loads(render_json(results))


def listening_process(port: int) -> str:
    """The command line of the process listening on TCP port `port` of 127.0.0.1 ('' if none),
    from /proc: which process answers, not only that something does."""
    inodes = set()
    for line in Path("/proc/net/tcp").read_text().splitlines()[1:]:
        fields = line.split()
        if fields[1] == f"0100007F:{port:04X}" and fields[3] == "0A":  # LISTEN
            inodes.add(f"socket:[{fields[9]}]")
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            fds = os.listdir(f"/proc/{pid}/fd")
            if any(os.readlink(f"/proc/{pid}/fd/{fd}") in inodes for fd in fds):
                return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
        except OSError:  # gone, or not ours to read
            continue
    return ""


def descendants(pid: int) -> dict[int, str]:
    """The processes below `pid` (children, theirs, ...) and their command lines, from /proc."""
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                # The parent is the 2nd field after the command, which is in parentheses.
                parent = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError):
                continue
            children.setdefault(parent, []).append(int(entry.name))
    found: dict[int, str] = {}
    frontier = [pid]
    while frontier:
        for child in children.get(frontier.pop(), []):
            found[child] = command_line(child)
            frontier.append(child)
    return found


def command_line(pid: int) -> str:
    """The command line of a live process (not a zombie), else ''."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        if state == "Z":
            return ""
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode().strip()
    except (OSError, IndexError):
        return ""


def processes_mentioning(text: str) -> dict[int, str]:
    """Live processes whose command line holds `text`."""
    found = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            line = command_line(int(entry.name))
            if text in line:
                found[int(entry.name)] = line
    return found
