"""`links serve --host 127.0.0.1` listens on loopback only: its own port, and every port of the
Ray it starts (GCS, raylet, object manager, workers, agents, metrics), read from /proc for the
server's whole process tree."""

from __future__ import annotations

import contextlib
import ipaddress
import os
from pathlib import Path

import pytest

from links_ray.serve.app import bindable_port
from tests.support.serving import command_line, descendants, links_serve

pytestmark = pytest.mark.ray  # `links serve` starts a Ray of its own

#: /proc/net tables, and the state of a socket that takes connections or datagrams in each.
_TABLES = {"tcp": "0A", "tcp6": "0A", "udp": "07", "udp6": "07"}


def _address(field: str) -> tuple[ipaddress.IPv4Address | ipaddress.IPv6Address, int]:
    """An address and port as /proc/net writes them: hex, each 32-bit word in host order."""
    host, port = field.split(":")
    raw = bytes.fromhex(host)
    words = b"".join(raw[i : i + 4][::-1] for i in range(0, len(raw), 4))
    return ipaddress.ip_address(words), int(port, 16)


def listening_sockets() -> dict[str, tuple[str, str, int]]:
    """Every listening TCP socket and unconnected UDP socket of this network namespace, by the
    name a process's descriptor links to (`socket:[INODE]`): (table, address, port)."""
    found = {}
    for table, state in _TABLES.items():
        for line in Path(f"/proc/net/{table}").read_text().splitlines()[1:]:
            fields = line.split()
            remote = fields[2].split(":")[1]
            if fields[3] == state and (table.startswith("tcp") or remote == "0000"):
                address, port = _address(fields[1])
                found[f"socket:[{fields[9]}]"] = (table, str(address), port)
    return found


def is_loopback(address: str) -> bool:
    """127.0.0.0/8, ::1, or an IPv4 loopback address mapped into IPv6 (::ffff:127.0.0.1)."""
    parsed = ipaddress.ip_address(address)
    mapped = getattr(parsed, "ipv4_mapped", None)
    return parsed.is_loopback or (mapped is not None and mapped.is_loopback)


def tree_listeners(pid: int) -> list[tuple[str, str, int, int, str]]:
    """(table, address, port, pid, command line) of each socket the process `pid` and every
    process below it listen on."""
    sockets = listening_sockets()
    listeners = []
    for member, command in {pid: command_line(pid), **descendants(pid)}.items():
        links = set()
        try:
            for fd in os.listdir(f"/proc/{member}/fd"):
                with contextlib.suppress(OSError):  # closed meanwhile
                    links.add(os.readlink(f"/proc/{member}/fd/{fd}"))
        except OSError:  # gone meanwhile
            continue
        for link in sorted(links & sockets.keys()):
            table, address, port = sockets[link]
            listeners.append((table, address, port, member, command))
    return listeners


def test_links_serve_on_loopback_listens_on_loopback_only(
    lean_dataset: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Every socket of the server's tree listens on loopback: its request gate on the port
    asked for, and every server of the Ray it starts, each replica's inter-deployment gRPC
    server among them (`serve.deployments.keep_replica_grpc_on_loopback`)."""
    # As a user runs it: its own new Ray, with Ray's default authentication.
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    monkeypatch.delenv("RAY_AUTH_MODE", raising=False)
    port = bindable_port("127.0.0.1", 0)
    options = ("--host", "127.0.0.1")
    with links_serve(lean_dataset, port, tmp_path / "stderr.txt", options) as served:
        assert served.get("/api/health")[0] == 200
        (server,) = [
            pid
            for pid, command in descendants(os.getpid()).items()
            if "links_ray.cli serve" in command and f"--port {port}" in command
        ]
        listeners = tree_listeners(server)
        outside = [entry for entry in listeners if not is_loopback(entry[1])]
    shown = "\n".join(f"{t} {a}:{p} {pid} {c[:80]}" for t, a, p, pid, c in listeners)
    programs = {command.split()[0].rsplit("/", 1)[-1] for *_, command in listeners}
    # Not vacuous: Ray's own servers are among them, a replica's, and the port asked for.
    assert {"gcs_server", "raylet"} <= programs, shown
    assert any("ServeReplica" in command for *_, command in listeners), shown
    assert any(p == port and a == "127.0.0.1" for _, a, p, _, _ in listeners), shown
    assert outside == [], shown


def test_serve_listens_on_ports_the_kernel_never_hands_out() -> None:
    """The ports `links serve` keeps for Serve's own listeners lie below the kernel's ephemeral
    range, where none of the sockets Ray's processes bind meanwhile can take them, and are free
    when chosen."""
    from links_ray.serve.app import QUIET_PORTS, bindable_port, ephemeral_low, quiet_port

    low = ephemeral_low()
    ports = {quiet_port("127.0.0.1") for _ in range(20)}
    assert all(max(1024, low - QUIET_PORTS) <= port < low for port in ports)
    assert len(ports) > 1  # drawn, not one fixed port two servers would share
    for port in ports:
        assert bindable_port("127.0.0.1", port) == port
