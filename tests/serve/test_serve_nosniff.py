"""Every answer of the app says `X-Content-Type-Options: nosniff`, once: JSON answers, refusals
(bad input, a foreign Host, no such route) and the studio's files, over real HTTP."""

from __future__ import annotations

import http.client

from tests.support.serving import FOUR_BAR, Client


def raw_headers(
    port: int, method: str, path: str, body: bytes | None = None, host: str | None = None
) -> tuple[int, str, list[str]]:
    """(status, Content-Type, every value sent for X-Content-Type-Options) of one request."""
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=60)
    try:
        conn.putrequest(method, path, skip_host=host is not None)
        if host is not None:
            conn.putheader("Host", host)
        if body is not None:
            conn.putheader("Content-Type", "application/json")
            conn.putheader("Content-Length", str(len(body)))
        conn.endheaders(body)
        response = conn.getresponse()
        response.read()
        sniffing = [v for k, v in response.getheaders() if k.lower() == "x-content-type-options"]
        return response.status, response.getheader("Content-Type", ""), sniffing
    finally:
        conn.close()


def test_every_answer_says_nosniff_once(client: Client) -> None:
    import json

    four_bar = json.dumps({**FOUR_BAR, "steps": 20}).encode()
    cases = {
        "health": ("GET", "/api/health", None, None, 200),
        "a simulation": ("POST", "/api/simulate", four_bar, None, 200),
        "bad JSON": ("POST", "/api/retrieve", b"{not json", None, 400),
        "a foreign Host": ("POST", "/api/simulate", four_bar, "evil.example", 400),
        "no such route": ("GET", "/api/nope", None, None, 404),
        "the studio": ("GET", "/", None, None, 200),
    }
    for way in (client, client.proxy):
        assert way is not None
        for name, (method, path, body, host, expected) in cases.items():
            status, kind, sniffing = raw_headers(way.port, method, path, body, host)
            assert status == expected, (name, status)
            assert sniffing == ["nosniff"], (name, sniffing)
            if name != "the studio":
                assert kind.startswith("application/json"), (name, kind)
