"""What the commands print is the project's own: on a clean run, `links generate`, `curate`,
`retrieve`, `synthesize` and `serve`'s start-up print no line in one of Ray's log formats.

Each command runs as a user runs it: a process of its own that starts its own Ray (2 CPUs, its
files in a folder of its own, so that it joins no other Ray on the machine), on a small
dataset this module generates. Ray's warnings keep their level: a run that loses a node or
spills objects still says so, in Ray's format, which is why the formats are recognized here
and `test_ray_formats_are_recognized` holds the pattern to lines Ray prints.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from collections.abc import Iterator

import numpy as np
import pytest

from links_ray.serve.app import bindable_port
from tests.support.serving import TWO_CPU_RAY

#: Ray's own log lines, by where they come from. Colour codes are taken out first.
RAY_LOG_FORMATS = {
    # The core (C++): `[date time,ms level pid tid] file.cc:line: ...`, anywhere in a line (a
    # progress bar may come before it).
    "core": r"\[\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3} [DIWEF] \d+ \d+\] [\w./-]+\.(?:cc|h):\d+:",
    # Ray's Python loggers: `date time,ms LEVEL file.py:line -- ...`.
    "python": (
        r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3}\s+(?:DEBUG|INFO|WARNING|ERROR|CRITICAL)"
        r" [\w.-]+\.py:\d+ -- "
    ),
    # Ray Serve's components: `LEVEL date time,ms component id -- ...`.
    "serve": (
        r"^(?:DEBUG|INFO|WARNING|ERROR|CRITICAL) \d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3} \S+ \S+ -- "
    ),
    # What a worker or an actor printed, forwarded to the driver: `(Name pid=N[, ip=A]) ...`,
    # and the messages of Ray's own processes: `(raylet) ...`.
    "forwarded": (
        r"^\((?:[^\n]*?\bpid=\d+(?:, ip=[\w.:]+)?"
        r"|raylet|gcs_server|autoscaler|monitor|dashboard\w*)[^)\n]*\)"
    ),
}
RAY_LOG_LINE = re.compile("|".join(f"(?:{pattern})" for pattern in RAY_LOG_FORMATS.values()))
ANSI_COLOUR = re.compile(r"\x1b\[[0-9;]*m")

#: Mechanisms of the dataset the commands run on (four shards of five).
MECHANISMS = 20
#: Seconds any one command may take, on a loaded machine, its kernels compiled on first use.
COMMAND_TIMEOUT_S = 900
#: Warnings of Ray's about real conditions a loaded machine can bring about on any run: they
#: must show, and may.
REAL_WARNINGS = (
    "replicas that have taken more than 30s to initialize",
    "This may be caused by a slow __init__ or reconfigure method.",
    "Failed to get queue length from Replica",
    "Proxy actor readiness check for proxy on",
    "Proxy actor reported not ready on node",
    "failed the health check 3 times in a row",
)


def ray_lines(output: str) -> list[str]:
    """The lines of `output` in one of Ray's log formats."""
    lines = re.split(r"[\r\n]+", ANSI_COLOUR.sub("", output))
    return [line for line in lines if RAY_LOG_LINE.search(line)]


def unexpected_ray_lines(output: str) -> list[str]:
    """`ray_lines` but for the REAL_WARNINGS."""
    return [line for line in ray_lines(output) if not any(real in line for real in REAL_WARNINGS)]


@pytest.mark.parametrize(
    "line",
    [
        # As `links curate` printed it while Ray Data's curator actors could restart.
        "[2026-11-25 22:36:41,510 E 15161 15161] core_worker.cc:2465: Actor with class name: "
        "'MapWorker(MapBatches(ShardCurator))' and ID: '6efffbdc76f1921c61aec44e01000000' has "
        "constructor arguments in the object store and max_restarts > 0. If the arguments in "
        "the object store go out of scope or are lost, the actor restart will fail.",
        "2026-11-25 22:30:56,215\tINFO worker.py:2004 -- Started a local Ray instance.",
        "2026-11-25 22:30:56,215\tWARNING worker.py:2114 -- The node with node id: 4f3c and "
        "address: 10.0.0.2 and node name: 10.0.0.2 has been marked dead",
        "\x1b[36m(ServeController pid=5771)\x1b[0m INFO 2026-11-25 22:41:43,999 controller 5771 "
        "-- Direct ingress is enabled in ServeController.",
        'INFO 2026-11-25 22:41:48,368 serve 4871 -- Started Serve in namespace "serve".',
        "(MapWorker(MapBatches(ShardCurator)) pid=6395, ip=10.0.0.2) printed by a curator",
        "\x1b[33m(raylet)\x1b[0m Spilled 2048 MiB, 3 objects, write throughput 512 MiB/s.",
        "Running 0: 0.00 row [00:00, ? row/s][2026-11-25 22:36:41,510 W 15161 15161] "
        "object_manager.cc:120: a warning after a progress bar",
    ],
    ids=[
        "core",
        "python",
        "python-node-dead",
        "serve-forwarded",
        "serve-driver",
        "actor-print",
        "raylet-spill",
        "core-after-a-bar",
    ],
)
def test_ray_formats_are_recognized(line: str) -> None:
    assert ray_lines(f"ours\n{line}\nours again\n") == [ANSI_COLOUR.sub("", line)]


