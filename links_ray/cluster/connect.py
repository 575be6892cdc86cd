"""Joining Ray: the cluster a driver names, the one `ray job submit` sets, or a local one."""

from __future__ import annotations

import contextlib
import ipaddress
import logging
import os
from collections.abc import Iterator

import ray
from ray._private import ray_constants

#: Where Ray 2.60 announces that a new local cluster uses token authentication.
_TOKEN_NOTICE_LOGGER = "ray._private.authentication.authentication_token_setup"


def connect(address: str | None = None, loopback: bool = False) -> None:
    """Join the Ray cluster at `address` (or RAY_ADDRESS, as under `ray job submit`), or start
    a local one on this machine's CPUs; `address="local"` starts a new local one whatever
    RAY_ADDRESS says.

    With `loopback`, a local Ray this call starts is a new one (never a cluster `ray start`
    left running) whose every listener binds 127.0.0.1 (`loopback_ray`); a cluster it joins
    keeps the addresses it was started with."""
    if ray.is_initialized():
        return
    if address != "local" and (address or os.environ.get("RAY_ADDRESS")):
        ray.init(address=address, logging_level="WARNING")
        return
    # A new local cluster gets token authentication, and Ray says so on every run unless
    # RAY_AUTH_MODE is set: a notice with nothing to act on. Only that logger is quieted, and
    # only while this cluster starts; authentication stays on.
    notice = logging.getLogger(_TOKEN_NOTICE_LOGGER)
    level = notice.level
    notice.setLevel(logging.ERROR)
    try:
        if loopback:
            with loopback_ray():
                ray.init(address="local", include_dashboard=False, logging_level="WARNING")
        else:
            ray.init(address=address, include_dashboard=False, logging_level="WARNING")
    finally:
        notice.setLevel(level)


def is_loopback(host: str) -> bool:
    """Whether `host` (a name or an address, IPv6 with or without brackets) is this machine's
    loopback: `localhost` or an address in 127.0.0.0/8 or ::1."""
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


@contextlib.contextmanager
def loopback_ray() -> Iterator[None]:
    """While inside, a local Ray started here takes 127.0.0.1 as its node's address.

    Ray binds each of its listeners (the GCS, the raylet and its object manager, every
    worker's and actor's gRPC server, the dashboard's and the runtime-env agents, the metrics
    exporters) to loopback when, and only when, its node's address is a loopback one; on any
    other it binds all interfaces or the machine's address. `ray.init(_node_ip_address=...)`
    replaces a loopback address by the machine's own; the node's address is loopback only
    where Ray takes the machine for a single-node one (its switch for Windows and macOS,
    `RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0`, read once at import), so the switch is set here for
    the start alone. The processes the node starts are given its address, not the switch."""
    kept = ray_constants.ENABLE_RAY_CLUSTER
    ray_constants.ENABLE_RAY_CLUSTER = False
    try:
        yield
    finally:
        ray_constants.ENABLE_RAY_CLUSTER = kept
