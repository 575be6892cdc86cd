"""Who answers, and to which names: the replica answers HTTP on its own port (direct ingress),
Serve's proxy on its own, and a Host the app was not told of is refused 400 (the `client`
fixture's app); the allowed host names the app's builder takes."""

import pytest

from tests.support.serving import FOUR_BAR, Client, listening_process


def test_the_replica_answers_http_itself(client: Client) -> None:
    """Direct ingress: the replica owns the port; Serve's proxy answers on its own port too."""
    assert "ServeReplica:links:LinksApi" in listening_process(client.port)
    assert client.proxy is not None
    assert "ProxyActor" in listening_process(client.proxy.port)
    assert client.proxy.get("/api/health") == client.get("/api/health")


def test_allowed_hosts_args(dataset: str) -> None:
    from links_ray.serve.app import app_builder, build_app

    app_builder({"root": dataset, "allowed_hosts": ["links.example.org", "*"]})
    for bad, message in (
        ("links.example.org", "allowed hosts must be a list of host names, got str"),
        (["links example"], "'links example' is not a host name"),
        ([""], "'' is not a host name"),
        ([7], "7 is not a host name"),
        (["a" * 254], "is not a host name"),
    ):
        with pytest.raises(ValueError, match=f"args.allowed_hosts: .*{message}"):
            app_builder({"root": dataset, "allowed_hosts": bad})
        with pytest.raises(ValueError, match=message):
            build_app(dataset, allowed_hosts=bad)


def test_a_host_it_was_not_told_of_gets_400(client: Client) -> None:
    """A request for a DNS name the server was not given (how a web page reaches a loopback
    server through a name it controls) is refused 400 before its body is read, through the
    replica and through Serve's proxy; addresses, localhost and the allowed name are answered."""
    from tests.support.serve_app import ALLOWED_HOST

    port = client.port
    for way in (client, client.proxy):
        for host in ("attacker.example", f"attacker.example:{port}", "127.0.0.1.nip.io", "local"):
            status, _, data = way.request("POST", "/api/simulate", FOUR_BAR, {"Host": host})
            assert status == 400, (host, status, data)
            assert data["error"].startswith(f"Host {host!r}: this server answers its addresses")
            assert "--allow-host" in data["error"]
        for host in (
            f"127.0.0.1:{port}",
            "127.0.0.1",
            f"[::1]:{port}",
            f"localhost:{port}",
            "studio.localhost",
            f"{ALLOWED_HOST}:{port}",
            ALLOWED_HOST.upper(),
        ):
            status, _, data = way.request("POST", "/api/simulate", FOUR_BAR, {"Host": host})
            assert status == 200, (host, status, data)
    # HTTP/1.0 lets a request leave its host unsaid; one without is refused as well.
    import socket

    with socket.create_connection(("127.0.0.1", port), timeout=60) as sock:
        sock.sendall(b"GET /api/health HTTP/1.0\r\n\r\n")
        answer = b""
        while chunk := sock.recv(65536):
            answer += chunk
    assert answer.startswith(b"HTTP/1.1 400"), answer[:200]
    assert b"no Host header" in answer
