"""The machine a benchmark ran on, as every benchmark reports it."""

from __future__ import annotations

import os
import platform
from importlib import metadata


def machine_info() -> dict:
    """The machine a benchmark ran on: CPU count, processor, Python and numba versions."""
    return {
        "cpus": os.cpu_count(),
        "processor": platform.processor() or platform.machine(),
        "python": platform.python_version(),
        "numba": metadata.version("numba"),
    }
