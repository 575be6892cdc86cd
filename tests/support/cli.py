"""The `links` command line run as a new process, as a user runs it."""

from __future__ import annotations

import subprocess
import sys


def links(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "links_ray.cli", *args], capture_output=True, text=True, timeout=600
    )