def test_the_projects_own_lines_are_not_taken_for_rays() -> None:
    ours = [
        "links curate: compiling the path kernels (first run only, about 5 s)...",
        "5/20 mechanisms (25%), 0 mechanisms/s, 40 s left",
        "(--json for everything; the full summary is also in /data/_links/summary.json)",
        "links-ray: serving /data at http://127.0.0.1:8000/ (API under /api)",
        "rank  chamfer  retrieved  joints  joint  from path  crank deg",
        "links curate: error: curation stopped: the store refused shard 3: No space left",
    ]
    assert ray_lines("\n".join(ours)) == []


def _environment(ray_dir: str) -> dict[str, str]:
    """A user's environment, but for a Ray of 2 CPUs whose files are under `ray_dir`."""
    env = {name: value for name, value in os.environ.items() if name != "RAY_ADDRESS"}
    return {**env, **TWO_CPU_RAY, "RAY_TMPDIR": ray_dir}


def _links(env: dict[str, str], *args: str) -> str:
    """Run `links ARGS`; its stdout and stderr together, once it has succeeded."""
    done = subprocess.run(
        [sys.executable, "-m", "links_ray.cli", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
        timeout=COMMAND_TIMEOUT_S,
    )
    assert done.returncode == 0, done.stdout[-3000:]
    return done.stdout


@pytest.fixture(scope="module")
def ran(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, str]]:
    """The output of each command on a clean run, the dataset's root under "root"."""
    folder = tmp_path_factory.mktemp("output")
    ray_dir = tempfile.mkdtemp(prefix="links-out-", dir="/tmp")  # short: Ray's socket paths
    env = _environment(ray_dir)
    root = str(folder / "links")
    angle = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    drawing = folder / "drawing.json"
    drawing.write_text(json.dumps(np.column_stack([np.cos(angle), 0.5 * np.sin(angle)]).tolist()))
    outputs = {"root": root, "env_ray_dir": ray_dir}
    outputs["generate"] = _links(env, "generate", "--out", root, "--mechanisms", str(MECHANISMS))
    outputs["curate"] = _links(env, "curate", root)
    outputs["retrieve"] = _links(env, "retrieve", root, "--points", str(drawing), "--table")
    outputs["synthesize"] = _links(
        env, "synthesize", root, "--points", str(drawing), "--iterations", "20"
    )
    yield outputs
    shutil.rmtree(ray_dir, ignore_errors=True)  # every command's Ray has stopped


@pytest.mark.ray  # `ran` runs the commands on a Ray of their own
@pytest.mark.parametrize(
    ("command", "says"),
    [
        ("generate", f"{MECHANISMS} mechanisms (complete)"),
        ("curate", "shards curated by this run"),
        ("retrieve", "3 paths in"),
        ("synthesize", "3 mechanisms in"),
    ],
)
def test_a_command_prints_no_line_of_rays(ran: dict[str, str], command: str, says: str) -> None:
    assert says in ran[command], ran[command][-3000:]
    assert unexpected_ray_lines(ran[command]) == []


@pytest.mark.ray
def test_serve_starts_up_printing_no_line_of_rays(ran: dict[str, str]) -> None:
    """`links serve` until its replica answers health, then SIGTERM: it stops cleanly."""
    port = bindable_port("127.0.0.1", 0)
    server = subprocess.Popen(
        [sys.executable, "-m", "links_ray.cli", "serve", ran["root"], "--port", str(port)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=_environment(ran["env_ray_dir"]),
    )
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(server.stdout), daemon=True)
    reader.start()
    try:
        deadline = time.monotonic() + COMMAND_TIMEOUT_S
        while True:
            assert server.poll() is None, "".join(lines[-30:])
            assert time.monotonic() < deadline, "".join(lines[-30:])
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/health") as answer:
                    if answer.status == 200:
                        break
            except OSError:  # not listening yet
                time.sleep(1.0)
        while not any("links-ray: serving" in line for line in lines):  # said once Serve is up
            assert server.poll() is None and time.monotonic() < deadline, "".join(lines[-30:])
            time.sleep(0.5)
        time.sleep(2.0)  # what start-up prints late (forwarded from Ray's workers) comes too
        start_up = "".join(lines)
        server.send_signal(signal.SIGTERM)
        assert server.wait(timeout=COMMAND_TIMEOUT_S) == 0, "".join(lines[-30:])
    finally:
        if server.poll() is None:
            server.kill()
            server.wait()
    assert f"at http://127.0.0.1:{port}/" in start_up, start_up[-3000:]
    assert unexpected_ray_lines(start_up) == []
