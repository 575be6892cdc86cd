"""The links Serve app the HTTP tests talk to.

A pytest plugin (tests/conftest.py lists it): fixture `client`, the app answering on
`serve_port` (tests/support/cluster.py), serving `lean_dataset`: the lean twin of the tests'
`dataset`, whose index and points the tests compare the answers with.
"""

from __future__ import annotations

import time
from collections.abc import Iterator

import pytest

from tests.support.serving import Client, low_port

#: The one host name the `client` fixture's app answers to besides addresses and localhost.
ALLOWED_HOST = "links.test"


class _SharedApp:
    """The links app the `client` fixture hands to one test module after another: started
    when a module first asks for it, shut down when a test runs an app of its own
    (`serving.serving` calls `stop_shared_app`: the replica's port is the session's one), and
    at the session's end. One start serves every module in a row that asks, not one a module."""

    client: Client | None = None


_SHARED = _SharedApp()


def stop_shared_app() -> None:
    """Shut down the `client` fixture's app, if it runs (the next module asking starts it)."""
    if _SHARED.client is None:
        return
    from ray import serve

    _SHARED.client = None
    serve.shutdown()


def _start_shared_app(dataset: str, serve_port: int) -> Client:
    from ray import serve

    from links_ray.bench.load_clients import wait_for_port
    from links_ray.serve.app import build_app

    wait_for_port(serve_port)  # an app of a test's own may still be letting go of it
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
    except BaseException:
        serve.shutdown()
        raise
    print(f"\nServe app ready on 127.0.0.1:{serve_port} in {time.perf_counter() - start:.1f} s")
    return Client(serve_port, proxy=Client(proxy_port))


@pytest.fixture(scope="session")
def links_app(ray_cluster: str) -> Iterator[_SharedApp]:
    """The session's holder of the `client` app; shuts it down before Ray stops."""
    yield _SHARED
    stop_shared_app()


@pytest.fixture(scope="module")
def client(links_app: _SharedApp, lean_dataset: str, serve_port: int) -> Client:
    """The links app, answering on `serve_port` from its replica as under `links serve`
    (`client.proxy`: the same app through Serve's HTTP proxy). Shared by the modules that ask
    for it, one after another (`_SharedApp`); started again after a test ran its own app."""
    if links_app.client is None:
        links_app.client = _start_shared_app(lean_dataset, serve_port)
    return links_app.client
