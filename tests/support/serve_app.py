"""The links Serve app the HTTP tests talk to.

A pytest plugin (tests/conftest.py lists it): fixture `client`, the app answering on
`serve_port` (tests/support/cluster.py).
"""

from __future__ import annotations

import time
from collections.abc import Iterator

import pytest

from tests.support.serving import Client, low_port

#: The one host name the `client` fixture's app answers to besides addresses and localhost.
ALLOWED_HOST = "links.test"


@pytest.fixture(scope="module")
def client(dataset: str, serve_port: int) -> Iterator[Client]:
    """The links app for one test module, answering on `serve_port` from its replica as
    under `links serve` (`client.proxy`: the same app through Serve's HTTP proxy); Serve shut
    down after."""
    from ray import serve

    from links_ray.serve.app import build_app

    proxy_port = low_port()
    no_access_log = {"enable_access_log": False}
    start = time.perf_counter()
    serve.start(
        http_options={"host": "127.0.0.1", "port": proxy_port}, logging_config=no_access_log
    )
    try:
        # The name `allowed_host` is the one the host check's test sends besides addresses.
        app = build_app(dataset, allowed_hosts=[ALLOWED_HOST])
        serve.run(app, name="links", route_prefix="/", logging_config=no_access_log)
        print(f"\nServe app ready on 127.0.0.1:{serve_port} in {time.perf_counter() - start:.1f} s")
        yield Client(serve_port, proxy=Client(proxy_port))
    finally:
        serve.shutdown()
