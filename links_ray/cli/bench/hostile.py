"""`links bench hostile`: a running `links serve` under the worst small inputs it is bounded
against, while its health is checked every HEALTH_EVERY_S.

The server is started as a user starts it (`links serve ROOT`, its own Ray), in a process of
its own. Then, in turn: each of `hostile_inputs.hostile_drawings` is posted to `/api/curve`;
clients that send a retrieval's headers and never its body hold their connections while one
more client retrieves; and a last retrieval is asked for. Reported: each answer's status,
seconds and message; health's latencies and failures throughout; and how much the server's
process tree (the command, its Ray and the replicas) grew in resident memory above what it
held when it first answered.
"""

from __future__ import annotations

import http.client
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from typing import Any

import numpy as np

from links_ray.cli import report
from links_ray.cli.bench.data import retrieval_dataset
from links_ray.cli.bench.hostile_inputs import hostile_drawings
from links_ray.cli.bench.machine import machine_info
from links_ray.serve.limits import BODY_TIMEOUT_S

#: How often health is asked for, and how long one check may take before it counts as failed.
HEALTH_EVERY_S, HEALTH_TIMEOUT_S = 0.2, 30.0
#: Clients that send only a retrieval's headers, all at once.
SILENT_CLIENTS = 10
#: How long the server may take to answer its first health check.
START_TIMEOUT_S = 600.0


def tree_rss_bytes(pid: int) -> int:
    """Resident bytes of process `pid` and every process under it (Linux /proc)."""
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as stat:
                fields = stat.read().rsplit(")", 1)[1].split()
        except OSError:  # gone meanwhile
            continue
        children.setdefault(int(fields[1]), []).append(int(entry))
    total, todo = 0, [pid]
    while todo:
        current = todo.pop()
        todo += children.get(current, [])
        try:
            with open(f"/proc/{current}/status") as status:
                for line in status:
                    if line.startswith("VmRSS:"):
                        total += int(line.split()[1]) * 1024
        except OSError:
            continue
    return total


class _Watch:
    """Health asked for every HEALTH_EVERY_S on a connection of its own, and the server's
    tree memory sampled as often, in a thread, until `stop`."""

    def __init__(self, port: int, pid: int) -> None:
        self.port, self.pid = port, pid
        self.latencies: list[float] = []
        self.failures: list[str] = []
        self.peak_rss = 0
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._done.is_set():
            began = time.perf_counter()
            try:
                status, _ = _request(self.port, "GET", "/api/health", None, HEALTH_TIMEOUT_S)
                if status != 200:
                    self.failures.append(f"HTTP {status}")
            except OSError as exc:
                self.failures.append(type(exc).__name__)
            self.latencies.append(time.perf_counter() - began)
            self.peak_rss = max(self.peak_rss, tree_rss_bytes(self.pid))
            self._done.wait(max(0.0, HEALTH_EVERY_S - (time.perf_counter() - began)))

    def stop(self) -> None:
        self._done.set()
        self._thread.join()


def _request(
    port: int, method: str, path: str, body: Any, timeout: float
) -> tuple[int, dict | None]:
    """(status, JSON answer or None) of one request on a connection of its own."""
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=timeout)
    try:
        data = None if body is None else json.dumps(body).encode()
        headers = {} if body is None else {"Content-Type": "application/json"}
        conn.request(method, path, data, headers)
        response = conn.getresponse()
        raw = response.read()
    finally:
        conn.close()
    try:
        return response.status, json.loads(raw)
    except ValueError:
        return response.status, None


def _timed(port: int, path: str, body: Any) -> dict[str, Any]:
    """One POST: its `status`, `seconds` and `error` message (None when answered 200)."""
    began = time.perf_counter()
    try:
        status, answer = _request(port, "POST", path, body, 600.0)
    except OSError as exc:
        return {"status": None, "seconds": time.perf_counter() - began, "error": repr(exc)}
    error = answer.get("error") if isinstance(answer, dict) else None
    return {"status": status, "seconds": time.perf_counter() - began, "error": error}


def _headers_only(port: int) -> dict[str, Any]:
    """A retrieval's headers (declaring 100 body bytes) and nothing more: the answer's
    status and the seconds it took."""
    began = time.perf_counter()
    with socket.create_connection(("127.0.0.1", port), timeout=600) as sock:
        sock.sendall(
            b"POST /api/retrieve HTTP/1.1\r\nHost: 127.0.0.1\r\n"
            b"Content-Type: application/json\r\nContent-Length: 100\r\n\r\n"
        )
        first = sock.recv(4096)
    status = int(first.split()[1]) if first.startswith(b"HTTP/") else None
    return {"status": status, "seconds": time.perf_counter() - began}


