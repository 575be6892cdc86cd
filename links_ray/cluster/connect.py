"""Joining Ray: the cluster a driver names, the one `ray job submit` sets, or a local one."""

from __future__ import annotations

import logging
import os

import ray

#: Where Ray 2.60 announces that a new local cluster uses token authentication.
_TOKEN_NOTICE_LOGGER = "ray._private.authentication.authentication_token_setup"


def connect(address: str | None = None) -> None:
    """Join the Ray cluster at `address` (or RAY_ADDRESS, as under `ray job submit`), or start
    a local one on this machine's CPUs; `address="local"` starts a new local one whatever
    RAY_ADDRESS says."""
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
        ray.init(address=address, include_dashboard=False, logging_level="WARNING")
    finally:
        notice.setLevel(level)
