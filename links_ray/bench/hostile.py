"""`links bench hostile`: a running `links serve` under the worst small inputs and clients a
single machine can send it, while its health is checked every HEALTH_EVERY_S.

The server is started as a user starts it (`links serve ROOT`, its own Ray), in a process of
its own. Then, in turn: each of `hostile_inputs.hostile_drawings` is posted to `/api/curve`;
then each attack of `hostile_clients` runs (`_attacks`: crowds of idle and trickling clients
with a real request meanwhile, heads too large, too long or endless, clients that never read,
bodies over the limits, a malformed Content-Length, a foreign Host, a synthesis over its work
bound); then a last retrieval. Reported for each: its answers' statuses, the slowest, the real
request's answer, health's checks and worst latency during it, and how much the server's
process tree (the command and its gate, its Ray and the replicas) grew in resident memory
above what it held when it first answered. Health is watched from a process of its own.
With `fuzz_seconds`, the release importer's unpickler is fuzzed last (`pickle_fuzz`).
"""

from __future__ import annotations

import http.client
import json
import multiprocessing
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

import numpy as np

from links_ray.bench import hostile_clients
from links_ray.bench.data import retrieval_dataset
from links_ray.bench.hostile_inputs import hostile_drawings
from links_ray.bench.machine import machine_info
from links_ray.cli import report
from links_ray.engine.inputs import MAX_POINTS
from links_ray.engine.synthesis.options import MAX_SYNTHESIS_ITERATIONS
from links_ray.serve.http.limits import BODY_TIMEOUT_S, HEAD_TIMEOUT_S, MAX_REQUEST_JOINT_STEPS

#: How often health is asked for, and how long one check may take before it counts as failed.
HEALTH_EVERY_S, HEALTH_TIMEOUT_S = 0.25, 30.0
#: Clients of each crowd (header-only, trickling), all at once, and how long tricklers go on.
CROWD, TRICKLE_S = 210, 25.0
#: Points of the bodies over the point limit (about 2 MB of JSON each).
OVER_POINTS = 80_000
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


def _watch_health(port: int, pid: int, ready: Any, stop: Any, results: Any) -> None:
    """In a process of its own (the attacks' client threads would otherwise hold its GIL and
    count their own waits as the server's): health asked for every HEALTH_EVERY_S and the
    server's tree memory sampled, each as (time, seconds, failure, rss), until `stop` is set;
    then the samples put on `results`."""
    samples = []
    ready.set()
    while not stop.is_set():
        began = time.perf_counter()
        failure = None
        try:
            status, _ = _request(port, "GET", "/api/health", None, HEALTH_TIMEOUT_S)
            if status != 200:
                failure = f"HTTP {status}"
        except OSError as exc:
            failure = type(exc).__name__
        seconds = time.perf_counter() - began
        samples.append((time.time(), seconds, failure, tree_rss_bytes(pid)))
        stop.wait(max(0.0, HEALTH_EVERY_S - (time.perf_counter() - began)))
    results.put(samples)


class _Watch:
    """Health and the server's memory watched from a process of its own (`_watch_health`);
    each attack's span of time marked (`mark`), so that its checks are told apart."""

    def __init__(self, port: int, pid: int) -> None:
        context = multiprocessing.get_context("spawn")
        ready, self._stop = context.Event(), context.Event()
        self._results = context.Queue()
        self._process = context.Process(
            target=_watch_health, args=(port, pid, ready, self._stop, self._results), daemon=True
        )
        self._process.start()
        ready.wait(timeout=120)
        self.spans: dict[str, tuple[float, float]] = {}
        self.samples: list[tuple[float, float, str | None, int]] = []

    def mark(self, phase: str, began: float, ended: float) -> None:
        """`phase` ran from `began` to `ended` (time.time())."""
        self.spans[phase] = (began, ended)

    def summary(self, phase: str, baseline: int) -> dict[str, Any]:
        """Health's checks during `phase`, and how far the server grew above `baseline`."""
        began, ended = self.spans[phase]
        checks = [sample for sample in self.samples if began <= sample[0] <= ended]
        latencies = [seconds for _, seconds, _, _ in checks] or [0.0]
        return {
            "checks": len(checks),
            "failures": [failure for _, _, failure, _ in checks if failure],
            "health_max_ms": max(latencies) * 1e3,
            "growth_bytes": max([0] + [rss - baseline for *_, rss in checks]),
        }

    def stop(self) -> None:
        """Stop watching; the samples are then in `samples`."""
        self._stop.set()
        self.samples = self._results.get(timeout=60)
        self._process.join(timeout=60)


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


