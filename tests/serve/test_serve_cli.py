"""`links serve` as a user runs it, in a child process with a Ray of its own: answering from its
replica (one index, or shards), refusing in one line what cannot fit or has nothing to serve,
and stopping cleanly on Ctrl-C or SIGTERM, a request under way answered first."""

import contextlib
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from links_ray.serve.app import bindable_port
from tests.support.serving import (
    EXIT_S,
    POINTS,
    TWO_CPU_RAY,
    Client,
    command_line,
    curated_shards,
    descendants,
    links_serve,
    listening_process,
    processes_mentioning,
)


#: The Ray a `links serve` of these tests starts has 2 CPUs, whatever the machine's count
#: (Ray's own override of a node's resources): as on a 2-core laptop.
@pytest.mark.parametrize("shards", [None, 2], ids=["one-index", "2-shards"])
def test_links_serve_answers_from_its_replica_and_stops_on_ctrl_c(
    dataset: str, curated: Any, shards: int | None, tmp_path: Path
) -> None:
    """`links serve` starts its own Ray; its request gate answers on --port and passes requests
    to the replica (the gateway, with --shards), and Ctrl-C (one index) or SIGTERM (shards) stops
    all, cleanly. On its Ray of 2 CPUs, `--shards 2` does not fit at 1 CPU a partition beside the
    gateway's 1: the partitions share the CPU the gateway leaves, said in one line on stderr."""
    port = bindable_port("127.0.0.1", 0)
    sharding = () if shards is None else ("--shards", str(shards))
    errors = tmp_path / "stderr.txt"
    stop = signal.SIGINT if shards is None else signal.SIGTERM
    with links_serve(dataset, port, errors, sharding, stop) as served:
        status, health = served.get("/api/health")
        assert status == 200 and health["paths"] == len(curated)
        assert len(health.get("shards", [])) == (shards or 0)
        status, data = served.post("/api/retrieve", {"points": [[0, 0], [1, 0.5], [2, 0], [1, -1]]})
        assert status == 200 and len(data["results"]) == 3
        # The request gate, in the command's own process, answers on the port; the replica
        # answers the gate on loopback.
        assert "links_ray.cli serve" in listening_process(port)
        # The port is taken now: a second server says so in one line, before starting Ray.
        taken = subprocess.run(
            [sys.executable, "-m", "links_ray.cli", "serve", dataset, "--port", str(port)],
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert taken.returncode == 2
        assert taken.stderr.strip().endswith(f"port {port}: Address already in use")
    assert listening_process(port) == ""
    notices = [line for line in errors.read_text().splitlines() if "partition replicas" in line]
    if shards is None:
        assert notices == []
    else:
        assert notices == [
            "links-ray: this Ray has 2 CPUs and the gateway takes 1: each of the 2 partition "
            "replicas reserves 0.5 CPU (--shard-cpus to choose)"
        ]
    assert "Traceback" not in errors.read_text()


def test_links_serve_refuses_partitions_when_the_gateway_takes_every_cpu(dataset: str) -> None:
    """Where no share is left (two gateway replicas on 2 CPUs), one line and exit status 2,
    not a server waiting for CPUs forever; and the same for shards told to take 1 CPU each."""
    port = str(bindable_port("127.0.0.1", 0))
    for options, words in (
        (
            ["--replicas", "2"],
            "this Ray has 2 CPUs and the gateway takes 2 (one a replica): none "
            "is left for the partitions; serve fewer replicas, or no --shards",
        ),
        (
            ["--shard-cpus", "1"],
            "the app needs 3 CPUs (1 a gateway replica, 1 a partition replica) and this Ray has 2",
        ),
    ):
        command = [sys.executable, "-m", "links_ray.cli", "serve", dataset, "--port", port]
        refused = subprocess.run(
            [*command, "--shards", "2", *options],
            capture_output=True,
            text=True,
            timeout=300,
            env={**os.environ, **TWO_CPU_RAY},
        )
        assert refused.returncode == 2, refused.stderr[-3000:]
        last = refused.stderr.strip().splitlines()[-1]
        assert last.startswith("links serve: error: ") and words in last, refused.stderr[-3000:]


@contextlib.contextmanager
def served_by_the_cli(root: str) -> Iterator[tuple[subprocess.Popen, Client, list[str]]]:
    """`links serve root` in a process of its own, once it answers health: the process, a
    client and the lines it prints (as they come). Its Ray keeps its files in a folder of
    its own (RAY_TMPDIR), so it neither joins nor is confused with any other Ray here."""
    port = bindable_port("127.0.0.1", 0)
    ray_dir = tempfile.mkdtemp(prefix="links-serve-", dir="/tmp")  # short: Ray's socket paths
    env = {name: value for name, value in os.environ.items() if name != "RAY_ADDRESS"}
    env["RAY_TMPDIR"] = ray_dir
    server = subprocess.Popen(
        [sys.executable, "-m", "links_ray.cli", "serve", root, "--port", str(port)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
    )
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(server.stdout), daemon=True)
    reader.start()
    served = Client(port)
    try:
        deadline = time.monotonic() + 600
        while True:
            assert server.poll() is None, "".join(lines[-30:])
            assert time.monotonic() < deadline, "".join(lines[-30:])
            try:
                if served.get("/api/health")[0] == 200:
                    break
            except OSError:  # not listening yet
                pass
            time.sleep(0.25)
        yield server, served, lines
    finally:
        if server.poll() is None:
            for pid in descendants(server.pid):
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
            server.kill()
            server.wait()
        for pid in processes_mentioning(ray_dir):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        shutil.rmtree(ray_dir, ignore_errors=True)


def stopped_by_sigterm(server: subprocess.Popen, timeout: float) -> tuple[float, dict[int, str]]:
    """SIGTERM `server`: the seconds it took to exit, and those of its processes (Ray's,
    as they were when it was sent) still alive when it had."""
    below = descendants(server.pid)
    assert below, "links serve has started no processes: is its Ray its own?"
    start = time.monotonic()
    server.send_signal(signal.SIGTERM)
    try:
        server.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        pytest.fail(f"links serve still running {timeout:g} s after SIGTERM")
    seconds = time.monotonic() - start
    left = {pid: line for pid, line in below.items() if line and command_line(pid) == line}
    return seconds, left


def test_links_serve_finishes_a_request_under_way_at_sigterm(dataset: str) -> None:
    """A synthesis under way when SIGTERM comes is answered in full (200, its results), after
    the signal; then, nothing being under way, the server exits within EXIT_S, with status 0,
    saying so, and leaves none of its Ray's processes behind."""
    from links_ray.serve.deployments import SHUTDOWN_DRAIN_S

    seconds = 4.0
    with served_by_the_cli(dataset) as (server, served, lines):
        answer: dict[str, Any] = {}

        def synthesize() -> None:
            status, data = served.post("/api/synthesize", {"points": POINTS, "seconds": seconds})
            answer.update(status=status, data=data, at=time.monotonic())

        asking = threading.Thread(target=synthesize)
        asking.start()
        time.sleep(1.0)  # under way: its budget is seconds
        assert not answer, answer
        sent = time.monotonic()
        exited, left = stopped_by_sigterm(server, timeout=120)
        asking.join(timeout=60)
        text = "".join(lines)
        print(f"\nlinks serve exited {exited:.1f} s after SIGTERM, a request under way")
        assert answer["status"] == 200 and len(answer["data"]["results"]) == 3, answer
        assert answer["at"] > sent
        assert server.returncode == 0, text[-3000:]
        assert "links-ray: shutting down" in text and "Traceback" not in text, text[-3000:]
        assert exited < SHUTDOWN_DRAIN_S + EXIT_S, f"{exited:.1f} s"
        after_answer = sent + exited - answer["at"]
        assert after_answer < EXIT_S, f"exited {after_answer:.1f} s after the last answer"
        assert left == {}, left


def test_serve_cli_refuses_a_root_without_curated_paths(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """One line and exit status 2, before Ray or Serve is touched."""
    from links_ray.cli.main import main

    port = bindable_port("127.0.0.1", 0)
    assert main(["serve", str(tmp_path / "nothing"), "--port", str(port)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "no curated table" in err


def test_serve_cli_refuses_more_shards_than_the_data_splits_into(
    dataset: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """One line and exit status 2, before Ray or Serve is touched; bad numbers likewise."""
    from links_ray.cli.main import main

    port = bindable_port("127.0.0.1", 0)
    count = curated_shards(dataset)
    assert main(["serve", dataset, "--port", str(port), "--shards", str(count + 1)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0
    assert err.endswith(
        f"in {count + 1} partitions, partition {count} would have none; use a smaller --shards"
    )
    for option, value, words in (
        ("--shards", "0", "must be a positive integer, got 0"),
        ("--shard-cpus", "-1", "must be a positive number, got -1"),
        ("--shard-memory-gb", "inf", "must be a positive number, got inf"),
    ):
        with pytest.raises(SystemExit) as exited:
            main(["serve", dataset, option, value])
        assert exited.value.code == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and words in err, err
