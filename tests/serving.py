"""Helpers for tests of the Serve app: a small JSON client over `http.client`, and
mechanisms the tests share."""

from __future__ import annotations

import http.client
import json
from typing import Any

FOUR_BAR = {
    "adjacency": [[0, 1, 0, 0], [1, 0, 0, 1], [0, 0, 0, 1], [0, 1, 1, 0]],
    "node_types": [0, 2, 0, 1],
    "positions": [[0.5, 0.5], [0.55, 0.5], [0.8, 0.5], [0.6, 0.7]],
}
#: The coupler (1-3) and rocker (2-3) are too short to span joints 1 and 2 over a full turn.
LOCKING_FOUR_BAR = {**FOUR_BAR, "positions": [[0.5, 0.5], [0.55, 0.5], [0.62, 0.5], [0.585, 0.52]]}


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
        headers: dict[str, str] | None = None,
        connection: http.client.HTTPConnection | None = None,
        chunked: bool = False,
    ) -> tuple[int, dict[str, str], Any]:
        """(status, headers, JSON body or text) of one request."""
        headers = dict(headers or {})
        if body is not None and not isinstance(body, bytes):
            body = json.dumps(body).encode()
        if body is not None:
            headers.setdefault("Content-Type", "application/json")
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