def _silent_clients(port: int, query: list) -> dict[str, Any]:
    """SILENT_CLIENTS clients that send headers only, and a real retrieval a second after
    they have: each one's answer."""
    answers: list[dict[str, Any]] = []
    lock = threading.Lock()

    def silent() -> None:
        answer = _headers_only(port)
        with lock:
            answers.append(answer)

    threads = [threading.Thread(target=silent) for _ in range(SILENT_CLIENTS)]
    for thread in threads:
        thread.start()
    time.sleep(1.0)
    retrieval = _timed(port, "/api/retrieve", {"points": query})
    for thread in threads:
        thread.join()
    return {"silent": sorted(answers, key=lambda a: a["seconds"]), "retrieval": retrieval}


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def _wait_until_serving(server: subprocess.Popen, port: int) -> None:
    deadline = time.monotonic() + START_TIMEOUT_S
    while time.monotonic() < deadline:
        if server.poll() is not None:
            raise RuntimeError(f"links serve exited with {server.returncode} before serving")
        try:
            if _request(port, "GET", "/api/health", None, 5.0)[0] == 200:
                return
        except OSError:
            pass
        time.sleep(0.5)
    raise RuntimeError(f"links serve did not answer within {START_TIMEOUT_S:g} s")


def bench_hostile(paths: int = 60_000, root: str | None = None) -> dict:
    """Serve `root` (default: the cached bench dataset of `paths` curated paths) with `links
    serve` and send it the hostile inputs, as the module says; the result, by part."""
    root = root or retrieval_dataset(paths)
    port = _free_port()
    env = {**os.environ, "RAY_AUTH_MODE": "disabled"}
    server = subprocess.Popen(
        [sys.executable, "-m", "links_ray", "serve", root, "--port", str(port)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env=env,
        start_new_session=True,
    )
    try:
        _wait_until_serving(server, port)
        time.sleep(2.0)  # what starting left running settles
        baseline = tree_rss_bytes(server.pid)
        query = np.stack(
            [np.cos(np.linspace(0, 2 * np.pi, 64)), np.sin(np.linspace(0, 2 * np.pi, 64))], 1
        ).tolist()
        watch = _Watch(port, server.pid)
        try:
            drawings = {
                name: {
                    "bytes": len(text.encode()),
                    **_timed(port, "/api/curve", {"name": file, "text": text}),
                }
                for name, (file, text) in hostile_drawings().items()
            }
            silent = _silent_clients(port, query)
            after = _timed(port, "/api/retrieve", {"points": query})
        finally:
            watch.stop()
    finally:
        server.send_signal(signal.SIGINT)
        try:
            server.wait(timeout=120)
        except subprocess.TimeoutExpired:
            os.killpg(server.pid, signal.SIGKILL)
            server.wait()
    latencies = np.array(watch.latencies)
    return {
        "machine": machine_info(),
        "root": root,
        "drawings": drawings,
        "silent_clients": silent,
        "retrieval_after": after,
        "health": {
            "checks": len(latencies),
            "failures": watch.failures,
            "p50_ms": float(np.percentile(latencies, 50) * 1e3),
            "max_ms": float(latencies.max() * 1e3),
        },
        "memory": {
            "baseline_bytes": baseline,
            "peak_bytes": watch.peak_rss,
            "growth_bytes": max(0, watch.peak_rss - baseline),
        },
        "body_timeout_s": BODY_TIMEOUT_S,
    }


def format_hostile(result: dict) -> str:
    """The result as tables: each hostile input's answer, then health and memory."""
    rows = [
        [
            name,
            report.count(d["bytes"]),
            d["status"],
            f"{d['seconds']:.2f}",
            (d["error"] or "")[:70],
        ]
        for name, d in result["drawings"].items()
    ]
    silent = result["silent_clients"]
    statuses = sorted({answer["status"] for answer in silent["silent"]}, key=str)
    slowest = max(answer["seconds"] for answer in silent["silent"])
    rows.append(
        [
            f"{len(silent['silent'])} headers-only clients",
            "0",
            "/".join(map(str, statuses)),
            f"{slowest:.2f}",
            f"the body timeout is {result['body_timeout_s']:g} s",
        ]
    )
    for name, answer in (
        ("a retrieval meanwhile", silent["retrieval"]),
        ("a retrieval after", result["retrieval_after"]),
    ):
        rows.append([name, "", answer["status"], f"{answer['seconds']:.2f}", answer["error"] or ""])
    health, memory = result["health"], result["memory"]
    return "\n".join(
        [
            report.table(["input", "bytes", "status", "seconds", "message"], rows),
            f"health: {health['checks']} checks every {HEALTH_EVERY_S:g} s, "
            f"{len(health['failures'])} failed, p50 {health['p50_ms']:.1f} ms, "
            f"worst {health['max_ms']:.1f} ms",
            f"server tree memory: {_gib(memory['baseline_bytes'])} serving, peak "
            f"{_gib(memory['peak_bytes'])}, grew {_gib(memory['growth_bytes'])}",
        ]
    )


def _gib(count: int) -> str:
    return f"{count / 2**30:.2f} GiB"
