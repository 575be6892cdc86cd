"""A part's import held in its actor until the test kills that actor, for the fault tests of
`links import-release` on Ray (tests/release/test_release_import_ray.py).

`held_work` is the import's own work (`release.import_shards.import_part`), except that the
first actor to take shard `hold` writes its pid to `pid_file` and waits there: the test kills
that process, mid-shard, and the shard is redone by another actor, which finds the file and
goes on. Ray's actors load this module as they unpickle the work, so it lives where they can
import it.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from pathlib import Path

from links_ray.data.store import Store
from links_ray.release.import_shards import ImportOptions, ShardPart, import_part

#: How long the held actor waits to be killed: far longer than the test takes to kill it.
HOLD_S = 120.0


def held_work(
    store: Store,
    part: ShardPart,
    fence: Callable[[], None],
    options: ImportOptions,
    hold: int,
    pid_file: str,
) -> dict:
    """`import_part`, held in the first actor that takes shard `hold` (the module docstring)."""
    if part.shard_id == hold:
        try:
            with open(pid_file, "x") as out:  # the first attempt only
                out.write(str(os.getpid()))
        except FileExistsError:
            pass
        else:
            deadline = time.monotonic() + HOLD_S
            while time.monotonic() < deadline:
                time.sleep(0.05)
            raise RuntimeError(f"shard {hold}'s actor was not killed within {HOLD_S:.0f} s")
    return import_part(store, part, fence, options=options)


def wait_for_pid(pid_file: Path, timeout_s: float = 120.0) -> int:
    """The pid the held actor wrote, once it has."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        text = pid_file.read_text() if pid_file.exists() else ""
        if text:
            return int(text)
        time.sleep(0.02)
    raise TimeoutError(f"no actor took the held shard within {timeout_s:.0f} s")
