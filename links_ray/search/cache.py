"""The on-disk cache of retrieval indexes, and the lease that lets one process build each.

The arrays of each part of an index are saved under ``ROOT/_links/index/part-P-of-N/`` in a
build folder of their own; ``current.json`` names the build in use (the commit) and what it
was made from: the curated shards' fingerprint, the row count, the format and the build
settings. A saved index is reused while all of those still hold. Of several processes opening
one part at once, the one holding the part's index lease builds; the others wait for its save.

No Ray.
"""

from __future__ import annotations

import io
import json
import uuid

import numpy as np

from links_ray.data.lease import Lease, LeaseHeld, index_lease_name
from links_ray.data.path_draw import PathDraw
from links_ray.data.store import META, Store, StoreError
from links_ray.search import kernels
from links_ray.search.build import DIMENSIONS, MAX_LISTS, ROWS_PER_LIST, SAMPLE, Basis
from links_ray.search.mechanisms import MechanismBank

INDEX_FOLDER = f"{META}/index"
#: How often a process waiting for another's index build looks for the saved index (seconds).
CACHE_POLL_S = 1.0
#: How long `RetrievalIndex.open` waits for another process's build of the same part by
#: default (seconds): well past the longest build measured (docs/benchmarks.md).
BUILD_WAIT_S = 1800.0
INDEX_FORMAT = 7  # 7: no codes; the scan reads sketches
#: The arrays a saved index holds: one entry per row, and the rest, besides the basis.
ROW_ARRAYS = (
    "mechanism_row",
    "joint",
    "sketches",
    "transmission",
    "file_row",
)
SAVED_ARRAYS = (*ROW_ARRAYS, "list_start", "centroids")
BASIS_ARRAYS = ("mean", "components")
#: What a saved index was built with: one built otherwise is rebuilt.
BUILD_SETTINGS = {
    "dimensions": DIMENSIONS,
    "sketch_points": kernels.SKETCH_POINTS,
    "sample": SAMPLE,
    "rows_per_list": ROWS_PER_LIST,
    "max_lists": MAX_LISTS,
}


def check_part(part: int, parts: int) -> None:
    """ValueError unless 0 <= part < parts (both integers)."""
    for name, value in (("part", part), ("parts", parts)):
        if isinstance(value, bool) or not isinstance(value, int | np.integer):
            raise ValueError(f"{name} must be an integer, got {value!r}")
    if parts < 1 or not 0 <= part < parts:
        raise ValueError(f"part must be in 0..parts-1 with parts >= 1, got part {part} of {parts}")


def cache_folder(part: int, parts: int, draw: PathDraw | None = None) -> str:
    """Where part `part` of an index split in `parts` keeps its arrays (an index of a draw of
    the curated paths, in a folder named after the draw)."""
    place = INDEX_FOLDER if draw is None else f"{INDEX_FOLDER}/{draw.name}"
    return f"{place}/part-{part}-of-{parts}"


def shards_fingerprint(markers: dict[int, dict]) -> str:
    """A fingerprint of curated shards' commit markers: it changes whenever curated shards are
    added or redone."""
    rows = sorted(
        (shard, m["rows"].get("curated", 0), m.get("attempt")) for shard, m in markers.items()
    )
    return json.dumps(rows)


def save_index(store: Store, folder: str, fingerprint: str, arrays: dict, build_s: float) -> None:
    """Save an index's arrays (`build.build_arrays`) in a new build folder, then point
    `current.json` at it (the commit), then delete older builds. Raises OSError if the store
    takes no writes."""
    build = uuid.uuid4().hex[:12]
    named = {name: arrays[name] for name in SAVED_ARRAYS}
    named.update({f"basis_{name}": getattr(arrays["basis"], name) for name in BASIS_ARRAYS})
    named.update({f"bank_{name}": array for name, array in arrays["bank"].arrays().items()})
    for name, array in named.items():
        buffer = io.BytesIO()
        np.save(buffer, array)
        store.write_bytes(f"{folder}/{build}/{name}.npy", buffer.getbuffer())
    current = {
        "format": INDEX_FORMAT,
        "fingerprint": fingerprint,
        "build": build,
        "rows": len(arrays["joint"]),
        "steps": arrays["steps"],
        "settings": BUILD_SETTINGS,
        "build_s": build_s,
        "arrays": sorted(named),
    }
    store.write_json(f"{folder}/current.json", current)
    older = {relative[len(folder) + 1 :].split("/")[0] for relative in store.list_files(folder)}
    for name in older - {build, "current.json"}:
        store.delete_folder(f"{folder}/{name}")


def load_index(store: Store, folder: str, fingerprint: str, rows: int) -> dict | None:
    """The saved index's arrays (as `build.build_arrays` makes them) if it holds this
    fingerprint's `rows` paths, else None (also for one that is missing, damaged or of
    another format or build settings)."""
    current = store.read_json(f"{folder}/current.json")
    if (
        current is None
        or current.get("format") != INDEX_FORMAT
        or current.get("fingerprint") != fingerprint
        or current.get("rows") != rows
        or current.get("settings") != BUILD_SETTINGS
    ):
        return None
    named = {}
    try:
        for name in current["arrays"]:
            data = store.read_bytes(f"{folder}/{current['build']}/{name}.npy")
            if data is None:
                return None
            named[name] = np.load(io.BytesIO(data), allow_pickle=False)
        basis = Basis(*(named.pop(f"basis_{name}") for name in BASIS_ARRAYS))
        bank = MechanismBank(
            **{name[5:]: named.pop(name) for name in list(named) if name.startswith("bank_")}
        )
        saved = {name: named.pop(name) for name in SAVED_ARRAYS}
    except (OSError, ValueError, KeyError, TypeError, EOFError):
        return None
    if named or any(len(saved[name]) != rows for name in ROW_ARRAYS):
        return None
    return {**saved, "steps": int(current["steps"]), "basis": basis, "bank": bank}


def build_lease(
    store: Store,
    part: int,
    parts: int,
    folder: str,
    fingerprint: str,
    rows: int,
    rebuild: bool,
    wait_s: float,
) -> Lease | dict | None:
    """The part's index lease (this process builds), the index another process saved in
    `folder` while this one waited (not with `rebuild`), or None (build without the lease: the
    root takes no writes). Raises `LeaseHeld` after `wait_s` seconds, naming the holder. The
    full index's part and any draw's share a lease: their builds take turns."""

    def saved() -> dict | None:
        return None if rebuild else load_index(store, folder, fingerprint, rows)

    try:
        got = Lease.acquire_waiting(
            store,
            index_lease_name(part, parts),
            "the retrieval index build",
            wait_s,
            done=saved,
            poll_s=CACHE_POLL_S,
        )
    except LeaseHeld:
        raise
    except (OSError, StoreError):
        return None
    if isinstance(got, dict):
        return got
    got.keep_renewed()  # a large build takes minutes
    # The index may have been saved between our look and our lease.
    found = saved()
    if found is None:
        return got
    got.release()
    return found
