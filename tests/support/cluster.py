"""The tests' Ray: one local cluster of two CPUs for the session, reaching the S3 server.

A pytest plugin (tests/conftest.py lists it): fixtures `serve_port` and `ray_cluster`; a test
using `ray_cluster`, or a fixture that depends on it, is marked `ray`.
"""

from __future__ import annotations

import os
import random
from collections.abc import Iterator

import pytest

from tests.support.s3 import S3Server

#: Where `serve_port` is drawn: below Linux's ephemeral range (32768+), where every outgoing
#: connection takes its local port (Ray opens many whenever an app starts, and one can take
#: the port while no app holds it, between two apps), and clear of weed's ports (P and
#: P + 10000 for P in [_PORT_LOW, _PORT_HIGH]).
_SERVE_PORT_LOW, _SERVE_PORT_HIGH = 23_000, 29_999


@pytest.fixture(scope="session")
def serve_port() -> int:
    """The loopback port the Serve app's replica answers HTTP on, as under `links serve`.

    Fixed for the session (Ray's direct ingress takes it when Ray starts), and used by one app
    after another."""
    from links_ray.serve.app import bindable_port

    rng = random.Random()
    for _ in range(200):
        try:
            return bindable_port("127.0.0.1", rng.randint(_SERVE_PORT_LOW, _SERVE_PORT_HIGH))
        except ValueError:
            continue
    raise RuntimeError("no free port for the Serve app")


@pytest.fixture(scope="session")
def ray_cluster(s3_server: S3Server, serve_port: int) -> Iterator[str]:
    """A real local Ray cluster with two CPUs; yields its address for other drivers.

    Ray's workers take the environment of the process that starts the cluster, so the S3
    server's standard AWS variables are set first: actors then reach it like any store. So is
    Serve's direct ingress on `serve_port`, as `links serve` sets it.
    """
    import ray

    from links_ray.serve.app import direct_ingress_env

    os.environ.update(
        {
            "RAY_AUTH_MODE": "disabled",
            "AWS_ENDPOINT_URL": s3_server.endpoint,
            "AWS_ACCESS_KEY_ID": s3_server.access_key,
            "AWS_SECRET_ACCESS_KEY": s3_server.secret_key,
            "AWS_REGION": s3_server.region,
            "AWS_EC2_METADATA_DISABLED": "true",
            **direct_ingress_env(serve_port),
        }
    )
    ray.init(num_cpus=2, include_dashboard=False, logging_level="WARNING")
    yield ray.get_runtime_context().gcs_address
    ray.shutdown()