#: A four-bar whose simulation at SIMULATION_STEPS steps is the largest answer the limits
#: allow a mechanism this size (`serve.http.limits.MAX_REQUEST_JOINT_STEPS`): what non-reading
#: clients ask for.
FOUR_BAR = {
    "adjacency": [[0, 1, 0, 0], [1, 0, 0, 1], [0, 0, 0, 1], [0, 1, 1, 0]],
    "node_types": [0, 2, 0, 1],
    "positions": [[0.5, 0.5], [0.55, 0.5], [0.8, 0.5], [0.6, 0.7]],
}
SIMULATION_STEPS = MAX_REQUEST_JOINT_STEPS // 4


def _circle(points: int) -> list[list[float]]:
    turn = np.linspace(0, 2 * np.pi, points, endpoint=False)
    return np.stack([np.cos(turn), np.sin(turn)], 1).tolist()


def _meanwhile(port: int, attack: Callable[[], list[dict]], query: list) -> dict[str, Any]:
    """`attack`'s answers, and a real retrieval asked for two seconds after it began."""
    answers: list[dict] = []
    thread = threading.Thread(target=lambda: answers.extend(attack()))
    thread.start()
    time.sleep(2.0)
    retrieval = hostile_clients.post_json(port, "/api/retrieve", {"points": query})
    thread.join()
    return {"answers": answers, "retrieval": retrieval}


def _attacks(port: int, query: list) -> dict[str, Callable[[], dict[str, Any]]]:
    """Every attack after the drawings, by name, in the order they run."""
    crowd = hostile_clients.crowd
    stroke = _circle(2 * MAX_POINTS)[:MAX_POINTS]  # half a turn, at the point limit
    simulation = json.dumps({**FOUR_BAR, "steps": SIMULATION_STEPS}).encode()
    return {
        f"{CROWD} header-only clients": lambda: _meanwhile(
            port, lambda: crowd(CROWD, lambda: hostile_clients.headers_only(port)), query
        ),
        f"{CROWD} trickling clients": lambda: _meanwhile(
            port,
            lambda: crowd(CROWD, lambda: hostile_clients.trickling(port, TRICKLE_S)),
            query,
        ),
        "8 heads of 20,000 headers": lambda: {
            "answers": crowd(8, lambda: hostile_clients.many_headers(port))
        },
        "a 6 MiB URL in 1 KiB pieces": lambda: {"answers": [hostile_clients.long_url(port)]},
        "40 heads that never end": lambda: {
            "answers": crowd(40, lambda: hostile_clients.endless_headers(port))
        },
        "150 clients not reading": lambda: {
            "answers": crowd(150, lambda: hostile_clients.not_reading(port, simulation, 15.0))
        },
        "16 bodies of 2 MB over the point limit": lambda: {
            "answers": crowd(8, lambda: hostile_clients.over_limit_body(port, OVER_POINTS))
            + crowd(8, lambda: hostile_clients.over_limit_body(port, OVER_POINTS))
        },
        "Content-Length of 5,000 digits": lambda: {
            "answers": [hostile_clients.padded_content_length(port)]
        },
        "Serve's /-/routes for a foreign Host": lambda: {
            "answers": [hostile_clients.foreign_host(port, "/-/routes")]
        },
        "synthesis, 10,000 iterations on 10,000 points": lambda: {
            "answers": [
                hostile_clients.post_json(
                    port,
                    "/api/synthesize",
                    {"points": stroke, "partial": True, "iterations": MAX_SYNTHESIS_ITERATIONS},
                )
            ],
            "retrieval": hostile_clients.post_json(
                port, "/api/synthesize", {"points": query, "seconds": 1.0}
            ),
        },
    }


