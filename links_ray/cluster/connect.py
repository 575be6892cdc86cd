"""Joining Ray: the cluster a driver names, the one `ray job submit` sets, or a local one."""

from __future__ import annotations

import os

import ray


def connect(address: str | None = None) -> None:
    """Join the Ray cluster at `address` (or RAY_ADDRESS, as under `ray job submit`), or start
    a local one on this machine's CPUs."""
    if ray.is_initialized():
        return
    if address or os.environ.get("RAY_ADDRESS"):
        ray.init(address=address, logging_level="WARNING")
    else:
        ray.init(include_dashboard=False, logging_level="WARNING")