def bench_hostile(paths: int = 60_000, root: str | None = None, fuzz_seconds: float = 0.0) -> dict:
    """Serve `root` (default: the cached bench dataset of `paths` curated paths) with `links
    serve` and send it the hostile inputs, as the module says; then fuzz the release importer's
    unpickler for `fuzz_seconds`, if any. The result, by attack."""
    root = root or retrieval_dataset(paths)
    port = _free_port()
    server = subprocess.Popen(
        [sys.executable, "-m", "links_ray", "serve", root, "--port", str(port)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    attacks: dict[str, dict[str, Any]] = {}
    try:
        _wait_until_serving(server, port)
        time.sleep(2.0)  # what starting left running settles
        baseline = tree_rss_bytes(server.pid)
        query = _circle(64)
        watch = _Watch(port, server.pid)
        try:
            began = time.time()
            drawings = {
                name: {
                    "bytes": len(text.encode()),
                    **_timed(port, "/api/curve", {"name": file, "text": text}),
                }
                for name, (file, text) in hostile_drawings().items()
            }
            watch.mark("drawings", began, time.time() + HEALTH_EVERY_S)
            for name, attack in _attacks(port, query).items():
                began = time.time()
                attacks[name] = attack()
                attacks[name]["seconds"] = time.time() - began
                time.sleep(3 * HEALTH_EVERY_S)  # health's checks of its end
                watch.mark(name, began, time.time())
            after = _timed(port, "/api/retrieve", {"points": query})
        finally:
            watch.stop()
        drawings_watch = watch.summary("drawings", baseline)
        for name in attacks:
            attacks[name].update(watch.summary(name, baseline))
    finally:
        server.send_signal(signal.SIGINT)
        try:
            server.wait(timeout=120)
        except subprocess.TimeoutExpired:
            os.killpg(server.pid, signal.SIGKILL)
            server.wait()
    result = {
        "machine": machine_info(),
        "root": root,
        "drawings": drawings,
        "drawings_health": drawings_watch,
        "attacks": attacks,
        "retrieval_after": after,
        "baseline_bytes": baseline,
        "body_timeout_s": BODY_TIMEOUT_S,
        "head_timeout_s": HEAD_TIMEOUT_S,
    }
    if fuzz_seconds > 0:
        from links_ray.bench.pickle_fuzz import fuzz_release_pickles

        result["pickle_fuzz"] = fuzz_release_pickles(fuzz_seconds, seed=0)
    return result


def format_hostile(result: dict) -> str:
    """The result as tables: each drawing's answer; each attack's answers, health's worst
    and the server's growth meanwhile; the unpickler's fuzzing, if run."""
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
    health = result["drawings_health"]
    lines = [
        report.table(["drawing", "bytes", "status", "seconds", "message"], rows),
        f"health meanwhile: {health['checks']} checks, {len(health['failures'])} failed, worst "
        f"{health['health_max_ms']:.0f} ms; server grew {_mib(health['growth_bytes'])}",
        "",
    ]
    rows = []
    for name, attack in result["attacks"].items():
        answers = attack["answers"]
        statuses = Counter(str(answer["status"]) for answer in answers)
        worst = max((answer["seconds"] for answer in answers), default=0.0)
        meanwhile = attack.get("retrieval")
        rows.append(
            [
                name,
                ", ".join(f"{count} x {status}" for status, count in sorted(statuses.items())),
                f"{worst:.1f}",
                ""
                if meanwhile is None
                else f"{meanwhile['status']} in {meanwhile['seconds']:.2f} s",
                f"{attack['checks'] - len(attack['failures'])}/{attack['checks']}",
                f"{attack['health_max_ms']:.0f}",
                _mib(attack["growth_bytes"]),
            ]
        )
    lines.append(
        report.table(
            [
                "attack",
                "answers",
                "slowest s",
                "a real request meanwhile, or after",
                "health 200",
                "health worst ms",
                "server grew",
            ],
            rows,
        )
    )
    messages = {
        name: next((a["error"] for a in attack["answers"] if a.get("error")), None)
        for name, attack in result["attacks"].items()
    }
    lines += [f"  {name}: {message[:110]}" for name, message in messages.items() if message]
    after = result["retrieval_after"]
    lines.append(f"a retrieval after all: {after['status']} in {after['seconds']:.2f} s")
    fuzz = result.get("pickle_fuzz")
    if fuzz is not None:
        from links_ray.bench.pickle_fuzz import format_pickle_fuzz

        lines += ["", format_pickle_fuzz(fuzz)]
    return "\n".join(lines)


def _mib(count: int) -> str:
    return f"{count / 2**20:.0f} MiB"
